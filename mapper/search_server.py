"""The planners' queryables: ``<p>/mapper/search`` (find targets, where to look next, what
lies beyond) and ``<p>/mapper/occupancy`` (box / slice / points), plus standing searches
published on ``<p>/mapper/searches/<id>`` (module map: ARCHITECTURE.md). A robot's onboard
planner asks the same on ``<p>/mapper/robots/<robot>/search`` / ``occupancy`` (the site ACL
lets a robot certificate ask only its own); its standing searches are published on
``<p>/mapper/robots/<robot>/searches/<id>``. Standing searches are leased and capped
(:mod:`mapper.leases`).

A search runs like a query (:class:`mapper.query_server.QueryServer`): under
``state.query_lock``, on the query copy of the current map generation (the map worker is
first asked to flush buffered frames), scoring outside the map lock; it takes the map lock
again only to read occupancy and frontiers for look-next goals (at most
``search.lock_timeout_s``; past it the reply has no goals and ``timings_ms.stale = 1``).
The identity trackers (one per target, docs/identity.md) live in ``state.trackers``, so ids
stay stable across searches.
Scoring and answering: :mod:`mapper.search_answer`. Occupancy read-outs:
:mod:`planning.occupancy_queries`, under the map lock, bounded by
``search.max_occupancy_cells``.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Iterable

from common.messages import MessageError
from common.search_messages import (
    OccupancyReply,
    SearchReply,
    SearchRequest,
    decode_occupancy_request,
    decode_search_request,
    encode_occupancy_reply,
    encode_search_reply,
)
from mapper.replies import reply_to
from mapper.search_answer import answer_search
from mapper.service_config import set_torch_threads

log = logging.getLogger("rayfronts.mapper")


#: standing searches are re-run at most this often (s) when the map changed
STANDING_PERIOD_S = 1.0


class SearchServer:
    """Search and occupancy answers against the shared map (``queries``: the
    :class:`mapper.query_server.QueryServer` whose snapshot a search reads)."""

    def __init__(self, state, queries):
        self.state = state
        self.queries = queries
        self.trackers = state.trackers
        self.standing: dict[str, SearchRequest] = state.standing_searches
        self._last_gen: dict[str, int] = {}
        self.half_angle_deg: float | None = None     # the search volume's cone half-angle, for the shard info
        self.fleet = None                  # mapper.fleet_search.FleetSearchServer (set by the service)

    def _read_map(self, fn):
        """``fn(map)`` under the map lock (None when the lock stays busy past the timeout)."""
        s = self.state
        if not s.lock.acquire(timeout=max(0.0, float(s.cfg.search.lock_timeout_s))):
            return None
        try:
            return fn(s.map) if s.map is not None else None
        finally:
            s.lock.release()

    def run_search(self, req: SearchRequest, flush: bool = False) -> SearchReply:
        """Answer one search (raises :class:`MessageError` for an empty map or bad input)."""
        s = self.state
        t0 = time.perf_counter()
        if s.map is None or s.space is None:
            raise MessageError("the map is empty (no frames mapped yet)")
        with s.query_lock:
            set_torch_threads(s.cfg, query=True)
            timings: dict = {}
            snap = self.queries.query_copy(timings, flush=flush)
            rep = answer_search(snap, s.space, req, s.cfg, self.trackers, self._read_map, map_version=s.version)
            self.half_angle_deg = float(snap.half_angle)
        rep.timings_ms.update({k: float(v) for k, v in timings.items()})
        rep.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
        rerun = getattr(self.queries, "rerun", None)  # the mapper's rerun output, if any
        if rerun is not None:
            rerun.search_answered(rep, req)
        return rep

    def similarities(self, texts: list[str], softmax: bool) -> tuple:
        """:func:`mapper.search_answer.text_similarities` on the current map's query copy,
        plus the snapshot's ray origins and directions: ``(voxel xyz, voxel scores, ray
        origins, ray directions, ray scores)``; MessageError for an empty map."""
        from mapper.search_answer import text_similarities

        s = self.state
        if s.map is None or s.space is None:
            raise MessageError("the map is empty (no frames mapped yet)")
        with s.query_lock:
            set_torch_threads(s.cfg, query=True)
            snap = self.queries.query_copy({})
            vxyz, vs, rs = text_similarities(snap, s.space, list(texts), s.cfg, softmax)
            return vxyz, vs, snap.ray_origins.copy(), snap.ray_dirs.copy(), rs

    def _owned(self, req: SearchRequest, asker: str) -> bool:
        """Whether standing search ``req.id`` exists and belongs to ``asker`` (a robot id, or ""
        for the operators' key); one held by someone else is refused in one line."""
        held = self.standing.get(req.id)
        if held is None:
            return False
        if held.owner != asker:
            raise MessageError(f"standing search {req.id!r} belongs to "
                               f"{('robot ' + held.owner) if held.owner else 'the operators'}, not to "
                               f"{('robot ' + asker) if asker else 'the operators'}: use another id")
        return True

    def search_payload(self, data: bytes, asker: str = "") -> bytes:
        """Answer an encoded search request asked on the key of robot ``asker`` ("" = the
        operators' ``<p>/mapper/search``): an encoded reply (a cancel, a renewal, or a standing
        search registered before the map exists, gets an empty one). Standing searches are
        leased (:mod:`mapper.leases`) and owned by ``asker``: only it may renew or cancel them,
        and their results go to its key (``searches_key``)."""
        req = decode_search_request(data)
        req.owner = asker
        leases = self.state.search_leases
        if req.cancel:
            if self._owned(req, asker):
                self.standing.pop(req.id, None)
                leases.drop(req.id)
            return encode_search_reply(SearchReply(id=req.id))
        if req.renew:
            leases.renew(req.id, self._owned(req, asker))
            return encode_search_reply(SearchReply(id=req.id))
        fresh = False
        if req.standing:
            fresh = not self._owned(req, asker)
            req.client = f"robot-{asker}" if asker else (req.client or "anonymous")
            leases.admit(req.id, req.client, req.lease_s, len(self.standing))
            if self.state.map is None:
                # registered before any frame: answered (and published) once the map exists
                self.standing[req.id] = req
                return encode_search_reply(SearchReply(id=req.id))
        try:
            rep = self.run_search(req, flush=True)
        except Exception:
            if fresh:
                leases.drop(req.id)
            raise
        if req.standing:
            self.standing[req.id] = req
            self._last_gen[req.id] = self.state.map_gen
        return encode_search_reply(rep)

    def searches_key(self, req: SearchRequest) -> str:
        """Where standing search ``req`` is published: its robot's key, or ``<p>/mapper/searches/<id>``."""
        keys = self.state.keys
        return keys.robot_searches(req.owner, req.id) if req.owner else keys.mapper_searches(req.id)

    def asker(self, query) -> str:
        """The robot a robot-scoped planner key names (its certificate may ask only its own)."""
        robot = self.state.keys.asker_from_key(query.key_expr)
        if robot is None:
            raise MessageError(f"{query.key_expr}: ask on <prefix>/mapper/robots/<robot id>/... with one "
                               "robot id (no wildcards)")
        return robot

    def shard_info(self) -> bytes | None:
        """The shard info attached to search / occupancy replies and standing-search puts
        (``common.robot_messages``: the client merges several shards' answers with it)."""
        fleet = self.state.fleet
        return None if fleet is None else fleet.shard_info(half_angle_deg=self.half_angle_deg)

    def on_search(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/search``: one reply, a search reply or an error."""
        reply_to(query, "search", self.search_payload, self.shard_info)

    def on_robot_search(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/robots/*/search``: a robot's own search."""
        reply_to(query, "search", lambda data: self.search_payload(data, self.asker(query)), self.shard_info)

    def occupancy(self, data: bytes) -> OccupancyReply:
        """Answer an encoded occupancy request (under the map lock)."""
        from planning.occupancy_queries import costmap_slice, point_states, state_grid

        req = decode_occupancy_request(data)
        s = self.state
        limit = int(s.cfg.search.max_occupancy_cells)
        with s.lock:
            m = s.map
            if m is None:
                raise MessageError("the map is empty (no frames mapped yet)")
            vox, grid = float(m.cfg.vox_size), m.occupancy_view()
            rep = OccupancyReply(kind=req.kind, frames_mapped=int(s.mapped), map_version=int(s.version))
            origin: Iterable[float]                  # the grid's corner (m); none for points
            if req.kind == "box":                    # validate() checked what each kind needs
                assert req.box_min is not None and req.box_max is not None
                rep.states, origin, rep.cell_m = state_grid(grid, vox, req.box_min, req.box_max, req.stride,
                                                            max_cells=limit)
            elif req.kind == "slice":
                assert req.box_min is not None and req.box_max is not None and req.z_band is not None
                rep.states, origin, rep.cell_m = costmap_slice(grid, vox, req.box_min, req.box_max,
                                                               req.z_band, req.stride, max_cells=limit)
            else:
                assert req.points is not None
                rep.states, rep.dist = point_states(grid, vox, req.points, float(req.radius), max_cells=limit)
                origin, rep.cell_m = [], vox
        rep.origin = [float(v) for v in origin]
        return rep

    def on_occupancy(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/occupancy`` and ``<p>/mapper/robots/*/occupancy``
        (the same answer for a robot: occupancy is not per robot)."""
        def answer(data: bytes) -> bytes:
            if str(query.key_expr) != self.state.keys.mapper_occupancy:
                self.asker(query)
            return encode_occupancy_reply(self.occupancy(data))

        reply_to(query, "occupancy request", answer, self.shard_info)

    def standing_loop(self) -> None:
        """Re-runs standing searches after map changes (at most every :data:`STANDING_PERIOD_S`)
        and publishes them on ``<p>/mapper/searches/<id>``."""
        s = self.state
        while not s.stop.wait(STANDING_PERIOD_S):
            for sid in s.search_leases.expired():
                self._last_gen.pop(sid, None)
                if self.standing.pop(sid, None) is not None:
                    log.info("standing search %s ended: its lease ran out (the client is gone)", sid)
            for sid, req in list(self.standing.items()):
                if s.map is None or self._last_gen.get(sid) == s.map_gen:
                    continue
                self._last_gen[sid] = s.map_gen
                try:
                    rep = self.run_search(req)
                    s.session.put(self.searches_key(req), encode_search_reply(rep), attachment=self.shard_info())
                except Exception as e:
                    s.warn(f"search:{sid}", "standing search %s failed: %s", sid, e)


def start_search_server(state, queries, session, keys) -> tuple[SearchServer, list, threading.Thread]:
    """Declare the search and occupancy queryables and start the standing-search thread:
    ``(server, zenoh entities, thread)``."""
    srv = SearchServer(state, queries)
    ents = [session.declare_queryable(keys.mapper_search, srv.on_search),
            session.declare_queryable(keys.mapper_occupancy, srv.on_occupancy),
            session.declare_queryable(keys.robot_search_all, srv.on_robot_search),
            session.declare_queryable(keys.robot_occupancy_all, srv.on_occupancy)]
    t = threading.Thread(target=srv.standing_loop, name="mapper-search", daemon=True)
    t.start()
    return srv, ents, t
