"""Several robots in one map: feature-space compatibility and re-projection, per-robot
``world_from_robot`` transforms, per-robot rates, status and the bounds on per-robot state.

Pure computation and bookkeeping (no Zenoh, no threads of its own); the mapper's ingest,
map and query jobs call it.

**Feature spaces.** Each edge may fit its own PCA basis, so robots of one fleet usually
send features in different *compressed* spaces of the same *uncompressed* encoder space.
The map keeps one space (the first robot's, or the restored snapshot's). A robot is
*compatible* with the map when encoder name, version, input dimension, text model and
language head (config and weights) are equal (:func:`common.feature_space.compatibility`); it is then brought
into the map's basis by the mapper — decompress with the robot's basis and mean, compress
with the map's — which, both being affine, is one small affine map per robot
(:class:`Reprojection`: ``y_map = A·y_robot + b``, ``A = V_mᵀV_r`` (k_m×k_r),
``b = V_mᵀ(m_r − m_m)``), exact up to the map basis' truncation of what the robot's basis
kept. We chose re-projection over a fleet basis handed out by the mapper because it needs
nothing from the edges (an edge that fitted online, restarted, or was configured
elsewhere still maps) and costs one ``k×k`` matrix product per feature pixel (0.1 ms for a
100×14×14 map). The score error it adds is measured in ``tests/test_fleet.py`` and
``rayfronts bench fleet`` (README "Several robots").

**Frames.** ``world_from_robot`` (a rigid 4×4) maps a robot's odometry/world frame into
the map's world frame: ``pose_map = world_from_robot · pose_robot`` before integration.

**Bounds.** A robot id costs a small :class:`RobotState`-like record plus its bounded
queue. Robots that never serve a feature space are evicted after ``no_space_evict_s``,
robots that went away after ``gone_evict_s``; at most ``max_robots`` ids are tracked
(frames of further ids are rejected, counted globally, not per id); frames held for a
robot whose space is not known yet expire after ``pending_ttl_s`` and at most
``max(pending_max_frames, queues.per_robot)`` are held over all robots (oldest first dropped).
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Union

import numpy as np
import numpy.typing as npt

from common.config import field_

if TYPE_CHECKING:
    import torch

    from common.feature_space import FeatureSpace

#: a rigid transform as configured: 16 numbers, a 4×4 nested list / array, or {xyz, rpy_deg}
TransformSpec = Union[dict, npt.ArrayLike]

log = logging.getLogger("rayfronts.mapper")


# ------------------------------------------------------------------ config
@dataclass
class FleetSection:
    """Several robots in one map (mapper config section ``fleet``)."""

    world_from_robot: dict = field_({}, "per-robot rigid transform into the map's world frame, applied to every "
                                        "pose before integration: robot id -> 16 numbers (row-major 4x4), a 4x4 "
                                        "list, or {xyz: [x, y, z], rpy_deg: [roll, pitch, yaw]}; settable at run "
                                        "time with a get on mapper/robots/<robot>/world_from_robot")
    reproject: bool = field_(True, "bring robots with the map's encoder but another PCA basis into the map's "
                                   "basis (decompress with theirs, compress with the map's); false = refuse them")
    reproject_warn_kept: float = field_(0.8, "warn (one line) when a re-projected robot's features keep less than "
                                             "this share of their variance in the map's basis (its classes may "
                                             "become unqueryable; give it the map's basis: pca.basis=map)")
    max_robots: int = field_(128, "robot ids tracked at most; frames of further ids are rejected (counted)")
    no_space_evict_s: float = field_(60.0, "forget a robot that has not served a feature space this long after "
                                           "its first frame (s)")
    gone_evict_s: float = field_(300.0, "forget a robot whose edge went away (liveliness) and sent nothing for "
                                        "this long (s); its mapped frames stay in the map")
    pending_ttl_s: float = field_(60.0, "frames held while a robot's feature space is fetched expire after "
                                        "this long (s)")
    pending_max_frames: int = field_(32, "frames held over all robots whose feature space is not known yet, at "
                                         "least queues.per_robot (one robot's queue); oldest dropped first")
    status_period_s: float = field_(1.0, "per-robot status (mapper/robots/<robot>/status) is published on every "
                                         "change of state and at most this often otherwise")
    drop_warn_s: float = field_(10.0, "warn about a robot's dropped frames at most this often (s), with the rate")
    rate_window_s: float = field_(5.0, "window (s) of the per-robot received / mapped / dropped rates")


# ------------------------------------------------------------- feature spaces
class Reprojection:
    """Affine map from a robot's stored features to the map's: ``y_m = A·y_r + b``.

    With ``x̂ = V_r·y_r + m_r`` (the robot's decompression) and ``y_m = V_mᵀ(x̂ − m_m)``
    (the map's compression): ``A = V_mᵀV_r``, ``b = V_mᵀ(m_r − m_m)``; a space without
    PCA has ``V = I``, ``m = 0``. Computed in float64, applied in float32."""

    def __init__(self, map_fs, robot_fs):
        def vm(fs):
            if fs.pca is None:
                return np.eye(fs.in_dim), np.zeros(fs.in_dim)
            return fs.pca.basis.astype(np.float64), fs.pca.mean.astype(np.float64)

        vr, mr = vm(robot_fs)
        vmap, mmap = vm(map_fs)
        self.robot_id, self.map_id = robot_fs.id, map_fs.id
        self.A = (vmap.T @ vr).astype(np.float32)                 # (k_m, k_r)
        self.b = (vmap.T @ (mr - mmap)).astype(np.float32)        # (k_m,)
        self.in_dim, self.out_dim = self.A.shape[1], self.A.shape[0]
        # share of the robot's compressed variance inside the map basis' span (1 = nothing lost),
        # weighted by the robot basis' explained variance (uniform without one)
        w = robot_fs.pca.explained_variance if robot_fs.pca is not None else None
        w = np.ones(self.in_dim) if w is None or not np.sum(w) > 0 else np.asarray(w, np.float64)
        self.kept = float((np.square(self.A.astype(np.float64)).sum(0) * w).sum() / w.sum())
        # the same against the robot's uncompressed features (what the map can still tell apart of
        # what the robot's encoder saw): its basis' captured variance, then what survives
        tv = float(robot_fs.pca.total_variance) if robot_fs.pca is not None else 0.0
        self.kept_of_raw = float((np.square(self.A.astype(np.float64)).sum(0) * w).sum() / tv) if tv > 0 \
            else self.kept

    def features(self, f: np.ndarray) -> np.ndarray:
        """``(k_r, h, w)`` → ``(k_m, h, w)`` float32."""
        f = np.asarray(f)
        if f.ndim != 3 or f.shape[0] != self.in_dim:
            raise ValueError(f"features must be ({self.in_dim}, h, w), got {f.shape}")
        c, h, w = f.shape
        y = self.A @ f.reshape(c, h * w).astype(np.float32, copy=False)
        y += self.b[:, None]
        return y.reshape(self.out_dim, h, w)

    def vector(self, g: np.ndarray) -> np.ndarray:
        """``(k_r,)`` → ``(k_m,)`` float32 (a frame's global feature)."""
        g = np.asarray(g, np.float32).reshape(-1)
        if g.shape[0] != self.in_dim:
            raise ValueError(f"global feature must have {self.in_dim} values, got {g.shape[0]}")
        return self.A @ g + self.b


# ------------------------------------------------------------------ transforms
class TransformError(ValueError):
    """A world_from_robot value that is not a finite rigid transform."""


def _rpy(roll, pitch, yaw) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def parse_transform(value: TransformSpec, what: str = "world_from_robot") -> np.ndarray:
    """A 4×4 float64 rigid transform from 16 numbers (row-major), a 4×4 nested list, or
    ``{"xyz": [x, y, z], "rpy_deg": [roll, pitch, yaw]}`` (z-y-x order, degrees)."""
    from common.conventions import is_rigid

    try:
        if isinstance(value, dict):
            unknown = set(value) - {"xyz", "rpy_deg"}
            if unknown:
                raise TransformError(f"{what}: unknown keys {sorted(unknown)} (use xyz, rpy_deg)")
            t = np.asarray(value.get("xyz", [0, 0, 0]), np.float64).reshape(3)
            r = np.radians(np.asarray(value.get("rpy_deg", [0, 0, 0]), np.float64).reshape(3))
            T = np.eye(4)
            T[:3, :3] = _rpy(*r)
            T[:3, 3] = t
        else:
            T = np.asarray(value, np.float64).reshape(4, 4)
    except TransformError:
        raise
    except (TypeError, ValueError) as e:
        raise TransformError(f"{what}: expected 16 numbers, a 4x4 list or {{xyz, rpy_deg}}: {e}") from None
    if not is_rigid(T):
        raise TransformError(f"{what}: not a finite rigid transform (orthonormal rotation, last row 0 0 0 1)")
    return T


class RobotTransforms:
    """Per-robot ``world_from_robot`` (thread-safe). Robots without one map as they are.
    Those set at run time (:meth:`set`) are listed by :meth:`runtime` (snapshots keep them)."""

    def __init__(self, initial: dict | None = None):
        self._lock = threading.Lock()
        self._t: dict[str, np.ndarray] = {}
        self._runtime: set[str] = set()
        for robot, v in (initial or {}).items():
            self._t[str(robot)] = parse_transform(v, f"fleet.world_from_robot.{robot}")

    def get(self, robot: str) -> np.ndarray | None:
        with self._lock:
            t = self._t.get(robot)
            return None if t is None else t.copy()

    def set(self, robot: str, value: TransformSpec) -> np.ndarray:
        """Set ``robot``'s transform at run time (raises :class:`TransformError`)."""
        T = parse_transform(value)
        with self._lock:
            self._t[robot] = T
            self._runtime.add(robot)
        return T

    def runtime(self) -> dict[str, list[float]]:
        """``{robot: 16 numbers, row-major}`` of the transforms set at run time."""
        with self._lock:
            return {r: self._t[r].reshape(-1).tolist() for r in sorted(self._runtime)}

    def as_dict(self) -> dict:
        with self._lock:
            return {r: t.reshape(-1).tolist() for r, t in self._t.items()}

    def apply(self, robot: str, pose: np.ndarray) -> np.ndarray:
        """``world_from_robot · pose`` (the pose itself when the robot has no transform)."""
        with self._lock:
            t = self._t.get(robot)
        return pose if t is None else t @ np.asarray(pose, np.float64)


# ------------------------------------------------------------------ rates
class RateMeter:
    """Events per second over the last ``window`` seconds (bounded: at most ``cap`` stamps)."""

    def __init__(self, window: float = 5.0, cap: int = 512):
        self.window = float(window)
        self._t: collections.deque = collections.deque(maxlen=cap)

    def add(self, n: int = 1, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        for _ in range(min(int(n), self._t.maxlen or 0)):     # made with a maxlen
            self._t.append(now)

    def rate(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        while self._t and now - self._t[0] > self.window:
            self._t.popleft()
        if not self._t:
            return 0.0
        if len(self._t) == self._t.maxlen:        # saturated: the span of what it holds
            span = max(now - self._t[0], 1e-3)
            return len(self._t) / span
        return len(self._t) / self.window


@dataclass
class RobotRates:
    """Received / mapped / dropped / rejected rates of one robot."""

    window: float = 5.0
    received: RateMeter = field(init=False)
    mapped: RateMeter = field(init=False)
    dropped: RateMeter = field(init=False)
    rejected: RateMeter = field(init=False)

    def __post_init__(self):
        for k in ("received", "mapped", "dropped", "rejected"):
            setattr(self, k, RateMeter(self.window))

    def as_dict(self, now: float | None = None) -> dict:
        now = time.monotonic() if now is None else now
        return {f"{k}_hz": round(getattr(self, k).rate(now), 3) for k in ("received", "mapped", "dropped", "rejected")}


class DropWarner:
    """Warns that a robot's frames are dropped, at most once per ``period`` s per robot, with
    the number dropped since the last warning and the rates."""

    def __init__(self, period: float = 10.0, logger: logging.Logger | None = None):
        self.period = float(period)
        self.log = logger or log
        self._last: dict[str, float] = {}
        self._since: collections.Counter = collections.Counter()
        self._lock = threading.Lock()

    def dropped(self, robot: str, n: int, rates: dict, queue_len: int, now: float | None = None) -> bool:
        """Count ``n`` dropped frames of ``robot``; True when a warning was logged."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._since[robot] += n
            last = self._last.get(robot)
            if last is not None and now - last < self.period:
                return False
            k, self._since[robot] = self._since[robot], 0
            self._last[robot] = now
        self.log.warning("robot %s: %d frame(s) dropped (%.1f/s; received %.1f/s, mapped %.1f/s, queue %d): the "
                         "mapper cannot keep up; use publish.rate_hz=auto on the edge, lower its rate, or raise "
                         "queues.per_robot", robot, k, rates.get("dropped_hz", 0.0), rates.get("received_hz", 0.0),
                         rates.get("mapped_hz", 0.0), queue_len)
        return True

    def forget(self, robot: str) -> None:
        with self._lock:
            self._last.pop(robot, None)
            self._since.pop(robot, None)


# ------------------------------------------------------------------ status
STATES = ("pending", "accepted", "refused", "evicted")


def robot_status(name: str, state: str, reason: str, st: object, rates: dict, map_space: str, shard: str = "",
                 advised_hz: float | None = None) -> dict:
    """The per-robot status body published on ``mapper/robots/<robot>/status``.

    ``st`` is duck-typed (received, mapped, dropped, rejected Counter, queue, feature_space);
    ``advised_hz``: the publish rate this robot may use without its frames being dropped."""
    if state not in STATES:
        raise ValueError(f"unknown robot state {state!r}")
    rej = {str(k): int(v) for k, v in getattr(st, "rejected", {}).items()}
    return {"robot": name, "state": state, "reason": reason, "received": int(getattr(st, "received", 0)),
            "mapped": int(getattr(st, "mapped", 0)), "dropped": int(getattr(st, "dropped", 0)),
            "rejected": rej, "rejected_total": int(sum(rej.values())),
            "queue": len(getattr(st, "queue", ()) or ()), "feature_space": str(getattr(st, "feature_space", "")),
            "map_feature_space": map_space, "reprojected": bool(getattr(st, "reprojection", None) is not None),
            "shard": shard, **rates, "advised_hz": None if advised_hz is None else round(float(advised_hz), 3),
            "stamp": time.time()}


def advised_rate(mapped_total_hz: float, active_robots: int, robot: dict, per_robot_queue: int) -> float | None:
    """The rate a robot may publish at: its fair share of what the mapper maps when frames
    are being dropped or more than one waits in its queue (a queue kept short keeps the
    latency at about one frame per robot), else 25 % above its current rate (probing
    upwards). None before anything was mapped."""
    if mapped_total_hz <= 0 or active_robots <= 0:
        return None
    share = mapped_total_hz / active_robots
    congested = robot.get("dropped_hz", 0.0) > 0 or robot.get("queue", 0) > 1
    if congested:
        return 0.9 * min(share, max(robot.get("mapped_hz", 0.0), 0.1))
    return max(share, 1.25 * max(robot.get("mapped_hz", 0.0), 0.1))


class StatusPublisher:
    """Decides when a robot's status is due: on every change of ``(state, reason)`` and at
    most once per ``period`` s otherwise (while something changed)."""

    def __init__(self, period: float = 1.0):
        self.period = float(period)
        self._last: dict[str, tuple] = {}

    def due(self, robot: str, status: dict, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        key = (status["state"], status["reason"])
        counts = (status["received"], status["mapped"], status["dropped"], status["rejected_total"])
        prev = self._last.get(robot)
        if prev is None or prev[0] != key or (prev[2] != counts and now - prev[1] >= self.period):
            self._last[robot] = (key, now, counts)
            return True
        return False

    def forget(self, robot: str) -> None:
        self._last.pop(robot, None)


# ------------------------------------------------------------------ bounds
def evictions(robots: dict, now_wall: float, cfg: FleetSection) -> list[tuple[str, str]]:
    """``[(robot, reason)]`` of robots to forget now. ``robots``: name → state with
    ``seen_at`` (wall time of the first frame / liveliness), ``last_frame_at`` (wall time of
    the last frame, 0 if none), ``present``, ``gone_at``, ``space_ok``, ``feature_space``,
    ``queue``."""
    out = []
    for name, st in robots.items():
        if st.present and st.space_ok:
            continue
        last = max(float(getattr(st, "last_frame_at", 0.0) or 0.0), float(st.seen_at or 0.0))
        if not st.present and st.gone_at is not None and cfg.gone_evict_s >= 0 \
                and now_wall - max(st.gone_at, last) >= cfg.gone_evict_s:
            out.append((name, f"gone for {now_wall - st.gone_at:.0f} s"))
        elif not st.space_ok and not st.feature_space and cfg.no_space_evict_s >= 0 \
                and now_wall - float(now_wall if st.seen_at is None else st.seen_at) >= cfg.no_space_evict_s:
            out.append((name, f"served no feature space within {cfg.no_space_evict_s:g} s"))
    return out


def expire_pending(robots: Iterable, now_wall: float, cfg: FleetSection, per_robot: int = 0) -> list[tuple[str, int]]:
    """Drop held frames (``(frame, t_recv)`` in ``st.queue``) of robots whose space is not
    known yet: older than ``pending_ttl_s``, then the oldest over ``max(pending_max_frames,
    per_robot)`` in total (one robot may always fill its own queue). Returns
    ``[(robot, n_dropped)]``."""
    waiting = [st for st in robots if not st.space_ok and st.queue]
    out: collections.Counter[str] = collections.Counter()
    for st in waiting:
        while st.queue and now_wall - st.queue[0][1] > cfg.pending_ttl_s:
            st.queue.popleft()
            out[st.name] += 1
    total = sum(len(st.queue) for st in waiting)
    while total > max(0, cfg.pending_max_frames, int(per_robot)):
        st = min((s for s in waiting if s.queue), key=lambda s: s.queue[0][1])
        st.queue.popleft()
        out[st.name] += 1
        total -= 1
    return sorted(out.items())


def _score_error(ref, got) -> dict:
    """``max_abs``, ``mean_abs``, ``p99_abs`` of ``got − ref`` ((Q, N) scores) and ``top1_agree``
    (share of queries whose best row is the same)."""
    d = (ref - got).abs().reshape(-1).numpy()
    agree = (ref.argmax(1) == got.argmax(1)).float().mean().item()
    return {"max_abs": float(d.max()), "mean_abs": float(d.mean()), "p99_abs": float(np.percentile(d, 99)),
            "top1_agree": float(agree)}


def reprojection_score_error(map_fs: FeatureSpace, robot_fs: FeatureSpace, x: np.ndarray | torch.Tensor,
                             queries: np.ndarray | torch.Tensor) -> dict:
    """Query-score loss of a robot's re-projected features, measured against the truth: the
    **uncompressed** encoder-space features ``x`` (N, D) scored against ``queries`` (Q, lang_dim)
    (cosine in the language space, :meth:`FeatureSpace.similarity` of the space without PCA).
    What the map then holds — ``x`` compressed in the robot's basis (float16, as on the wire) and
    re-projected into the map's basis (:class:`Reprojection`) — is scored the same way.

    Returns ``max_abs``, ``mean_abs``, ``p99_abs``, ``top1_agree`` of that loss (what the map can
    no longer tell apart), ``map_basis`` (the same figures for ``x`` compressed directly in the
    map's basis: the loss any robot would have) and ``kept`` (:attr:`Reprojection.kept`)."""
    import dataclasses

    import torch

    x = torch.as_tensor(np.asarray(x, np.float32))
    q = torch.as_tensor(np.asarray(queries, np.float32))
    raw_fs = dataclasses.replace(map_fs, pca=None, _head_cache={})
    s_raw = raw_fs.similarity(x, q)
    direct = torch.as_tensor(np.asarray(map_fs.compress(x))).to(torch.float16).float()
    yr = torch.as_tensor(np.asarray(robot_fs.compress(x))).to(torch.float16).float().numpy()
    rp = Reprojection(map_fs, robot_fs)
    moved = torch.as_tensor(yr @ rp.A.T + rp.b)
    out = _score_error(s_raw, map_fs.similarity(moved, q))
    out.update(map_basis=_score_error(s_raw, map_fs.similarity(direct, q)), n_features=int(x.shape[0]),
               n_queries=int(q.shape[0]), kept=rp.kept)
    return out
