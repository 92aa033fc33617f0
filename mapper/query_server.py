"""The mapper's query side: the query and stats queryables, standing queries and ``stats()``
(module map: :mod:`mapper.state`; ARCHITECTURE.md).

A query holds the map lock only to bring its copy of the map
(:class:`mapper.query_answer.QueryCopy`) up to date: the copy is maintained
incrementally (only the voxel rows the map changed since the last query are copied, and
their prepared norms recomputed outside the lock), so the lock is held for O(changed rows),
not O(N·dim), and the first query after a change costs about what a later one does. It
scores, clusters and measures outside the lock, so mapping goes on meanwhile. A query waits
at most ``query.lock_timeout_s`` for the map lock (held while one frame is integrated);
after that it is answered from the last consistent copy and the reply says so:
``timings.stale = 1``, ``timings.stale_gens`` = map changes it does not include,
``frames_mapped`` = the map state it reflects.

A one-shot query sees every frame mapped before it arrived: frames are committed into the
map's accumulation buffers (``map.vox_accum_period`` / ``ray_accum_period`` frames per
block) and only become voxels at the next block or the idle flush, so when the map buffers
frames the query first asks the map worker to flush them (``MapperState.request_flush``;
the worker serves it before its next frame: at most one frame's integration plus one
voxel and one ray block). That wait and the lock wait share the ``query.lock_timeout_s``
budget; past it the query goes on (``timings.flush_pending = 1``; ``flush_wait`` = ms
waited). Standing queries do not flush (they re-run on each map change anyway), so the
map's block schedule is left alone by them. Queries are serialised by
``state.query_lock`` (taken before the map lock) and run with ``query.threads`` torch threads
(auto: all CPUs; scoring is one big matrix product). Standing queries run on their own thread
(``mapper-standing``), woken by the map worker through ``state.standing_due``.

``stats()`` reports the map thread's CPU per integration (``timings.integrate_cpu_ms``), the
process CPU from the first to the last integration (``cpu_s.mapping``) and, per robot, the
edge's CPU per frame from the ``cpu_s`` its frames carry in their meta
(``edge_cpu_ms_per_frame``). How a query is scored (text embedding, softmax, clustering,
search volume) lives in :mod:`mapper.query_answer`.
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

from common.messages import (
    MessageError,
    QueryRequest,
    QueryResult,
    decode_query_request,
    encode_error,
    encode_query_result,
    encode_stats,
)
from mapper.replies import REQUEST_ERRORS, reply_to
from mapper.service_config import set_torch_threads
from mapper.state import MapperState, jsonable

if TYPE_CHECKING:
    import zenoh

    from mapper.outputs.rerun import RerunOutput
    from semantic_map.query_copy import QueryCopy

log = logging.getLogger("rayfronts.mapper")


class QueryServer:
    """One-shot and standing queries against the shared map; ``rerun`` (or None) logs answers."""

    def __init__(self, state: MapperState, rerun: RerunOutput | None = None) -> None:
        self.state = state
        self.rerun = rerun
        self.qsnap: QueryCopy | None = None   # QueryCopy of the last query

    def query_copy(self, timings: dict[str, float], flush: bool = False) -> QueryCopy:
        """The QueryCopy of the current map generation (caller holds ``query_lock``);
        with ``flush`` the map worker first integrates the frames the map buffers."""
        from semantic_map.query_copy import QueryCopy

        state = self.state
        budget = max(0.0, float(state.cfg.query.lock_timeout_s))
        deadline = time.monotonic() + budget
        m = state.map
        if flush and m is not None and getattr(m, "has_buffered", lambda: False)():
            t = time.perf_counter()
            if not state.request_flush(budget):
                timings["flush_pending"] = 1.0
            timings["flush_wait"] = (time.perf_counter() - t) * 1e3
        snap = self.qsnap
        if snap is not None and snap.gen == state.map_gen:
            return snap
        fresh = QueryCopy() if snap is None else snap
        m = state.map
        if m is not None:
            fresh.reserve(m)                      # allocations outside the lock (size hint)
        t = time.perf_counter()
        got = state.lock.acquire(timeout=max(0.0, deadline - time.monotonic()))
        if not got and snap is None:
            got = state.lock.acquire()            # nothing to fall back on: wait for the frame
        timings["lock_wait"] = (time.perf_counter() - t) * 1e3
        if not got:
            assert snap is not None               # without a copy the acquire above waits
            timings["stale"] = 1.0
            timings["stale_gens"] = float(max(0, state.map_gen - snap.gen))
            log.debug("query answered from the copy of map generation %d (map at %d): lock busy > %.2f s",
                      snap.gen, state.map_gen, state.cfg.query.lock_timeout_s)
            return snap
        try:
            if state.map is None:
                raise MessageError("the map is empty (no frames mapped yet)")
            if snap is None or snap.gen != state.map_gen:
                snap = fresh.sync(state.map, state.map_gen, state.mapped)
                self.qsnap = snap
                timings["snapshot"] = snap.take_ms
                timings["snapshot_rows"] = float(snap.changed_rows)
        finally:
            state.lock.release()
        return snap

    def run_query(self, req: QueryRequest, flush: bool = False) -> QueryResult:
        from mapper.query_answer import answer_snapshot

        state = self.state
        t0 = time.perf_counter()
        if state.map is None:
            raise MessageError("the map is empty (no frames mapped yet)")
        with state.query_lock:
            set_torch_threads(state.cfg, query=True)
            timings: dict = {}
            snap = self.query_copy(timings, flush=flush)
            assert state.space is not None        # the map is made with its feature space
            res = answer_snapshot(snap, state.space, req, state.cfg.query, device=state.cfg.device,
                                  model_dir=state.cfg.text_model_dir, standing=list(state.standing.values()))
            res.frames_mapped = snap.frames_mapped
        res.timings.update(timings)
        res.stamp = time.time()
        res.timings["total"] = (time.perf_counter() - t0) * 1e3
        state.timings["query_ms"].add(res.timings["total"])
        return res

    def on_query(self, query: zenoh.Query) -> None:
        state = self.state
        answered: list = []                   # the result, for the shard info

        def answer(data: bytes) -> bytes:
            req = decode_query_request(data)
            leases = state.query_leases
            if req.cancel:
                state.standing.pop(req.id, None)
                leases.drop(req.id)
                return encode_query_result(QueryResult(id=req.id, query="<cancelled>"))
            if req.renew:
                leases.renew(req.id, req.id in state.standing)
                return encode_query_result(QueryResult(id=req.id, query="<renewed>"))
            if req.standing:              # leased (mapper.leases); the mapper's own have no client
                req.client = req.client or "anonymous"
                fresh = req.id not in state.standing
                leases.admit(req.id, req.client, req.lease_s, len(state.standing))
                if state.map is None:
                    # registered before any frame: an empty answer now, published once the map exists
                    state.standing[req.id] = req
                    return encode_query_result(QueryResult(id=req.id, query=req.text or ""))
            try:
                res = self.run_query(req, flush=True)
            except Exception:
                if req.standing and fresh:
                    leases.drop(req.id)
                raise
            res.id = req.id
            answered.append(res)
            if req.standing:
                state.standing[req.id] = req
            payload = encode_query_result(res)
            if self.rerun is not None:
                self.rerun.query_answered(res, req)
            return payload

        fleet = state.fleet                   # shard info for the client-side merge (common.robot_messages)
        reply_to(query, "query", answer,
                 None if fleet is None else lambda: fleet.shard_info(answered[0] if answered else None))

    def standing_loop(self) -> None:
        """Re-runs standing queries when the map worker says the map changed."""
        state = self.state
        while not state.stop.is_set():
            self.end_expired()
            if not state.standing_due.wait(0.5):
                continue
            state.standing_due.clear()
            if state.stop.is_set():
                return
            self.run_standing()

    def end_expired(self) -> None:
        """Drop the standing queries whose lease ran out (their client stopped renewing)."""
        for qid in self.state.query_leases.expired():
            if self.state.standing.pop(qid, None) is not None:
                log.info("standing query %s ended: its lease ran out (the client is gone)", qid)

    def run_standing(self) -> None:
        state = self.state
        for qid, req in list(state.standing.items()):
            try:
                res = self.run_query(req)
                res.id = qid
                att = state.fleet.shard_info(res) if state.fleet is not None else None
                assert state.session is not None and state.keys is not None    # started
                state.session.put(state.keys.mapper_queries(qid), encode_query_result(res), attachment=att)
            except Exception as e:
                state.warn(f"standing:{qid}", "standing query %s failed: %s", qid, e)

    # ================================================================= stats
    def stats(self) -> dict:
        from mapper.query_answer import TEXT_MODEL_LOADS

        state = self.state
        with state.robots_lock:
            robots = {n: st.as_dict() for n, st in state.robots.items()}
            frames = {"received": state.received, "mapped": state.mapped, "dropped": state.dropped,
                      "rejected": dict(state.rejected), "rejected_total": int(sum(state.rejected.values()))}
        out: dict[str, Any] = {
            "frames": frames, "robots": robots,
            "queues": {n: r["queue"] for n, r in robots.items()},
            "timings": {k: v.summary() for k, v in state.timings.items()},
            "feature_space": state.space_id,
            "uptime_s": time.time() - state.started, "standing_queries": sorted(state.standing),
            "snapshot": dict(state.last_snapshot), "map_version": state.version,
            "flushed_version": state.flushed_version, "text_warm_up_s": state.text_warm_up_s,
            # which thread loaded each text model ("text-warm-up": before anyone asked)
            "text_models": {k: dict(v) for k, v in TEXT_MODEL_LOADS.items()},
            "search": {"standing": len(state.standing_searches), "instance_next_id": state.trackers.next_id,
                       "identity_trackers": len(state.trackers),
                       "instance_ids_reserved_below": state.trackers.reserved_below,
                       "instance_id_reserve_errors": state.trackers.reserve_errors,
                       "leases_s": state.search_leases.describe()},
            "query_leases_s": state.query_leases.describe(),
            "fleet_search": state.fleet_search.stats() if state.fleet_search is not None else {},
            "request_errors": dict(REQUEST_ERRORS),
            "first_mapped_at": state.first_mapped_at, "last_mapped_at": state.last_mapped_at,
            # process CPU (all threads) from the first to the last integration, and in total
            "cpu_s": {"mapping": (state.cpu_mapped[1] - state.cpu_mapped[0]) if state.cpu_mapped else 0.0,
                      "process": time.process_time()},
        }
        try:
            import psutil

            out["rss_mb"] = psutil.Process().memory_info().rss / 2 ** 20
        except Exception:
            pass
        if state.fleet is not None:
            with state.robots_lock:
                out["fleet"] = state.fleet.stats()
        if state.map is not None:
            from mapper.service_map import map_stats

            with state.lock:
                out["map"] = map_stats(state.map)
        return out

    def on_feature_space(self, query: zenoh.Query) -> None:
        """``<p>/mapper/feature_space``: the map's feature space as the first robot served it
        (``rayfronts.feature_space``), or an error while there is no map."""
        try:
            reply = self.state.space_reply
            query.reply(query.key_expr, reply if reply is not None
                        else encode_error("the map has no feature space yet (no frames mapped)"))
        except Exception as e:
            log.warning("feature space callback: %s", e)

    def on_stats(self, query: zenoh.Query) -> None:
        try:
            query.reply(query.key_expr, encode_stats(jsonable(self.stats())))
        except Exception as e:
            log.warning("stats callback: %s", e)
