"""The mapper process (base station): frames in over Zenoh, one shared RayFronts map out.

:class:`MapperService` only composes the mapper's jobs and owns their lifecycle (Zenoh
entities, threads, close); each job is its own module over one shared
:class:`mapper.state.MapperState`::

    Zenoh                          job (module)                         thread
    ─────────────────────────────  ───────────────────────────────────  ───────────────
    frames, frames/<tile> subscr.  Ingest.on_frame       (ingest)       Zenoh callback (copy only)
                                   Ingest.decode_loop    (ingest)       mapper-decode
    alive/*   liveliness sub       Ingest.on_alive       (ingest)       Zenoh callback
    robots/<r>/feature_space get   Ingest.space_loop     (ingest)       mapper-space
                                   MapWorker.loop        (map_worker)   mapper-map
    mapper/query queryable         QueryServer.on_query  (query_server) Zenoh callback
    mapper/queries/<id> put        QueryServer.standing_loop            mapper-standing
    mapper/stats queryable         QueryServer.on_stats  (query_server) Zenoh callback
    mapper/feature_space queryable QueryServer.on_feature_space         Zenoh callback
    mapper/shards/<name> token     (a named shard's membership)         —
    mapper/shards/<name>/routing   RobotsJob.on_routing      (robots_job)    Zenoh callback
    mapper/snapshot queryable      SnapshotStore.on_snapshot (snapshot_store)
    mapper/search, occupancy       SearchServer.on_search / on_occupancy (search_server) Zenoh callbacks
    mapper/searches/<id> put       SearchServer.standing_loop           mapper-search
    mapper/robots/*/search, occupancy  SearchServer.on_robot_search / on_occupancy   Zenoh callbacks
    mapper/robots/<r>/searches/<id> put  SearchServer.standing_loop     mapper-search
    mapper/fleet_search, robots/*/unreachable  FleetSearchServer.on_fleet_search / on_unreachable (fleet_search)
    mapper/fleet_searches/<id>, robots/<r>/fleet_goal put  FleetSearchServer.standing_loop  mapper-fleet-search
    mapper/layers/* put + get      LayerPublisher        (outputs.layers)
    mapper/robots/<r>/status put   RobotsJob.loop            (robots_job)    mapper-fleet
    mapper/robots/*/world_from_robot queryable  RobotsJob.on_transform      Zenoh callback
    (rerun file / gRPC)            RerunOutput           (outputs.rerun)
    ROS 2 topics (rmw_zenoh/bridge) RosOutput            (outputs.ros)   mapper-ros, Zenoh callbacks

Module map: ARCHITECTURE.md; locks and events: :mod:`mapper.state`. The service's
attributes ``map``, ``lock``, ``robots_lock``, ``mapped``, ``robots``, ... read and write the shared state.
"""
from __future__ import annotations

import json
import logging
import threading
from typing import TYPE_CHECKING

from common.zenoh_session import close_quietly, undeclare_all
from mapper.ingest import Ingest
from mapper.map_worker import MapWorker
from mapper.outputs.layers import LayerPublisher
from mapper.query_server import QueryServer
from mapper.service_config import set_torch_threads
from mapper.snapshot_store import SnapshotStore
from mapper.state import MapperState

if TYPE_CHECKING:
    from common.messages import QueryRequest, QueryResult
    from mapper.outputs.rerun import RerunOutput
    from mapper.outputs.ros import RosOutput

__all__ = ["MapperService"]

log = logging.getLogger("rayfronts.mapper")


def _shared(attr: str, doc: str = ""):
    """A service attribute that is the shared state's ``attr`` (reads and writes go to it)."""
    return property(lambda self: getattr(self.state, attr), lambda self, v: setattr(self.state, attr, v), doc=doc)


