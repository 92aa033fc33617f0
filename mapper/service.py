"""The mapper process (base station): frames in over Zenoh, one shared RayFronts map out.

Data path::

    Zenoh callback (per sample)          mapping thread
    ─────────────────────────            ───────────────────────────────────
    decode_frame (validates) ──reject──▶ counted by reason, rate-limited log
         │ ok
         ▼
    per-robot bounded deque  ──full───▶ oldest dropped (counted)
         │
         └──────────── round-robin ───▶ map.integrate → standing queries → layers
                                         → rerun → periodic snapshot

Nothing raised in a callback escapes it; nothing malformed reaches the map. Frames of a
robot whose feature space is unknown are held in its queue until a ``get`` on
``robots/<robot>/feature_space`` answers; frames whose feature space differs from the
map's are rejected (maps never mix spaces).

Locking: ``lock`` (the map lock) guards the map and its feature space; ``qlock`` the robot
table and queues; ``query_lock`` serialises queries (one-shot and standing), always taken
*before* ``lock``. A query holds the map lock only to copy the arrays it reads into a
:class:`mapper.service_map.QuerySnapshot` (an O(N·dim) memcpy into reused buffers, once per
map generation — ``map_gen`` bumps on every integrate, flush, create and restore); it
scores, clusters and measures outside the lock, so mapping goes on meanwhile. A query waits
at most ``query.lock_timeout_s`` for the map lock (held while one frame is integrated);
after that it is answered from the last snapshot (``timings.stale = 1``, ``frames_mapped``
says which map state). Standing queries run on their own thread, not the mapping thread.

Threads and CPU: every thread waits on its own event (the mapping thread's ``_wake`` is set
by each frame; the feature-space thread's ``_space_wake`` only when a robot needs its space
fetched), so no thread polls while frames queue — a polling Python thread takes the GIL
from the mapping thread at every one of the map's small torch calls. torch runs with
``cfg.threads`` intra-op threads in the mapping thread (auto: 1 on small machines, see
:func:`mapper.service_config.resolve_threads`) and ``cfg.query.threads`` in a query (auto:
all CPUs; scoring is one big matrix product). ``stats()`` reports the map thread's CPU per
integration (``timings.integrate_cpu_ms``), the process CPU from the first to the last
integration (``cpu_s.mapping``) and, per robot, the edge's CPU per frame from the ``cpu_s``
its frames carry in their meta (``edge_cpu_ms_per_frame``).
"""
from __future__ import annotations

import collections
import json
import logging
import os
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.messages import (
    MessageError, QueryRequest, decode_feature_space, decode_query_request, decode_snapshot_request,
    encode_error, encode_feature_space, encode_layer, encode_query_result, encode_snapshot_reply, encode_stats,
)
from common.wire import WireError, WireLimits, decode_frame

log = logging.getLogger("rayfronts.mapper")


def reject_reason(err: Exception) -> str:
    """A short, stable reason code from a decode error (``'depth'``, ``'pose'``, ``'message'``...)."""
    text = str(err)
    if text.startswith("frame: "):
        text = text[len("frame: "):]
    head = text.split(":", 1)[0].strip().split(" ")[0]
    head = head.split(".")[0].split("[")[0]
    return head[:40] or "malformed"


class _RateLimitedLog:
    """Logs the first occurrence of each key, then at most once per ``period`` s with a count."""

    def __init__(self, period: float = 10.0):
        self.period = period
        self._last: dict[str, float] = {}
        self._n: dict[str, int] = collections.Counter()
        self._lock = threading.Lock()

    def __call__(self, key: str, msg: str, *args) -> None:
        now = time.monotonic()
        with self._lock:
            self._n[key] += 1
            last = self._last.get(key)
            if last is not None and now - last < self.period:
                return
            n, self._n[key] = self._n[key], 0
            self._last[key] = now
        log.warning(msg + (f" (x{n} since last report)" if n > 1 else ""), *args)


