"""The mapper's query side: the query and stats queryables, standing queries and ``stats()``
(module map: :mod:`mapper.state`; ARCHITECTURE.md).

A query holds the map lock only to bring its copy of the map
(:class:`mapper.query_answer.QuerySnapshot`) up to date: the copy is maintained
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
from typing import Any

from common.messages import (
    MessageError,
    QueryRequest,
    QueryResult,
    decode_query_request,
    encode_error,
    encode_query_result,
    encode_stats,
)
from mapper.service_config import set_torch_threads
from mapper.state import MapperState, jsonable

log = logging.getLogger("rayfronts.mapper")


class QueryServer:
    """One-shot and standing queries against the shared map; ``rerun`` (or None) logs answers."""

    def __init__(self, state: MapperState, rerun=None):
        self.state = state
        self.rerun = rerun
        self.qsnap = None                    # QuerySnapshot of the last query

    def snapshot(self, timings: dict, flush: bool = False):
        """The QuerySnapshot of the current map generation (caller holds ``query_lock``);
        with ``flush`` the map worker first integrates the frames the map buffers."""
        from semantic_map.query_snapshot import QuerySnapshot

        s = self.state
        budget = max(0.0, float(s.cfg.query.lock_timeout_s))
        deadline = time.monotonic() + budget
        m = s.map
        if flush and m is not None and getattr(m, "has_buffered", lambda: False)():
            t = time.perf_counter()
            if not s.request_flush(budget):
                timings["flush_pending"] = 1.0
            timings["flush_wait"] = (time.perf_counter() - t) * 1e3
        snap = self.qsnap
        if snap is not None and snap.gen == s.map_gen:
            return snap
        fresh = QuerySnapshot() if snap is None else snap
        m = s.map
        if m is not None:
            fresh.reserve(m)                      # allocations outside the lock (size hint)
        t = time.perf_counter()
        got = s.lock.acquire(timeout=max(0.0, deadline - time.monotonic()))
        if not got and snap is None:
            got = s.lock.acquire()            # nothing to fall back on: wait for the frame
        timings["lock_wait"] = (time.perf_counter() - t) * 1e3
        if not got:
            timings["stale"] = 1.0
            timings["stale_gens"] = float(max(0, s.map_gen - snap.gen))
            log.debug("query answered from the copy of map generation %d (map at %d): lock busy > %.2f s",
                      snap.gen, s.map_gen, s.cfg.query.lock_timeout_s)
            return snap
        try:
            if s.map is None:
                raise MessageError("the map is empty (no frames mapped yet)")
            if snap is None or snap.gen != s.map_gen:
                snap = fresh.sync(s.map, s.map_gen, s.mapped)
                self.qsnap = snap
                timings["snapshot"] = snap.take_ms
                timings["snapshot_rows"] = float(snap.changed_rows)
        finally:
            s.lock.release()
        return snap

    def run_query(self, req: QueryRequest, flush: bool = False) -> QueryResult:
        from mapper.query_answer import answer_snapshot

        s = self.state
        t0 = time.perf_counter()
        if s.map is None:
            raise MessageError("the map is empty (no frames mapped yet)")
        with s.query_lock:
            set_torch_threads(s.cfg, query=True)
            timings: dict = {}
            snap = self.snapshot(timings, flush=flush)
            res = answer_snapshot(snap, s.space, req, s.cfg.query, device=s.cfg.device,
                                  model_dir=s.cfg.text_model_dir, standing=list(s.standing.values()))
            res.frames_mapped = snap.frames_mapped
        res.timings.update(timings)
        res.stamp = time.time()
        res.timings["total"] = (time.perf_counter() - t0) * 1e3
        s.timings["query_ms"].add(res.timings["total"])
        return res

    def on_query(self, query) -> None:
        s = self.state
        res = None
        try:
            try:
                if query.payload is None:
                    raise MessageError("query without payload")
                req = decode_query_request(query.payload.to_bytes())
                if req.cancel:
                    s.standing.pop(req.id, None)
                    payload = encode_query_result(QueryResult(id=req.id, query="<cancelled>"))
                else:
                    res = self.run_query(req, flush=True)
                    res.id = req.id
                    if req.standing:
                        s.standing[req.id] = req
                    payload = encode_query_result(res)
                    if self.rerun is not None:
                        self.rerun.query_answered(res, req)
            except (MessageError, ValueError) as e:
                payload = encode_error(str(e))
            except Exception as e:
                log.exception("query failed")
                payload = encode_error(f"internal error: {e!r}")
            if s.fleet is not None:   # shard info for the client-side merge (common.fleet)
                query.reply(query.key_expr, payload, attachment=s.fleet.shard_info(res))
            else:
                query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("query callback: %s", e)

    def standing_loop(self) -> None:
        """Re-runs standing queries when the map worker says the map changed."""
        s = self.state
        while not s.stop.is_set():
            if not s.standing_due.wait(0.5):
                continue
            s.standing_due.clear()
            if s.stop.is_set():
                return
            self.run_standing()

    def run_standing(self) -> None:
        s = self.state
        for qid, req in list(s.standing.items()):
            try:
                res = self.run_query(req)
                res.id = qid
                att = s.fleet.shard_info(res) if s.fleet is not None else None
                s.session.put(s.keys.mapper_queries(qid), encode_query_result(res), attachment=att)
            except Exception as e:
                s.warn(f"standing:{qid}", "standing query %s failed: %s", qid, e)

    # ================================================================= stats
    def stats(self) -> dict:
        s = self.state
        with s.qlock:
            robots = {n: st.as_dict() for n, st in s.robots.items()}
            frames = {"received": s.received, "mapped": s.mapped, "dropped": s.dropped,
                      "rejected": dict(s.rejected), "rejected_total": int(sum(s.rejected.values()))}
        out: dict[str, Any] = {
            "frames": frames, "robots": robots,
            "queues": {n: r["queue"] for n, r in robots.items()},
            "timings": {k: v.summary() for k, v in s.timings.items()},
            "feature_space": s.space_id,
            "uptime_s": time.time() - s.started, "standing_queries": sorted(s.standing),
            "snapshot": dict(s.last_snapshot), "map_version": s.version,
            "flushed_version": s.flushed_version,
            "first_mapped_at": s.first_mapped_at, "last_mapped_at": s.last_mapped_at,
            # process CPU (all threads) from the first to the last integration, and in total
            "cpu_s": {"mapping": (s.cpu_mapped[1] - s.cpu_mapped[0]) if s.cpu_mapped else 0.0,
                      "process": time.process_time()},
        }
        try:
            import psutil

            out["rss_mb"] = psutil.Process().memory_info().rss / 2 ** 20
        except Exception:
            pass
        if s.fleet is not None:
            with s.qlock:
                out["fleet"] = s.fleet.stats()
        if s.map is not None:
            from mapper.service_map import map_stats

            with s.lock:
                out["map"] = map_stats(s.map)
        return out

    def on_stats(self, query) -> None:
        try:
            query.reply(query.key_expr, encode_stats(jsonable(self.stats())))
        except Exception as e:
            log.warning("stats callback: %s", e)