class MapperService:
    """One mapper: Zenoh entities, per-robot queues, the map and its mapping thread.

    ``start()`` opens everything and returns; ``close()`` stops and releases it (idempotent).
    ``run()`` = start, wait for ``stop``, close."""

    map = _shared("map", "the RayFronts map (None until the first robot's feature space is known)")
    space = _shared("space", "FeatureSpace of the map")
    space_reply = _shared("space_reply")
    map_gen = _shared("map_gen", "bumps on every change of the map (under `lock`)")
    lock = _shared("lock", "the map lock (map + feature space)")
    robots_lock = _shared("robots_lock", "robot table + queues")
    query_lock = _shared("query_lock", "serialises queries; taken before `lock`")
    robots = _shared("robots")
    rejected = _shared("rejected")
    received = _shared("received")
    mapped = _shared("mapped")
    dropped = _shared("dropped")
    started = _shared("started")
    version = _shared("version")
    flushed_version = _shared("flushed_version")
    first_mapped_at = _shared("first_mapped_at")
    last_mapped_at = _shared("last_mapped_at")
    timings = _shared("timings")
    standing = _shared("standing")
    last_snapshot = _shared("last_snapshot")
    session = _shared("session")
    keys = _shared("keys")
    _wake = _shared("wake")
    _space_wake = _shared("space_wake")
    _standing_due = _shared("standing_due")

    def __init__(self, cfg, stop: threading.Event | None = None):
        self.cfg = cfg
        self.stop = stop or threading.Event()
        self.state = MapperState(cfg, self.stop)
        self.ingest = Ingest(self.state)
        self.queries = QueryServer(self.state)
        self.snapshots = SnapshotStore(self.state)
        self.layers = LayerPublisher(self.state)
        self.worker = MapWorker(self.state, self.ingest.next_frame, self.layers, self.snapshots)
        from mapper.robots_job import RobotsJob

        self.fleet = RobotsJob(self.state)         # several robots: status, bounds, transforms, shard
        self.rerun: RerunOutput | None = None  # once started with rerun.file / rerun.serve_grpc
        self.ros: RosOutput | None = None      # once started with ros.enabled
        self._entities: list = []
        self._threads: list[threading.Thread] = []
        self._closed = False

    @property
    def space_id(self) -> str:
        """Id of the map's feature space ("" before the map exists)."""
        return self.state.space_id

    @property
    def _qsnap(self):
        return self.queries.qsnap

    # ================================================================== lifecycle
    def start(self) -> "MapperService":
        from common.keys import KeySpace
        from common.robot_messages import robot_transform_all
        from common.zenoh_session import open_session
        from mapper.service_config import resolve_query_threads

        self.keys = KeySpace(self.cfg.zenoh.prefix)
        log.info("torch threads: %d (mapping), %d (queries)", self._set_threads(),
                 resolve_query_threads(self.cfg.query.threads))
        if self.cfg.snapshots.dir and self.cfg.snapshots.restore:
            self.snapshots.restore()
        if self.cfg.rerun.file or self.cfg.rerun.serve_grpc or self.cfg.rerun.serve_web:
            from mapper.outputs.rerun import RerunLogger, RerunOutput

            self._attach_rerun(RerunOutput(self.state, RerunLogger.from_config(self.cfg)))
        self.session = session = open_session(self.cfg.zenoh, stop=self.stop, default_mode="router")
        keys = self.keys
        try:
            self._entities = [
                *self._frame_subscribers(session),
                session.liveliness().declare_subscriber(keys.alive_all, self.ingest.on_alive, history=True),
                session.declare_subscriber(keys.edge_status_all, self.ingest.on_edge_status),
                session.declare_queryable(keys.mapper_query, self.queries.on_query),
                session.declare_queryable(keys.stats, self.queries.on_stats),
                session.declare_queryable(keys.mapper_feature_space, self.queries.on_feature_space),
                session.declare_queryable(keys.snapshot, self.snapshots.on_snapshot),
                session.declare_queryable(keys.layers_all, self.layers.on_layer_get),
                session.declare_queryable(robot_transform_all(keys), self.fleet.on_transform),
                *([session.declare_queryable(keys.mapper_shard_routing(self.cfg.shard.name), self.fleet.on_routing),
                   session.liveliness().declare_token(keys.mapper_shard_alive(self.cfg.shard.name))]
                  if self.cfg.shard.name else []),
                session.liveliness().declare_token(keys.mapper_alive),
            ]
            from mapper.search_server import start_search_server

            self.search, ents, t = start_search_server(self.state, self.queries, session, keys)
            self._entities[-1:-1] = ents          # before the liveliness token
            self._threads.append(t)
            from mapper.fleet_search import start_fleet_search

            self.search.fleet, ents, t = start_fleet_search(self.state, self.search, session, keys)
            self._entities[-1:-1] = ents
            self._threads.append(t)
        except Exception:
            self.close()
            raise
        for name, fn in (("mapper-decode", self.ingest.decode_loop), ("mapper-map", self.worker.loop),
                         ("mapper-space", self.ingest.space_loop), ("mapper-standing", self.queries.standing_loop),
                         ("mapper-fleet", self.fleet.loop)):
            t = threading.Thread(target=fn, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        if self.cfg.ros.enabled:  # the map as ROS 2 topics (RViz2)
            from mapper.outputs.ros import RosOutput

            try:
                self.ros = RosOutput(self.state, search=self.search).start()
            except Exception:
                self.close()
                raise
        log.info("mapper up (zid %s, prefix %r)", session.zid(), self.cfg.zenoh.prefix)
        return self

    def _frame_subscribers(self, session) -> list:
        """Frame subscribers (docs/key_space.md#shards): a named shard takes the plain key and the
        frames addressed to it (routed by the edges), plus with ``shard.tile_m`` the tile keys of
        its tiles; an unnamed mapper takes every frame key."""
        from mapper.shards import MAX_TILE_SUBSCRIPTIONS, ShardFilter

        shard = self.cfg.shard
        tiles = ShardFilter(shard).subscription_tiles(shard)
        if tiles is None and shard.tile_m > 0:
            log.warning("shard %s: no bounded tile set (shard.tiles / a finite region, at most %d tiles); "
                        "subscribing to every frame", shard.name or "(unnamed)", MAX_TILE_SUBSCRIPTIONS)
        if not shard.name or (tiles is None and shard.tile_m > 0):
            keys = [self.keys.frames_all, self.keys.frames_tiled_all]
        else:
            keys = [self.keys.frames_all, self.keys.frames_routed_all(shard.name),
                    *(self.keys.frames_tile_all(t) for t in sorted(tiles or ()))]
            log.info("shard %s: subscribed to its routed frames%s", shard.name,
                     f" and {len(tiles)} frame tiles" if tiles else "")
        return [session.declare_subscriber(k, self.ingest.on_frame) for k in keys]

    def _attach_rerun(self, rerun) -> None:
        self.rerun = rerun
        self.worker.rerun = rerun
        self.queries.rerun = rerun
        self.layers.followers.append(rerun)

    def _set_threads(self, query: bool = False) -> int:
        """Set the calling thread's torch threads (see :func:`mapper.service_config.set_torch_threads`)."""
        return set_torch_threads(self.cfg, query=query)

    def run(self) -> int:
        """Start, serve until stopped, close (the ``rayfronts mapper`` process)."""
        from mapper.service_config import freeze_startup_objects

        self.start()
        log.info("%d start-up objects frozen out of the garbage collector", freeze_startup_objects())
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
        if self.ros is not None:
            self.ros.close()
            self.ros = None
        # queryables go with the session: with zenoh 1.10 an explicit undeclare leaves a stale
        # route in the router when another mapper (a shard) serves the same key, and every
        # fan-out get then waits its whole timeout for this one (tests/test_shards.py)
        import zenoh

        undeclare_all(e for e in reversed(self._entities) if not isinstance(e, zenoh.Queryable))
        self._entities = []
        close_quietly(self.session)
        self.session = None
        if self.cfg.snapshots.dir and self.cfg.snapshots.on_exit and self.map is not None:
            try:
                self.save_snapshot()
            except Exception as e:
                log.error("snapshot on exit failed: %s", e)
        close_quietly(self.rerun, "the rerun output")
        self.rerun = None
        log.info("mapper closed: %s", json.dumps(self.stats()["frames"]))

    # ============================================ the jobs' entry points, as before
    def _space_loop(self) -> None:
        self.ingest.space_loop()

    def run_query(self, req: QueryRequest) -> QueryResult:
        return self.queries.run_query(req)

    def stats(self) -> dict:
        return self.queries.stats()

    def save_snapshot(self) -> dict:
        return self.snapshots.save()

    def layer_bytes(self, layer: str) -> bytes:
        return self.layers.layer_bytes(layer)