@dataclass
class RobotState:
    name: str
    queue: collections.deque
    received: int = 0
    mapped: int = 0
    dropped: int = 0
    rejected: collections.Counter = field(default_factory=collections.Counter)
    present: bool = False
    seen_at: float = 0.0
    gone_at: float | None = None
    feature_space: str = ""          # id of the robot's space once fetched
    space_ok: bool = False           # space known and equal to the map's
    space_error: str = ""
    fetch_after: float = 0.0
    fetch_started: float = -1e9      # monotonic start of the last feature-space get
    last_seq: int = -1
    edge_cpu: tuple | None = None    # (first, last) edge process CPU s (frame meta ``cpu_s``) of mapped frames
    edge_cpu_frames: int = 0         # mapped frames between them

    def as_dict(self) -> dict:
        d = {"received": self.received, "mapped": self.mapped, "dropped": self.dropped,
             "rejected": dict(self.rejected), "queue": len(self.queue), "present": self.present,
             "seen_at": self.seen_at, "gone_at": self.gone_at, "feature_space": self.feature_space,
             "space_ok": self.space_ok, "space_error": self.space_error, "last_seq": self.last_seq}
        if self.edge_cpu is not None and self.edge_cpu_frames > 0:
            # the robot's edge process CPU per frame, over its mapped frames (frame meta cpu_s)
            d["edge_cpu_ms_per_frame"] = (self.edge_cpu[1] - self.edge_cpu[0]) * 1e3 / self.edge_cpu_frames
        return d


class _Pct:
    """Ring buffer of recent samples with percentiles (ms)."""

    def __init__(self, n: int = 1000):
        self._d: collections.deque = collections.deque(maxlen=n)

    def add(self, x: float) -> None:
        self._d.append(float(x))

    def summary(self) -> dict:
        if not self._d:
            return {"n": 0}
        a = np.fromiter(self._d, float)
        return {"n": int(a.size), "p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
                "max": float(a.max()), "mean": float(a.mean()), "last": float(a[-1])}


