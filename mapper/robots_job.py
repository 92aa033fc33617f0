"""The mapper's fleet job: several robots in one map, told what happens, bounded; and this
mapper as one shard of several (module map: ARCHITECTURE.md).

Hooks (the other jobs call them; pure parts in :mod:`mapper.robot_registry`, :mod:`mapper.shards`):

* ``MapperState.robot`` (a new robot id, ``robots_lock`` held): :meth:`RobotsJob.admit` (robot cap);
* ingest, feature-space fetch: :meth:`RobotsJob.space_decided` — refuses another encoder family
  with one line, builds the :class:`mapper.robot_registry.Reprojection` of a robot with another PCA
  basis;
* map worker, before integrating: :meth:`RobotsJob.prepare` — re-projects features into the
  map's basis, applies ``world_from_robot`` to the pose, and leaves out frames outside this
  shard's region (counted ``outside_shard``);
* its own thread (:meth:`RobotsJob.loop`, every 0.5 s, waiting on ``stop``): per-robot rates
  from the counters ingest and the map worker keep, drop warnings with the rate, evictions,
  pending-frame expiry, per-robot status on ``mapper/robots/<robot>/status`` (on change,
  else at most every ``fleet.status_period_s``);
* the ``mapper/robots/*/world_from_robot`` queryable (:meth:`RobotsJob.on_transform`);
* query replies carry :meth:`RobotsJob.shard_info` as their attachment (client-side merge).

Per-robot frames never mix: a frame is queued under the robot of its key, and only when the
frame's own ``robot`` field equals it (ingest rejects ``robot_mismatch``); its features,
pose and seq travel together in one decoded :class:`common.frame.Frame` object from the
callback to the map; the robot's re-projection and transform are looked up by that robot's
state (``tests/test_fleet_runtime.py`` checks it end to end).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from common.feature_space import compatibility
from mapper.robot_registry import (
    DropWarner,
    RateMeter,
    Reprojection,
    RobotRates,
    RobotTransforms,
    StatusPublisher,
    TransformError,
    advised_rate,
    evictions,
    expire_pending,
    robot_status,
)
from mapper.shards import ShardFilter

if TYPE_CHECKING:
    import zenoh

    from common.feature_space import FeatureSpace
    from common.frame import Frame
    from common.messages import QueryResult
    from mapper.state import MapperState, RobotState

log = logging.getLogger("rayfronts.mapper")


@dataclass
class FleetRobot:
    """Per-robot fleet data (``RobotState.fleet``)."""

    rates: RobotRates
    reprojection: Reprojection | None = None
    last_frame_at: float = 0.0
    outside_shard: int = 0
    pending_expired: int = 0
    refused: str = ""               # why the robot is refused ("" = not refused)
    counts: tuple | None = None     # (received, mapped, dropped, rejected) at the last sample

    def as_dict(self, now: float | None = None) -> dict:
        d = {"reprojected": self.reprojection is not None, "outside_shard": self.outside_shard,
             "pending_expired": self.pending_expired, **self.rates.as_dict(now)}
        if self.reprojection is not None:
            d["reprojection_kept"] = round(self.reprojection.kept, 4)
            d["reprojection_kept_of_raw"] = round(self.reprojection.kept_of_raw, 4)
        return d


class RobotsJob:
    """See the module docstring. One per mapper; ``state.fleet`` points at it."""

    def __init__(self, state: MapperState) -> None:
        self.state = state
        cfg = state.cfg
        self.cfg = cfg.fleet
        self.transforms = RobotTransforms(self.cfg.world_from_robot)
        self.shard = ShardFilter(cfg.shard)
        self.drops = DropWarner(self.cfg.drop_warn_s)
        self.status = StatusPublisher(self.cfg.status_period_s)
        self.map_rate = RateMeter(self.cfg.rate_window_s, cap=4096)
        self.capped = 0
        self.evicted = 0
        self.pending_expired = 0
        self._cap_warned = 0.0
        state.fleet = self

    # ------------------------------------------------------------ per robot
    def robot_data(self, st: RobotState) -> FleetRobot:
        fr = getattr(st, "fleet", None)
        if fr is None:
            fr = st.fleet = FleetRobot(RobotRates(self.cfg.rate_window_s))
        return fr

    def admit(self, name: str) -> bool:
        """True when ``name`` is tracked or may be (caller holds ``robots_lock``; ``MapperState.robot``
        asks for every new id); else counts the frame under ``robot_cap`` (globally: nothing is
        kept per refused id)."""
        state = self.state
        if name in state.robots or len(state.robots) < max(1, self.cfg.max_robots):
            return True
        self.capped += 1
        state.rejected["robot_cap"] += 1
        now = time.monotonic()
        if now - self._cap_warned > self.cfg.drop_warn_s:
            self._cap_warned = now
            log.warning("robot %s refused: %d robots tracked already (fleet.max_robots); %d refused so far",
                        name, len(state.robots), self.capped)
        return False

    def sample_counts(self, st: RobotState, now: float, now_wall: float) -> None:
        """Turn the robot's counters (received / mapped / dropped / rejected, kept by ingest and
        the map worker) into rates, warn about drops with their rate. Caller holds ``robots_lock``."""
        fr = self.robot_data(st)
        cur = (st.received, st.mapped, st.dropped, int(sum(st.rejected.values())))
        prev = fr.counts if fr.counts is not None else (0, 0, 0, 0)
        fr.counts = cur
        d_recv, d_map, d_drop, d_rej = (max(0, a - b) for a, b in zip(cur, prev, strict=True))
        if d_recv:
            fr.rates.received.add(d_recv, now)
            fr.last_frame_at = now_wall
        if d_map:
            fr.rates.mapped.add(d_map, now)
            self.map_rate.add(d_map, now)
        if d_rej:
            fr.rates.rejected.add(d_rej, now)
        if d_drop:
            fr.rates.dropped.add(d_drop, now)
            self.drops.dropped(st.name, d_drop, fr.rates.as_dict(now), len(st.queue), now)

    def space_decided(self, st: RobotState, fs: FeatureSpace) -> str:
        """Decide on a robot's fetched feature space ``fs``: "" (accepted, possibly
        re-projected) or the one-line reason it is refused. Caller holds the map ``lock``."""
        state = self.state
        fr = self.robot_data(st)
        assert state.space is not None        # the caller made the map (and its space) first
        why = compatibility(state.space, fs, self.cfg.reproject)
        fr.reprojection = None
        if not why and fs.id != state.space_id:
            fr.reprojection = rp = Reprojection(state.space, fs)
            if rp.kept_of_raw < self.cfg.reproject_warn_kept:
                log.warning("robot %s: its features keep only %.0f%% of their variance in the map's PCA basis "
                            "(re-projected from its own basis); what it sees may not be queryable: give it the "
                            "map's basis (pca.basis=map)", st.name, 100 * rp.kept_of_raw)
        fr.refused = why
        return why

    def prepare(self, st: RobotState, frame: Frame) -> Frame | None:
        """The frame as the map integrates it (re-projected, transformed), or None when it is
        outside this shard (counted)."""
        fr = self.robot_data(st)
        pose = self.transforms.apply(st.name, frame.pose)
        if self.shard.active and not self.shard.accepts(st.name, pose):
            fr.outside_shard += 1
            return None
        rp = fr.reprojection
        if rp is None and pose is frame.pose:
            return frame
        ch: dict[str, Any] = {"pose": pose}
        if rp is not None:
            assert frame.features is not None     # ingest rejects frames without features
            ch["features"] = rp.features(frame.features)
            if frame.global_feature is not None:
                ch["global_feature"] = rp.vector(frame.global_feature)
        return replace(frame, **ch)

    # ------------------------------------------------------------ status
    def _state_of(self, st: RobotState) -> tuple[str, str]:
        fr = self.robot_data(st)
        if fr.refused or st.space_error:
            return "refused", fr.refused or st.space_error
        if not st.space_ok:
            return "pending", "waiting for the robot's feature space (robots/<robot>/feature_space)"
        if self.shard.active and fr.outside_shard and not st.mapped:
            return "accepted", f"frames outside shard {self.shard.name or '(unnamed)'}: mapped by another shard"
        return "accepted", ("re-projected into the map's PCA basis" if fr.reprojection is not None else "")

    def status_of(self, st: RobotState, now: float | None = None) -> dict:
        shared = self.state
        now = time.monotonic() if now is None else now
        fr = self.robot_data(st)
        state, reason = self._state_of(st)
        rates = fr.rates.as_dict(now)
        with_frames = [r for r in shared.robots.values() if r.space_ok and r.fleet is not None
                       and r.fleet.rates.received.rate(now) > 0]
        adv = advised_rate(self.map_rate.rate(now), len(with_frames),
                           {**rates, "queue": len(st.queue)}, st.queue.maxlen or 1) if state == "accepted" else None
        return robot_status(st.name, state, reason, _Counts(st, fr), rates, shared.space_id, self.shard.name, adv)

    def _publish(self, body: dict) -> None:
        from common.robot_messages import encode_robot_status, robot_status_key

        state = self.state
        if state.session is None:
            return
        try:
            assert state.keys is not None         # set with the session
            state.session.put(robot_status_key(state.keys, body["robot"]), encode_robot_status(body))
        except Exception as e:
            state.warn("status", "publishing robot status failed: %s", e)

    def tick(self) -> None:
        """Evictions, pending expiry, status publication (the fleet thread, every 0.5 s)."""
        state = self.state
        now, now_w = time.monotonic(), time.time()
        out = []
        with state.robots_lock:
            for st in state.robots.values():
                self.sample_counts(st, now, now_w)
            for name, n in expire_pending(state.robots.values(), now_w, self.cfg, state.cfg.queues.per_robot):
                st = state.robots[name]
                self.robot_data(st).pending_expired += n
                st.rejected["pending_expired"] += n
                state.rejected["pending_expired"] += n
                self.pending_expired += n
            for name, why in evictions({n: _Evictable(st, self.robot_data(st)) for n, st in state.robots.items()},
                                       now_w, self.cfg):
                st = state.robots.pop(name)
                self.evicted += 1
                self.drops.forget(name)
                self.status.forget(name)
                body = self.status_of(st, now)
                out.append(dict(body, state="evicted", reason=why))
                log.info("robot %s evicted: %s", name, why)
            for st in state.robots.values():
                fr = self.robot_data(st)
                if self.shard.active and not st.mapped and fr.outside_shard and not fr.refused:
                    continue            # another shard's robot: its status comes from there
                body = self.status_of(st, now)
                if self.status.due(st.name, body, now):
                    out.append(body)
        for body in out:
            self._publish(body)

    def loop(self) -> None:
        state = self.state
        while not state.stop.wait(0.5):
            try:
                self.tick()
            except Exception as e:      # the fleet thread never dies
                state.warn("fleet", "fleet bookkeeping failed: %s", e)

    # ------------------------------------------------------------ transforms
    def on_transform(self, query: zenoh.Query) -> None:
        """``get mapper/robots/<robot>/world_from_robot``: payload (16 numbers) sets it; none reads it."""
        from common.messages import encode_error
        from common.robot_messages import (
            FleetMessageError,
            decode_transform_request,
            encode_transform_reply,
            robot_from_mapper_key,
        )

        state = self.state
        try:
            assert state.keys is not None         # the queryable is declared in start()
            robot = robot_from_mapper_key(state.keys, query.key_expr)
            try:
                if robot is None:
                    raise FleetMessageError(f"no robot id in {query.key_expr} (use mapper/robots/<robot>/"
                                            "world_from_robot, no wildcards)")
                vals = decode_transform_request(query.payload.to_bytes()) if query.payload is not None else None
                if vals is not None:
                    T = self.transforms.set(robot, vals)
                    log.info("robot %s world_from_robot set at run time: t=%s", robot,
                             np.round(T[:3, 3], 3).tolist())
                cur = self.transforms.get(robot)
                payload = encode_transform_reply(robot, None if cur is None else cur.reshape(-1).tolist())
            except (FleetMessageError, TransformError) as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("world_from_robot query failed: %s", e)

    # ------------------------------------------------------------ routing
    def routing_bytes(self) -> bytes:
        """This shard's routing announcement (``common.shard_routing``): what it owns, its halo
        and the ``world_from_robot`` transforms it applies now."""
        from common.shard_routing import encode_shard_routing

        reg = replace(self.shard.region, transforms={
            r: np.asarray(v, np.float64).reshape(4, 4) for r, v in self.transforms.as_dict().items()})
        return encode_shard_routing(reg)

    def on_routing(self, query: zenoh.Query) -> None:
        """``get mapper/shards/<name>/routing``: the announcement (edges route frames with it)."""
        try:
            query.reply(query.key_expr, self.routing_bytes())
        except Exception as e:  # never raise out of a zenoh callback
            log.warning("routing query failed: %s", e)

    # ------------------------------------------------------------ queries, stats
    def shard_info(self, res: QueryResult | None = None, half_angle_deg: float | None = None) -> bytes:
        """The shard info attached to query, search and occupancy replies (``common.robot_messages``);
        ``half_angle_deg`` when ``res`` does not carry it (a search)."""
        from common.robot_messages import encode_shard_info

        q = self.state.cfg.query
        info = {"shard": self.shard.name, "search_range_m": float(q.search_range_m),
                "search_cell_m": float(q.search_cell_m), "search_samples": int(q.search_samples),
                "search_rays": int(q.search_rays), "cluster_rel_score": float(q.cluster_rel_score),
                "vox_size": float(self.state.cfg.map.vox_size)}
        sh = self.shard
        if sh.lo is not None and sh.hi is not None:      # a region has both
            info["region"] = [float(v) if np.isfinite(v) else (1e9 if v > 0 else -1e9)
                              for v in (*sh.lo, *sh.hi)]
        if sh.tiles:
            info["tile_m"], info["tiles"] = sh.tile_m, sorted([list(t) for t in sh.tiles])
        if half_angle_deg is not None:
            info["half_angle_deg"] = float(half_angle_deg)
        if res is not None:
            for k, v in (("score_min", res.score_min), ("half_angle_deg", res.half_angle_deg)):
                if v is not None:
                    info[k] = float(v)
        return encode_shard_info(info)

    def stats(self) -> dict:
        return {"robots_tracked": len(self.state.robots), "max_robots": self.cfg.max_robots,
                "refused_robot_cap": self.capped, "evicted": self.evicted, "pending_expired": self.pending_expired,
                "pending_frames": int(sum(len(st.queue) for st in self.state.robots.values() if not st.space_ok)),
                "mapped_hz": round(self.map_rate.rate(), 3), "shard": self.shard.name,
                "world_from_robot": self.transforms.as_dict()}


class _Counts:
    """What :func:`mapper.robot_registry.robot_status` reads from a robot (its state + fleet data)."""

    def __init__(self, st: RobotState, fr: FleetRobot) -> None:
        self.received, self.mapped, self.dropped = st.received, st.mapped, st.dropped
        self.rejected, self.queue, self.feature_space = dict(st.rejected), st.queue, st.feature_space
        self.reprojection = fr.reprojection


class _Evictable:
    """What :func:`mapper.robot_registry.evictions` reads from a robot."""

    def __init__(self, st: RobotState, fr: FleetRobot) -> None:
        self.present, self.gone_at, self.seen_at = st.present, st.gone_at, st.seen_at
        self.space_ok = st.space_ok and not fr.refused
        self.feature_space, self.queue = st.feature_space, st.queue
        self.last_frame_at = fr.last_frame_at


def start_thread(fleet: RobotsJob) -> threading.Thread:
    t = threading.Thread(target=fleet.loop, name="mapper-fleet", daemon=True)
    t.start()
    return t
