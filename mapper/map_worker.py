"""The map worker: the one thread that integrates frames into the map (module map:
:mod:`mapper.state`; ARCHITECTURE.md).

Loop: take the next frame (round-robin over robots, :meth:`mapper.ingest.Ingest.next_frame`),
integrate it under the map lock, account it (timings, latency, edge CPU per frame), log it to
rerun every ``rerun.every_n_frames``; then, on the map's version changing: signal standing
queries (``query.standing_rate_hz``), publish layers (``layers.rate_hz``; while frames queue at
most every 5 periods), write a periodic snapshot (``snapshots.period_s``). When the input is
idle for ``queues.idle_flush_s`` the map's buffered accumulation is flushed, and so it is
when a one-shot query asks (:meth:`MapWorker.serve_flush`, checked before each frame).

torch runs with ``cfg.threads`` intra-op threads here (auto: 1 on small machines, see
:func:`mapper.service_config.resolve_threads`); the thread waits on ``state.wake`` (set by
each frame), never polls.

With ``cfg.pipeline`` (default) frames go through :class:`mapper.pipeline.MapPipeline`: a
frame's validation, geometry and sampling run on the ``map-prepare`` thread (no map lock)
while the previous frame is committed here under the map lock; a frame is accounted when it
is committed. Whenever no frame is queued the pipeline is drained first (a slow robot's
frame is never held back), and before a periodic snapshot; snapshots taken from other
threads meanwhile still save the exact committed state (:meth:`RayFrontsMap.rng_state`).
What integration does to the map (fusion, frontiers, rays) lives in
:mod:`semantic_map.map` via :func:`mapper.service_map.integrate`.
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from mapper.service_config import set_torch_threads
from mapper.state import MapperState

if TYPE_CHECKING:
    from mapper.pipeline import MapPipeline

log = logging.getLogger("rayfronts.mapper")


class MapWorker:
    """Runs :meth:`loop` on the ``mapper-map`` thread.

    ``next_frame`` pops a queued frame (or None); ``layers`` has ``publish()``; ``rerun`` is a
    :class:`mapper.outputs.rerun.RerunOutput` or None; ``snapshots`` has ``save()``.
    """

    def __init__(self, state: MapperState, next_frame, layers, snapshots, rerun=None):
        self.state = state
        self.next_frame = next_frame
        self.layers = layers
        self.snapshots = snapshots
        self.rerun = rerun
        self._pipe: MapPipeline | None = None

    def loop(self) -> None:
        state = self.state
        cfg = state.cfg
        set_torch_threads(cfg)
        last_layers = 0.0
        last_standing = 0.0
        last_snap = time.monotonic()
        standing_version = -1
        layers_version = -1
        idle_since = time.monotonic()
        try:
            self._loop(state, cfg, last_layers, last_standing, last_snap, standing_version, layers_version, idle_since)
        finally:
            self._close_pipe()

    def _loop(self, state, cfg, last_layers, last_standing, last_snap, standing_version, layers_version, idle_since):
        while not state.stop.is_set():
            ticket = state.flush_wanted()
            if ticket:
                self.serve_flush(ticket)
            item = self.next_frame()
            if item is None and self._pipe is not None and len(self._pipe):
                self._account_all(self._pipe.drain())  # input idle: commit what is in flight first
            elif item is None:
                state.wake.wait(0.05)
                state.wake.clear()
                idle_s = cfg.queues.idle_flush_s
                if (state.map is not None and state.version != state.flushed_version and idle_s > 0
                        and time.monotonic() - idle_since > idle_s):
                    self.flush()
            else:
                idle_since = time.monotonic()
                if not self._integrate(*item):
                    continue
            now = time.monotonic()
            if state.map is None:
                continue
            qcfg = cfg.query
            if (state.standing and state.version != standing_version and qcfg.standing_rate_hz > 0
                    and now - last_standing >= 1.0 / qcfg.standing_rate_hz):
                last_standing, standing_version = now, state.version
                state.standing_due.set()
            lcfg = cfg.layers
            if (lcfg.rate_hz > 0 and state.version != layers_version and now - last_layers >= 1.0 / lcfg.rate_hz
                    and (item is None or now - last_layers >= 5.0 / lcfg.rate_hz)):
                last_layers, layers_version = now, state.version
                self.layers.publish()
            scfg = cfg.snapshots
            if (scfg.dir and scfg.period_s > 0 and now - last_snap >= scfg.period_s
                    and (state.version != state.snap_version or state.trackers.generation != state.snap_trackers)):
                last_snap = now
                if self._pipe is not None:
                    self._account_all(self._pipe.drain())
                try:
                    self.snapshots.save()
                except Exception as e:
                    log.error("periodic snapshot failed: %s", e)

    # ---------------------------------------------------------------- pipeline
    def _commit(self, prepared) -> dict:
        """Commit one prepared frame into the current map under the map lock (pipeline path)."""
        state = self.state
        with state.lock:
            try:
                assert state.map is not None           # a pipeline exists only with a map
                return state.map.commit(prepared)
            finally:
                state.map_gen += 1
                state.version += 1

    def _pipeline(self):
        """The pipeline of the current map (a new one when the map object changed)."""
        state = self.state
        if self._pipe is not None and self._pipe.map is not state.map:
            self._close_pipe()
        if self._pipe is None:
            from mapper.pipeline import MapPipeline
            from mapper.service_config import resolve_threads

            threads = resolve_threads(int(getattr(state.cfg, "threads", 0)))
            assert state.map is not None               # frames are integrated once the map exists
            self._pipe = MapPipeline(state.map, depth=1, prepare_threads=threads, commit=self._commit)
        return self._pipe

    def _close_pipe(self) -> None:
        if self._pipe is not None:
            pipe, self._pipe = self._pipe, None
            self._account_all(pipe.close())

    def _account_all(self, done) -> None:
        for c in done:
            st, frame, t0 = c.tag
            if c.error is not None:
                log.error("integrating frame %s/%d failed: %r", st.name, frame.seq, c.error)
                self.state.reject(st.name, "integrate_failed", repr(c.error))
                continue
            self._account(st, frame, (time.perf_counter() - t0) * 1e3, c.cpu_ms)

    def _integrate(self, st, frame, t_recv) -> bool:
        """Integrate one frame (pipelined: submit it; frames committed meanwhile are
        accounted) and account it; False if integration failed (counted)."""
        if self.state.fleet is not None:   # re-projection into the map's basis, world_from_robot, shard
            try:
                frame = self.state.fleet.prepare(st, frame)
            except Exception as e:
                self.state.reject(st.name, "fleet_prepare", repr(e))
                return False
            if frame is None:
                return False
        state = self.state
        if getattr(state.cfg, "pipeline", False) and state.map is not None:
            g = None if frame.global_feature is None else np.array(frame.global_feature)
            try:
                done = self._pipeline().submit(frame.pose, frame.intrinsics, frame.depth, np.array(frame.rgb),
                                               np.array(frame.features), g, tag=(st, frame, time.perf_counter()))
            except Exception as e:
                log.exception("integrating frame %s/%d failed", st.name, frame.seq)
                state.reject(st.name, "integrate_failed", repr(e))
                return False
            self._account_all(done)
            return True
        from mapper.service_map import integrate

        t0 = time.perf_counter()
        c0 = time.thread_time()
        try:
            with state.lock:
                try:
                    assert state.map is not None       # frames are integrated once the map exists
                    integrate(state.map, frame, state.cfg.device)
                finally:
                    state.map_gen += 1
                state.version += 1
        except Exception as e:
            log.exception("integrating frame %s/%d failed", st.name, frame.seq)
            state.reject(st.name, "integrate_failed", repr(e))
            return False
        self._account(st, frame, (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3)
        return True

    def _account(self, st, frame, dt_ms: float, cpu_ms: float) -> None:
        """Timings, latency, counters and rerun of one integrated frame."""
        state = self.state
        state.timings["integrate_ms"].add(dt_ms)
        state.timings["integrate_cpu_ms"].add(cpu_ms)
        t_send = frame.meta.get("t_send") if isinstance(frame.meta, dict) else None
        if isinstance(t_send, (int, float)):
            state.timings["latency_ms"].add((time.time() - t_send) * 1e3)
        now_w = time.time()
        state.first_mapped_at = state.first_mapped_at or now_w
        state.last_mapped_at = now_w
        cpu = time.process_time()
        state.cpu_mapped = [state.cpu_mapped[0] if state.cpu_mapped else cpu, cpu]
        e_cpu = frame.meta.get("cpu_s") if isinstance(frame.meta, dict) else None
        with state.robots_lock:
            st.mapped += 1
            if frame.seq <= st.last_seq:
                st.seq_regressions += 1
            st.last_seq = frame.seq
            st.pose, st.pose_stamp = frame.pose, float(frame.stamp)
            state.mapped += 1
            if isinstance(e_cpu, (int, float)) and not isinstance(e_cpu, bool):
                if st.edge_cpu is None or e_cpu < st.edge_cpu[1]:   # first, or the edge restarted
                    st.edge_cpu, st.edge_cpu_frames = (float(e_cpu), float(e_cpu)), 0
                else:
                    st.edge_cpu, st.edge_cpu_frames = (st.edge_cpu[0], float(e_cpu)), st.edge_cpu_frames + 1
        if self.rerun is not None:
            self.rerun.frame_mapped(st.name, frame)

    def serve_flush(self, ticket: int) -> None:
        """A query asked for the map's buffered frames: commit the frames in flight and
        flush (only if the map buffers something: then it costs one voxel / ray block)."""
        state = self.state
        try:
            m = state.map
            if m is not None and getattr(m, "has_buffered", lambda: True)():
                self.flush()
        finally:
            state.flush_done(ticket)

    def flush(self) -> None:
        """Integrate what the map buffers (accumulation periods) when the input is idle."""
        from mapper.service_map import flush

        state = self.state
        if self._pipe is not None:
            self._account_all(self._pipe.drain())
        with state.lock:
            v = state.version
            try:
                assert state.map is not None           # both callers check it
                flush(state.map)
            except Exception as e:
                state.warn("flush", "map flush failed: %s", e)
            state.map_gen += 1
            state.flushed_version = v