class MapperService:
    """One mapper: Zenoh entities, per-robot queues, the map and its mapping thread.

    ``start()`` opens everything and returns; ``close()`` stops and releases it (idempotent).
    ``run()`` = start, wait for ``stop``, close."""

    def __init__(self, cfg, stop: threading.Event | None = None):
        self.cfg = cfg
        self.stop = stop or threading.Event()
        self.lock = threading.RLock()          # map + feature space
        self.qlock = threading.Lock()          # robot table + queues
        self.query_lock = threading.Lock()     # serialises queries; taken before `lock`
        self.map_gen = 0                       # bumps on every change of the map (under `lock`)
        self._qsnap = None                     # QuerySnapshot of the last query
        self._standing_due = threading.Event()
        self.map = None
        self.space = None                      # FeatureSpace of the map
        self._space_id: tuple = (None, "")     # (space, its id): FeatureSpace.id hashes the PCA basis
        self.space_reply: bytes | None = None  # its envelope (for snapshots)
        self.robots: dict[str, RobotState] = {}
        self.rejected: collections.Counter = collections.Counter()
        self.received = 0
        self.mapped = 0
        self.dropped = 0
        self.started = time.time()
        self.version = 0                       # bumps on every integrate
        self.flushed_version = 0               # version at the last map.flush()
        self.first_mapped_at: float | None = None
        self.last_mapped_at: float | None = None
        self._cpu_mapped: list[float] = []      # process CPU s at the first and the last integration
        self.timings = {"integrate_ms": _Pct(), "integrate_cpu_ms": _Pct(), "latency_ms": _Pct(),
                        "query_ms": _Pct(), "decode_ms": _Pct()}
        self.standing: dict[str, QueryRequest] = {}
        self.last_snapshot: dict = {}
        self._snap_version = -1
        self._warn = _RateLimitedLog()
        self._limits = WireLimits(max_message_bytes=int(cfg.queues.max_message_mb * (1 << 20)))
        self.session = None
        self.keys = None
        self._entities: list = []
        self._threads: list[threading.Thread] = []
        self._wake = threading.Event()        # mapping thread: a frame or a robot changed
        self._space_wake = threading.Event()  # feature-space thread: a robot needs its space (re)fetched
        self.rerun = None
        self._rr_count: collections.Counter = collections.Counter()
        self._closed = False

    @property
    def space_id(self) -> str:
        """Id of the map's feature space ("" before the map exists), computed once per space."""
        fs = self.space
        if fs is None:
            return ""
        if self._space_id[0] is not fs:
            self._space_id = (fs, fs.id)
        return self._space_id[1]

    # ================================================================== lifecycle
    def start(self) -> "MapperService":
        from common.keys import KeySpace
        from common.zenoh_session import open_session
        from mapper.service_config import resolve_query_threads

        self.keys = KeySpace(self.cfg.zenoh.prefix)
        log.info("torch threads: %d (mapping), %d (queries)", self._set_threads(),
                 resolve_query_threads(self.cfg.query.threads))
        if self.cfg.snapshots.dir and self.cfg.snapshots.restore:
            self._restore()
        if self.cfg.rerun.file or self.cfg.rerun.serve_grpc:
            from mapper.rerun_log import RerunLogger

            self.rerun = RerunLogger(self.cfg.rerun.app_id, file=self.cfg.rerun.file or None,
                                     serve_grpc=self.cfg.rerun.serve_grpc, grpc_port=self.cfg.rerun.grpc_port)
        self.session = s = open_session(self.cfg.zenoh, stop=self.stop, default_mode="router")
        k = self.keys
        try:
            self._entities = [
                s.declare_subscriber(k.frames_all, self._on_frame),
                s.liveliness().declare_subscriber(k.alive_all, self._on_alive, history=True),
                s.declare_queryable(k.mapper_query, self._on_query),
                s.declare_queryable(k.stats, self._on_stats),
                s.declare_queryable(k.snapshot, self._on_snapshot),
                s.declare_queryable(k.layers_all, self._on_layer_get),
                s.liveliness().declare_token(k.mapper_alive),
            ]
        except Exception:
            self.close()
            raise
        for name, fn in (("mapper-map", self._map_loop), ("mapper-space", self._space_loop),
                         ("mapper-standing", self._standing_loop)):
            t = threading.Thread(target=fn, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("mapper up (zid %s, prefix %r)", s.zid(), self.cfg.zenoh.prefix)
        return self

    def _set_threads(self, query: bool = False) -> int:
        """Set the calling thread's torch intra-op threads: ``cfg.query.threads`` for a query,
        else ``cfg.threads`` (mapping thread, process default). torch keeps the OpenMP count
        per thread once a thread has run parallel work (MKL's count is process-wide: the
        last caller's)."""
        import torch

        from mapper.service_config import resolve_query_threads, resolve_threads

        if query:
            n = resolve_query_threads(int(getattr(self.cfg.query, "threads", 0)))
        else:
            n = resolve_threads(int(getattr(self.cfg, "threads", 0)))
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)
        return n

    def run(self) -> int:
        self.start()
        try:
            while not self.stop.wait(0.5):
                pass
        finally:
            self.close()
        return 0

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.stop.set()
        self._wake.set()
        self._space_wake.set()
        self._standing_due.set()
        for t in self._threads:
            t.join(timeout=30.0)
        for e in reversed(self._entities):
            try:
                e.undeclare()
            except Exception:
                pass
        self._entities = []
        if self.session is not None:
            try:
                self.session.close()
            except Exception:
                pass
            self.session = None
        if self.cfg.snapshots.dir and self.cfg.snapshots.on_exit and self.map is not None:
            try:
                self.save_snapshot()
            except Exception as e:
                log.error("snapshot on exit failed: %s", e)
        if self.rerun is not None:
            try:
                with self.lock:
                    self._log_layers_rerun()
                self.rerun.close()
            except Exception as e:
                log.error("closing rerun failed: %s", e)
            self.rerun = None
        log.info("mapper closed: %s", json.dumps(self.stats()["frames"]))

    # ============================================================ frames in
    def _robot(self, name: str) -> RobotState:
        st = self.robots.get(name)
        if st is None:
            st = RobotState(name, collections.deque(maxlen=max(1, self.cfg.queues.per_robot)))
            self.robots[name] = st
            st.seen_at = time.time()
            self._wake.set()
            self._space_wake.set()
        return st

    def _reject(self, robot: str | None, reason: str, detail: str) -> None:
        with self.qlock:
            self.rejected[reason] += 1
            if robot is not None and robot in self.robots:
                self.robots[robot].rejected[reason] += 1
        self._warn(f"{robot}:{reason}", "rejected frame from %s (%s): %s", robot, reason, detail[:200])

    def _on_frame(self, sample) -> None:
        try:
            key_robot = self.keys.robot_from_key(str(sample.key_expr))
        except Exception:
            key_robot = None
        try:
            self.received += 1
            t0 = time.perf_counter()
            try:
                data = sample.payload.to_bytes()
                frame = decode_frame(data, limits=self._limits)
            except WireError as e:
                self._reject(key_robot if key_robot in self.robots else None, reject_reason(e), str(e))
                return
            self.timings["decode_ms"].add((time.perf_counter() - t0) * 1e3)
            if key_robot is None or frame.robot != key_robot:
                self._reject(None, "robot_mismatch", f"frame robot {frame.robot!r} on key {sample.key_expr}")
                return
            if frame.features is None:
                self._reject(key_robot, "no_features", "frame carries no features")
                return
            with self.qlock:
                st = self._robot(key_robot)
                st.received += 1
                if st.feature_space and frame.feature_space != st.feature_space:
                    # the edge may have restarted with another basis: refetch, reject meanwhile
                    st.fetch_after = 0.0
                    st.space_ok = False
                    st.feature_space = ""
                    self._space_wake.set()
                if len(st.queue) == st.queue.maxlen:
                    st.dropped += 1
                    self.dropped += 1
                st.queue.append((frame, time.time()))
                if not st.space_ok and not st.space_error:
                    # frames flow, so the edge's space is ready: fetch now rather than at the
                    # retry period (at most every 0.2 s), else frames pile up meanwhile
                    now = time.monotonic()
                    if st.fetch_after > now and now - st.fetch_started > 0.2:
                        st.fetch_after = 0.0
                        self._space_wake.set()
            self._wake.set()
        except Exception as e:  # never raise out of a callback
            self._reject(key_robot, "internal", repr(e))

    def _on_alive(self, sample) -> None:
        try:
            import zenoh

            robot = self.keys.robot_from_key(str(sample.key_expr))
            if robot is None:
                return
            with self.qlock:
                st = self._robot(robot)
                if sample.kind == zenoh.SampleKind.PUT:
                    st.present, st.seen_at, st.gone_at = True, time.time(), None
                    st.fetch_after = 0.0   # (re)fetch the space of a (re)started edge
                    log.info("robot %s present", robot)
                else:
                    st.present, st.gone_at = False, time.time()
                    log.info("robot %s gone", robot)
            self._wake.set()
            self._space_wake.set()
        except Exception as e:
            log.warning("liveliness callback: %s", e)

    # ====================================================== feature spaces
    def _space_loop(self) -> None:
        # its own event: the mapping thread's one is set by every frame and stays set while
        # frames are queued, which would turn this loop into a GIL-holding busy spin
        while not self.stop.is_set():
            self._space_wake.wait(0.5)
            self._space_wake.clear()
            now = time.monotonic()
            with self.qlock:
                todo = [st.name for st in self.robots.values()
                        if not st.space_ok and not st.space_error and st.fetch_after <= now]
            for robot in todo:
                if self.stop.is_set():
                    return
                self._fetch_space(robot)

    def _fetch_space(self, robot: str) -> None:
        from common.feature_space import FeatureSpace

        st = self.robots[robot]
        st.fetch_started = time.monotonic()
        try:
            replies = list(self.session.get(self.keys.feature_space(robot), timeout=3.0))
        except Exception as e:
            st.fetch_after = time.monotonic() + 1.0
            log.debug("feature space get for %s failed: %s", robot, e)
            return
        body = None
        err = "no reply"
        for r in replies:
            if r.ok is None:
                continue
            try:
                got, body = decode_feature_space(r.ok.payload.to_bytes())
                break
            except MessageError as e:
                err = str(e)
        if body is None:
            st.fetch_after = time.monotonic() + 1.0
            self._warn(f"{robot}:space", "feature space of %s not available yet: %s", robot, err)
            return
        try:
            fs = FeatureSpace.from_body(body)
        except Exception as e:
            st.fetch_after = time.monotonic() + 5.0
            self._warn(f"{robot}:space", "feature space of %s is invalid: %s", robot, e)
            return
        fs_id = fs.id
        with self.lock:
            if self.map is None:
                self._create_map(fs, encode_feature_space(robot, body))
            ok = fs_id == self.space_id
        with self.qlock:
            st.feature_space = fs_id
            st.space_ok = ok
            st.space_error = "" if ok else f"robot space {fs_id} differs from the map's {self.space_id}"
        if ok:
            log.info("robot %s feature space %s", robot, fs_id)
            self._wake.set()
        else:
            log.error("robot %s: %s; its frames are rejected", robot, st.space_error)

    def _create_map(self, fs, envelope: bytes) -> None:
        from mapper.service_map import create_map

        self.map = create_map(self.cfg, fs)
        self.map_gen += 1
        self.space = fs
        self.space_reply = envelope
        log.info("map created in feature space %s (dim %d)", fs.id, fs.dim)

    # ======================================================== mapping thread
    def _next_frame(self):
        """Round-robin over robots whose space matches the map; rejects frames of mismatched ones."""
        with self.qlock:
            names = sorted(self.robots)
            if not names:
                return None
            start = getattr(self, "_rr", 0)
            for i in range(len(names)):
                st = self.robots[names[(start + i) % len(names)]]
                if not st.queue:
                    continue
                if st.space_error:
                    n = len(st.queue)
                    st.queue.clear()
                    st.rejected["feature_space_differs"] += n
                    self.rejected["feature_space_differs"] += n
                    continue
                if not st.space_ok:
                    if not self.cfg.queues.hold_unknown_space:
                        n = len(st.queue)
                        st.queue.clear()
                        st.rejected["feature_space_unknown"] += n
                        self.rejected["feature_space_unknown"] += n
                    continue
                frame, t_recv = st.queue.popleft()
                if frame.feature_space != st.feature_space:
                    st.rejected["feature_space_mismatch"] += 1
                    self.rejected["feature_space_mismatch"] += 1
                    continue
                self._rr = (start + i + 1) % len(names)
                return st, frame, t_recv
        return None

    def _map_loop(self) -> None:
        self._set_threads()
        last_layers = 0.0
        last_standing = 0.0
        last_snap = time.monotonic()
        standing_version = -1
        layers_version = -1
        idle_since = time.monotonic()
        while not self.stop.is_set():
            item = self._next_frame()
            if item is None:
                self._wake.wait(0.05)
                self._wake.clear()
                idle_s = self.cfg.queues.idle_flush_s
                if (self.map is not None and self.version != self.flushed_version and idle_s > 0
                        and time.monotonic() - idle_since > idle_s):
                    self._flush()
            else:
                idle_since = time.monotonic()
                st, frame, t_recv = item
                t0 = time.perf_counter()
                c0 = time.thread_time()
                try:
                    with self.lock:
                        from mapper.service_map import integrate

                        try:
                            integrate(self.map, frame, self.cfg.device)
                        finally:
                            self.map_gen += 1
                        self.version += 1
                except Exception as e:
                    log.exception("integrating frame %s/%d failed", st.name, frame.seq)
                    self._reject(st.name, "integrate_failed", repr(e))
                    continue
                dt = (time.perf_counter() - t0) * 1e3
                self.timings["integrate_ms"].add(dt)
                self.timings["integrate_cpu_ms"].add((time.thread_time() - c0) * 1e3)
                t_send = frame.meta.get("t_send") if isinstance(frame.meta, dict) else None
                if isinstance(t_send, (int, float)):
                    self.timings["latency_ms"].add((time.time() - t_send) * 1e3)
                now_w = time.time()
                self.first_mapped_at = self.first_mapped_at or now_w
                self.last_mapped_at = now_w
                cpu = time.process_time()
                self._cpu_mapped = [self._cpu_mapped[0] if self._cpu_mapped else cpu, cpu]
                e_cpu = frame.meta.get("cpu_s") if isinstance(frame.meta, dict) else None
                with self.qlock:
                    st.mapped += 1
                    st.last_seq = frame.seq
                    self.mapped += 1
                    if isinstance(e_cpu, (int, float)) and not isinstance(e_cpu, bool):
                        if st.edge_cpu is None or e_cpu < st.edge_cpu[1]:   # first, or the edge restarted
                            st.edge_cpu, st.edge_cpu_frames = (float(e_cpu), float(e_cpu)), 0
                        else:
                            st.edge_cpu, st.edge_cpu_frames = (st.edge_cpu[0], float(e_cpu)), st.edge_cpu_frames + 1
                if self.rerun is not None:
                    self._rr_count[st.name] += 1
                    if (self._rr_count[st.name] - 1) % max(1, self.cfg.rerun.every_n_frames) == 0:
                        try:
                            self.rerun.log_frame(frame, self.mapped)
                        except Exception as e:
                            self._warn("rerun", "rerun logging failed: %s", e)
            now = time.monotonic()
            if self.map is None:
                continue
            qcfg = self.cfg.query
            if (self.standing and self.version != standing_version and qcfg.standing_rate_hz > 0
                    and now - last_standing >= 1.0 / qcfg.standing_rate_hz):
                last_standing, standing_version = now, self.version
                self._standing_due.set()
            lcfg = self.cfg.layers
            if (lcfg.rate_hz > 0 and self.version != layers_version and now - last_layers >= 1.0 / lcfg.rate_hz
                    and (item is None or now - last_layers >= 5.0 / lcfg.rate_hz)):
                last_layers, layers_version = now, self.version
                self._publish_layers()
            scfg = self.cfg.snapshots
            if scfg.dir and scfg.period_s > 0 and now - last_snap >= scfg.period_s and self.version != self._snap_version:
                last_snap = now
                try:
                    self.save_snapshot()
                except Exception as e:
                    log.error("periodic snapshot failed: %s", e)

    def _flush(self) -> None:
        """Integrate what the map buffers (accumulation periods) when the input is idle."""
        with self.lock:
            v = self.version
            try:
                from mapper.service_map import flush

                flush(self.map)
            except Exception as e:
                self._warn("flush", "map flush failed: %s", e)
            self.map_gen += 1
            self.flushed_version = v

    # ================================================================ layers
    def layer_bytes(self, layer: str) -> bytes:
        from mapper.service_map import layer_arrays

        with self.lock:
            if self.map is None:
                raise MessageError("no map yet")
            arrays, meta = layer_arrays(self.map, layer, self.cfg.layers)
        meta.update(frames_mapped=self.mapped, stamp=time.time())
        return encode_layer(layer, arrays, meta)

    def _publish_layers(self) -> None:
        from common.messages import LAYERS

        for layer in LAYERS:
            try:
                self.session.put(self.keys.layers(layer), self.layer_bytes(layer))
            except Exception as e:
                self._warn("layers", "publishing layer %s failed: %s", layer, e)
        if self.rerun is not None:
            try:
                with self.lock:
                    self._log_layers_rerun()
            except Exception as e:
                self._warn("rerun", "rerun layer logging failed: %s", e)

    def _log_layers_rerun(self) -> None:
        from mapper.service_map import layer_arrays

        if self.map is None:
            return
        big = type(self.cfg.layers)(rate_hz=0, max_voxels=10 ** 9, max_rays=10 ** 9)
        vox, _ = layer_arrays(self.map, "voxels", big)
        fr, _ = layer_arrays(self.map, "frontiers", big)
        rays, _ = layer_arrays(self.map, "rays", big)
        self.rerun.log_map(self.mapped, vox["xyz"], vox["rgb"], fr["xyz"], rays["origin"], rays["direction"],
                           vox_size=float(self.cfg.map.vox_size))

    def _on_layer_get(self, query) -> None:
        try:
            layer = str(query.key_expr).rsplit("/", 1)[-1]
            try:
                payload = self.layer_bytes(layer)
            except MessageError as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("layer query failed: %s", e)

    # =============================================================== queries
    def _snapshot(self, timings: dict):
        """The QuerySnapshot of the current map generation (caller holds ``query_lock``)."""
        from mapper.service_map import QuerySnapshot

        snap = self._qsnap
        if snap is not None and snap.gen == self.map_gen:
            return snap
        fresh = QuerySnapshot() if snap is None else snap
        m = self.map
        if m is not None:
            fresh.reserve(m)                      # allocations outside the lock (size hint)
        t = time.perf_counter()
        got = self.lock.acquire(timeout=max(0.0, float(self.cfg.query.lock_timeout_s)))
        if not got and snap is None:
            got = self.lock.acquire()            # nothing to fall back on: wait for the frame
        timings["lock_wait"] = (time.perf_counter() - t) * 1e3
        if not got:
            timings["stale"] = 1.0
            return snap
        try:
            if self.map is None:
                raise MessageError("the map is empty (no frames mapped yet)")
            if snap is None or snap.gen != self.map_gen:
                snap = fresh.take(self.map, self.map_gen, self.mapped)
                self._qsnap = snap
                timings["snapshot"] = snap.take_ms
        finally:
            self.lock.release()
        return snap

    def run_query(self, req: QueryRequest):
        from mapper.service_map import answer_snapshot

        t0 = time.perf_counter()
        if self.map is None:
            raise MessageError("the map is empty (no frames mapped yet)")
        with self.query_lock:
            self._set_threads(query=True)
            timings: dict = {}
            snap = self._snapshot(timings)
            res = answer_snapshot(snap, self.space, req, self.cfg.query, device=self.cfg.device,
                                  model_dir=self.cfg.text_model_dir)
            res.frames_mapped = snap.frames_mapped
        res.timings.update(timings)
        res.stamp = time.time()
        res.timings["total"] = (time.perf_counter() - t0) * 1e3
        self.timings["query_ms"].add(res.timings["total"])
        return res

    def _on_query(self, query) -> None:
        try:
            try:
                if query.payload is None:
                    raise MessageError("query without payload")
                req = decode_query_request(query.payload.to_bytes())
                if req.cancel:
                    self.standing.pop(req.id, None)
                    from common.messages import QueryResult

                    payload = encode_query_result(QueryResult(id=req.id, query="<cancelled>"))
                else:
                    res = self.run_query(req)
                    res.id = req.id
                    if req.standing:
                        self.standing[req.id] = req
                    payload = encode_query_result(res)
                    if self.rerun is not None:
                        try:
                            with self.lock:
                                self.rerun.log_query(res, self.map, self.space, req, self.mapped)
                        except Exception as e:
                            self._warn("rerun", "rerun query logging failed: %s", e)
            except (MessageError, ValueError) as e:
                payload = encode_error(str(e))
            except Exception as e:
                log.exception("query failed")
                payload = encode_error(f"internal error: {e!r}")
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("query callback: %s", e)

    def _standing_loop(self) -> None:
        """Re-runs standing queries when the mapping thread says the map changed."""
        while not self.stop.is_set():
            if not self._standing_due.wait(0.5):
                continue
            self._standing_due.clear()
            if self.stop.is_set():
                return
            self._run_standing()

    def _run_standing(self) -> None:
        for qid, req in list(self.standing.items()):
            try:
                res = self.run_query(req)
                res.id = qid
                self.session.put(self.keys.mapper_queries(qid), encode_query_result(res))
            except Exception as e:
                self._warn(f"standing:{qid}", "standing query %s failed: %s", qid, e)

    # ================================================================= stats
    def stats(self) -> dict:
        with self.qlock:
            robots = {n: st.as_dict() for n, st in self.robots.items()}
            frames = {"received": self.received, "mapped": self.mapped, "dropped": self.dropped,
                      "rejected": dict(self.rejected), "rejected_total": int(sum(self.rejected.values()))}
        out: dict[str, Any] = {
            "frames": frames, "robots": robots,
            "queues": {n: r["queue"] for n, r in robots.items()},
            "timings": {k: v.summary() for k, v in self.timings.items()},
            "feature_space": self.space_id,
            "uptime_s": time.time() - self.started, "standing_queries": sorted(self.standing),
            "snapshot": dict(self.last_snapshot), "map_version": self.version,
            "flushed_version": self.flushed_version,
            "first_mapped_at": self.first_mapped_at, "last_mapped_at": self.last_mapped_at,
            # process CPU (all threads) from the first to the last integration, and in total
            "cpu_s": {"mapping": (self._cpu_mapped[1] - self._cpu_mapped[0]) if self._cpu_mapped else 0.0,
                      "process": time.process_time()},
        }
        try:
            import psutil

            out["rss_mb"] = psutil.Process().memory_info().rss / 2 ** 20
        except Exception:
            pass
        if self.map is not None:
            from mapper.service_map import map_stats

            with self.lock:
                out["map"] = map_stats(self.map)
        return out

    def _on_stats(self, query) -> None:
        try:
            query.reply(query.key_expr, encode_stats(_jsonable(self.stats())))
        except Exception as e:
            log.warning("stats callback: %s", e)

    # ============================================================= snapshots
    def save_snapshot(self) -> dict:
        """Write the map atomically (tmp dir, then rename) to ``snapshots.dir/snap-<n>``."""
        root = Path(self.cfg.snapshots.dir)
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        with self.lock:
            if self.map is None:
                raise MessageError("nothing to snapshot: no map yet")
            version = self.version
            with self.qlock:
                meta = {"frames_mapped": self.mapped, "stamp": time.time(), "version": version,
                        "robots": {n: {"mapped": st.mapped, "last_seq": st.last_seq} for n, st in self.robots.items()}}
            path = write_snapshot(root, self.map, self.space_reply, meta, self.cfg.snapshots.keep)
        self._snap_version = version
        self.last_snapshot = {"path": str(path), "frames_mapped": meta["frames_mapped"], "stamp": meta["stamp"],
                              "seconds": time.perf_counter() - t0}
        log.info("snapshot %s (%d frames)", path, meta["frames_mapped"])
        return self.last_snapshot

    def _restore(self) -> None:
        from common.feature_space import FeatureSpace
        from mapper.service_map import load_map

        root = Path(self.cfg.snapshots.dir)
        ptr = root / "LATEST"
        if not ptr.is_file():
            return
        path = root / ptr.read_text().strip()
        try:
            meta = json.loads((path / "meta.json").read_text())
            envelope = (path / "feature_space.bin").read_bytes()
            _, body = decode_feature_space(envelope)
            fs = FeatureSpace.from_body(body)
            self.map = load_map(path / "map", self.cfg, fs)
            self.map_gen += 1
        except Exception as e:
            log.error("cannot restore snapshot %s: %s (starting empty)", path, e)
            self.map = None
            return
        self.space, self.space_reply = fs, envelope
        self.mapped = int(meta.get("frames_mapped", 0))
        self.version = self._snap_version = self.flushed_version = 1
        for name, r in meta.get("robots", {}).items():
            st = self._robot(name)
            st.mapped, st.last_seq = int(r.get("mapped", 0)), int(r.get("last_seq", -1))
        self.last_snapshot = {"path": str(path), "frames_mapped": self.mapped, "stamp": meta.get("stamp", 0.0),
                              "restored": True}
        log.info("restored snapshot %s (%d frames, space %s)", path, self.mapped, fs.id)

    def _on_snapshot(self, query) -> None:
        try:
            try:
                action = decode_snapshot_request(query.payload.to_bytes()) if query.payload is not None else "describe"
                if action == "save":
                    if not self.cfg.snapshots.dir:
                        raise MessageError("snapshots are off (set snapshots.dir)")
                    info = self.save_snapshot()
                else:
                    info = dict(self.last_snapshot)
                payload = encode_snapshot_reply(_jsonable(info))
            except (MessageError, OSError) as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("snapshot callback: %s", e)


def write_snapshot(root: Path, m, space_envelope: bytes, meta: dict, keep: int = 2) -> Path:
    """Write ``root/snap-<ms>`` atomically (a ``.tmp-`` dir renamed into place, then the
    ``LATEST`` pointer replaced) with the map, its feature-space envelope and ``meta``;
    keeps the newest ``keep`` snapshots. The caller holds the map lock."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = f"snap-{int(time.time() * 1000):015d}"
    tmp = root / f".tmp-{name}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    m.save(tmp / "map")
    (tmp / "feature_space.bin").write_bytes(space_envelope)
    (tmp / "meta.json").write_text(json.dumps(meta))
    os.replace(tmp, root / name)
    (root / ".latest.tmp").write_text(name)
    os.replace(root / ".latest.tmp", root / "LATEST")
    snaps = sorted(p for p in root.glob("snap-*") if p.is_dir())
    for old in snaps[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return root / name


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)
