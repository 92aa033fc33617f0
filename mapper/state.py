"""What the mapper's jobs share: the map, its feature space, the robot table, counters, locks
and the wake-up events (one :class:`MapperState` per :class:`mapper.service.MapperService`).

The mapper's module map (which job lives where, and its thread) is ARCHITECTURE.md, "mapper/".

Locking: ``lock`` (the map lock) guards the map and its feature space; ``robots_lock`` the robot
table and queues; ``query_lock`` serialises queries (one-shot and standing), always taken
*before* ``lock``. ``map_gen`` bumps on every change of the map (under ``lock``): integrate,
flush, create and restore.

Events: every thread waits on its own event, so no thread polls while frames queue: ``wake``
(map worker: a frame or a robot changed), ``space_wake`` (ingest's feature-space thread: a
robot needs its space fetched), ``standing_due`` (query server: the map changed and standing
queries are due). A one-shot query first asks the map worker to flush the frames the map
still buffers (``request_flush`` / ``flush_wanted`` / ``flush_done`` under ``flush_cv``), so it
sees every frame counted in ``frames.mapped`` before it arrived (see
:mod:`mapper.query_server`).
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from common.wire import WireLimits

if TYPE_CHECKING:
    import zenoh

    from common.feature_space import FeatureSpace
    from common.keys import KeySpace
    from mapper.service_config import MapperConfig
    from semantic_map.map import RayFrontsMap

log = logging.getLogger("rayfronts.mapper")


class RateLimitedLog:
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
    seq_regressions: int = 0         # mapped frames whose seq was not above the last one (edge restart)
    fleet: Any = None                # mapper.robots_job.FleetRobot (rates, re-projection, shard counts; Any: no cycle)
    edge_state: str = ""             # the edge's own state (robots/<robot>/edge_status): running, refused, ...
    edge_reason: str = ""            # why, for refused / failed
    pose: np.ndarray | None = None   # (4, 4) world pose of its last mapped frame (after world_from_robot)
    pose_stamp: float = 0.0          # that frame's stamp (s): the robot's own clock

    def as_dict(self) -> dict:
        d = {"received": self.received, "mapped": self.mapped, "dropped": self.dropped,
             "rejected": dict(self.rejected), "queue": len(self.queue), "present": self.present,
             "seen_at": self.seen_at, "gone_at": self.gone_at, "feature_space": self.feature_space,
             "space_ok": self.space_ok, "space_error": self.space_error, "last_seq": self.last_seq,
             "edge_state": self.edge_state, "edge_reason": self.edge_reason,
             "seq_regressions": self.seq_regressions}
        if self.fleet is not None:
            d.update(self.fleet.as_dict())
        if self.edge_cpu is not None and self.edge_cpu_frames > 0:
            # the robot's edge process CPU per frame, over its mapped frames (frame meta cpu_s)
            d["edge_cpu_ms_per_frame"] = (self.edge_cpu[1] - self.edge_cpu[0]) * 1e3 / self.edge_cpu_frames
        return d


class _DiscardQueue(collections.deque):
    """A queue that keeps nothing (the stand-in robot of ids over ``fleet.max_robots``)."""

    def append(self, item: object) -> None:
        pass


class Percentiles:
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


class MapperState:
    """The mutable state every mapper job reads and writes (see the module docstring for locks).

    ``session`` / ``keys`` are the Zenoh session and key space, set by ``MapperService.start``.
    """

    def __init__(self, cfg: MapperConfig, stop: threading.Event) -> None:
        self.cfg = cfg
        self.stop = stop
        self.lock = threading.RLock()          # map + feature space
        self.robots_lock = threading.Lock()          # robot table + queues
        self.query_lock = threading.Lock()     # serialises queries; taken before `lock`
        self.map_gen = 0                       # bumps on every change of the map (under `lock`)
        self.map: RayFrontsMap | None = None
        self.space: FeatureSpace | None = None   # FeatureSpace of the map
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
        self.snap_version = -1                 # version at the last snapshot
        self.snap_trackers = 0                 # trackers.generation at the last snapshot
        self.first_mapped_at: float | None = None
        self.last_mapped_at: float | None = None
        self.cpu_mapped: list[float] = []      # process CPU s at the first and the last integration
        self.standing: dict = {}               # standing query id -> QueryRequest
        self.standing_searches: dict = {}      # standing search id -> SearchRequest (mapper.search_server)
        from mapper.leases import Leases

        q, sc = cfg.query, cfg.search          # leases and caps of the standing requests clients register
        self.query_leases = Leases("standing query", "query", q.lease_s, q.max_standing, q.max_standing_per_client)
        self.search_leases = Leases("standing search", "search", sc.lease_s, sc.max_standing,
                                    sc.max_standing_per_client)
        from mapper.search_answer import TrackerStore

        self.trackers = TrackerStore(cfg.search.max_trackers)   # identity trackers; saved in snapshots
        self.last_snapshot: dict = {}          # what the last save / restore wrote or read
        self.text_warm_up_s: float | None = None  # seconds the text model's warm-up took (None: not done)
        self.timings = {"integrate_ms": Percentiles(), "integrate_cpu_ms": Percentiles(),
                        "latency_ms": Percentiles(), "query_ms": Percentiles(), "decode_ms": Percentiles()}
        self.warn = RateLimitedLog()
        self.limits = WireLimits(max_message_bytes=int(cfg.queues.max_message_mb * (1 << 20)))
        self.session: zenoh.Session | None = None
        self.keys: KeySpace | None = None
        self.wake = threading.Event()          # map worker: a frame or a robot changed
        self.space_wake = threading.Event()    # feature-space thread: a robot needs its space (re)fetched
        self.standing_due = threading.Event()  # query server: standing queries are due
        # a one-shot query asks the map worker to flush what the map buffers (request_flush)
        self.flush_cv = threading.Condition()
        self.flush_asked = 0                   # tickets handed out (under flush_cv)
        self.flush_served = 0                  # tickets the map worker has served (under flush_cv)
        # mapper.robots_job.RobotsJob (set by the service; Any: that module imports this one)
        self.fleet: Any = None
        self.fleet_search: Any = None          # mapper.fleet_search.FleetSearchServer (set by the service)
        self._overflow: RobotState | None = None   # stands in for ids over fleet.max_robots

    @property
    def space_id(self) -> str:
        """Id of the map's feature space ("" before the map exists), computed once per space."""
        fs = self.space
        if fs is None:
            return ""
        if self._space_id[0] is not fs:
            self._space_id = (fs, fs.id)
        return self._space_id[1]

    def robot(self, name: str) -> RobotState:
        """The robot's state, created on first sight (caller holds ``robots_lock``)."""
        st = self.robots.get(name)
        if st is None and self.fleet is not None and not self.fleet.admit(name):
            # over fleet.max_robots: one shared stand-in, never in the robot table, never mapped,
            # whose queue keeps nothing (counted under robot_cap, nothing kept per id)
            if self._overflow is None:
                self._overflow = RobotState("_over_robot_cap", _DiscardQueue())
            return self._overflow
        if st is None:
            st = RobotState(name, collections.deque(maxlen=max(1, self.cfg.queues.per_robot)))
            self.robots[name] = st
            st.seen_at = time.time()
            self.wake.set()
            self.space_wake.set()
        return st

    def request_flush(self, timeout: float) -> bool:
        """Ask the map worker to integrate what the map buffers (frames committed but not yet
        in a voxel / ray block) and wait at most ``timeout`` s; True once it has."""
        with self.flush_cv:
            self.flush_asked += 1
            ticket = self.flush_asked
        self.wake.set()
        with self.flush_cv:
            return bool(self.flush_cv.wait_for(lambda: self.flush_served >= ticket or self.stop.is_set(),
                                               max(0.0, timeout))) and self.flush_served >= ticket

    def flush_wanted(self) -> int:
        """The newest flush ticket not yet served (0: none)."""
        with self.flush_cv:
            return self.flush_asked if self.flush_asked > self.flush_served else 0

    def flush_done(self, ticket: int) -> None:
        """The map worker has served every ticket up to ``ticket``."""
        with self.flush_cv:
            self.flush_served = max(self.flush_served, ticket)
            self.flush_cv.notify_all()

    def reject(self, robot: str | None, reason: str, detail: str) -> None:
        """Count a rejected frame (globally and for its robot) and log it, rate-limited."""
        with self.robots_lock:
            self.rejected[reason] += 1
            if robot is not None and robot in self.robots:
                self.robots[robot].rejected[reason] += 1
        self.warn(f"{robot}:{reason}", "rejected frame from %s (%s): %s", robot, reason, detail[:200])

    def create_map(self, fs: FeatureSpace, envelope: bytes) -> None:
        """A new map in feature space ``fs`` (caller holds ``lock``)."""
        from mapper.service_map import create_map

        self.map = create_map(self.cfg, fs)
        self.map_gen += 1
        self.space = fs
        self.space_reply = envelope
        log.info("map created in feature space %s (dim %d)", fs.id, fs.dim)
        self.warm_up_text(fs)

    def warm_up_text(self, fs: FeatureSpace) -> threading.Thread | None:
        """Load the text model of ``fs`` and embed the search background on a daemon thread
        (``search.warm_up``), so the first query or search does not wait for them. The time
        it took is ``text_warm_up_s`` in stats."""
        if not self.cfg.search.warm_up:
            return None

        def run() -> None:
            from mapper.query_answer import warm_up_text

            try:
                self.text_warm_up_s = warm_up_text(fs, list(self.cfg.search.background), self.cfg.device,
                                                   self.cfg.text_model_dir, self.cfg.query.templates)
                log.info("text model %s ready (%.1f s)", fs.text_model, self.text_warm_up_s)
            except Exception as e:  # a query will load it (and report the error) later
                self.warn("text-warm-up", "loading the text model %s failed: %s", fs.text_model, e)

        t = threading.Thread(target=run, name="text-warm-up", daemon=True)
        t.start()
        return t


def jsonable(x: object) -> Any:
    """``x`` with numpy scalars/arrays turned into Python values and unknown objects into str."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)
