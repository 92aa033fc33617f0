"""The planners' queryables: ``<p>/mapper/search`` (find targets, where to look next, what
lies beyond) and ``<p>/mapper/occupancy`` (box / slice / points), plus standing searches
published on ``<p>/mapper/searches/<id>`` (module map: :mod:`mapper.state`).

A search runs like a query (:class:`mapper.query_server.QueryServer`): under
``state.query_lock``, on the query snapshot of the current map generation (the map worker is
first asked to flush buffered frames), scoring outside the map lock; it takes the map lock
again only to read occupancy and frontiers for look-next goals (at most
``search.lock_timeout_s``; past it the reply has no goals and ``timings_ms.stale = 1``).
The instance trackers (one per target set) live here, so ids stay stable across searches.
Scoring and answering: :mod:`mapper.search_answer`. Occupancy read-outs:
:mod:`semantic_map.occupancy_queries`, under the map lock, bounded by
``search.max_occupancy_cells``.
"""
from __future__ import annotations

import logging
import threading
import time

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
            snap = self.queries.snapshot(timings, flush=flush)
            rep = answer_search(snap, s.space, req, s.cfg, self.trackers, self._read_map, map_version=s.version)
            self.half_angle_deg = float(snap.half_angle)
        rep.timings_ms.update({k: float(v) for k, v in timings.items()})
        rep.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
        rerun = getattr(self.queries, "rerun", None)  # the mapper's rerun output, if any
        if rerun is not None:
            rerun.search_answered(rep, req)
        return rep

    def search_payload(self, data: bytes) -> bytes:
        """Answer an encoded search request: an encoded reply (a cancel, or a standing search
        registered before the map exists, gets an empty one)."""
        req = decode_search_request(data)
        if req.cancel:
            self.standing.pop(req.id, None)
            return encode_search_reply(SearchReply(id=req.id))
        if req.standing and self.state.map is None:
            # registered before any frame: answered (and published) once the map exists
            self.standing[req.id] = req
            return encode_search_reply(SearchReply(id=req.id))
        rep = self.run_search(req, flush=True)
        if req.standing:
            self.standing[req.id] = req
            self._last_gen[req.id] = self.state.map_gen
        return encode_search_reply(rep)

    def shard_info(self) -> bytes | None:
        """The shard info attached to search / occupancy replies and standing-search puts
        (``common.fleet``: the client merges several shards' answers with it)."""
        fleet = self.state.fleet
        return None if fleet is None else fleet.shard_info(half_angle_deg=self.half_angle_deg)

    def on_search(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/search``: one reply, a search reply or an error."""
        reply_to(query, "search", self.search_payload, self.shard_info)

    def occupancy(self, data: bytes) -> OccupancyReply:
        """Answer an encoded occupancy request (under the map lock)."""
        from semantic_map.occupancy_queries import costmap_slice, point_states, state_grid

        req = decode_occupancy_request(data)
        s = self.state
        limit = int(s.cfg.search.max_occupancy_cells)
        with s.lock:
            m = s.map
            if m is None:
                raise MessageError("the map is empty (no frames mapped yet)")
            vox = float(m.cfg.vox_size)
            rep = OccupancyReply(kind=req.kind, frames_mapped=int(s.mapped), map_version=int(s.version))
            if req.kind == "box":
                rep.states, origin, rep.cell_m = state_grid(m.occupancy, vox, req.box_min, req.box_max, req.stride,
                                                            max_cells=limit)
            elif req.kind == "slice":
                rep.states, origin, rep.cell_m = costmap_slice(m.occupancy, vox, req.box_min, req.box_max,
                                                               req.z_band, req.stride, max_cells=limit)
            else:
                rep.states, rep.dist = point_states(m.occupancy, vox, req.points, float(req.radius), max_cells=limit)
                origin, rep.cell_m = [], vox
        rep.origin = [float(v) for v in origin]
        return rep

    def on_occupancy(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/occupancy``."""
        reply_to(query, "occupancy request", lambda data: encode_occupancy_reply(self.occupancy(data)),
                 self.shard_info)

    def standing_loop(self) -> None:
        """Re-runs standing searches after map changes (at most every :data:`STANDING_PERIOD_S`)
        and publishes them on ``<p>/mapper/searches/<id>``."""
        s = self.state
        while not s.stop.wait(STANDING_PERIOD_S):
            for sid, req in list(self.standing.items()):
                if s.map is None or self._last_gen.get(sid) == s.map_gen:
                    continue
                self._last_gen[sid] = s.map_gen
                try:
                    rep = self.run_search(req)
                    s.session.put(s.keys.mapper_searches(sid), encode_search_reply(rep), attachment=self.shard_info())
                except Exception as e:
                    s.warn(f"search:{sid}", "standing search %s failed: %s", sid, e)


def start_search_server(state, queries, session, keys) -> tuple[SearchServer, list, threading.Thread]:
    """Declare the search and occupancy queryables and start the standing-search thread:
    ``(server, zenoh entities, thread)``."""
    srv = SearchServer(state, queries)
    ents = [session.declare_queryable(keys.mapper_search, srv.on_search),
            session.declare_queryable(keys.mapper_occupancy, srv.on_occupancy)]
    t = threading.Thread(target=srv.standing_loop, name="mapper-search", daemon=True)
    t.start()
    return srv, ents, t
