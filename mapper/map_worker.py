"""The map worker: the one thread that integrates frames into the map (module map:
:mod:`mapper.state`; ARCHITECTURE.md).

Loop: take the next frame (round-robin over robots, :meth:`mapper.ingest.Ingest.next_frame`),
integrate it under the map lock, account it (timings, latency, edge CPU per frame), log it to
rerun every ``rerun.every_n_frames``; then, on the map's version changing: signal standing
queries (``query.standing_rate_hz``), publish layers (``layers.rate_hz``; while frames queue at
most every 5 periods), write a periodic snapshot (``snapshots.period_s``). When the input is
idle for ``queues.idle_flush_s`` the map's buffered accumulation is flushed.

torch runs with ``cfg.threads`` intra-op threads here (auto: 1 on small machines, see
:func:`mapper.service_config.resolve_threads`); the thread waits on ``state.wake`` (set by
each frame), never polls. What integration does to the map (fusion, frontiers, rays) lives in
:mod:`mapper.map` via :func:`mapper.service_map.integrate`.
"""
from __future__ import annotations

import logging
import time

from mapper.service_config import set_torch_threads
from mapper.state import MapperState

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

    def loop(self) -> None:
        s = self.state
        cfg = s.cfg
        set_torch_threads(cfg)
        last_layers = 0.0
        last_standing = 0.0
        last_snap = time.monotonic()
        standing_version = -1
        layers_version = -1
        idle_since = time.monotonic()
        while not s.stop.is_set():
            item = self.next_frame()
            if item is None:
                s.wake.wait(0.05)
                s.wake.clear()
                idle_s = cfg.queues.idle_flush_s
                if (s.map is not None and s.version != s.flushed_version and idle_s > 0
                        and time.monotonic() - idle_since > idle_s):
                    self.flush()
            else:
                idle_since = time.monotonic()
                if not self._integrate(*item):
                    continue
            now = time.monotonic()
            if s.map is None:
                continue
            qcfg = cfg.query
            if (s.standing and s.version != standing_version and qcfg.standing_rate_hz > 0
                    and now - last_standing >= 1.0 / qcfg.standing_rate_hz):
                last_standing, standing_version = now, s.version
                s.standing_due.set()
            lcfg = cfg.layers
            if (lcfg.rate_hz > 0 and s.version != layers_version and now - last_layers >= 1.0 / lcfg.rate_hz
                    and (item is None or now - last_layers >= 5.0 / lcfg.rate_hz)):
                last_layers, layers_version = now, s.version
                self.layers.publish()
            scfg = cfg.snapshots
            if scfg.dir and scfg.period_s > 0 and now - last_snap >= scfg.period_s and s.version != s.snap_version:
                last_snap = now
                try:
                    self.snapshots.save()
                except Exception as e:
                    log.error("periodic snapshot failed: %s", e)

    def _integrate(self, st, frame, t_recv) -> bool:
        """Integrate one frame and account it; False if integration failed (counted)."""
        if self.state.fleet is not None:   # re-projection into the map's basis, world_from_robot, shard
            try:
                frame = self.state.fleet.prepare(st, frame)
            except Exception as e:
                self.state.reject(st.name, "fleet_prepare", repr(e))
                return False
            if frame is None:
                return False
        from mapper.service_map import integrate

        s = self.state
        t0 = time.perf_counter()
        c0 = time.thread_time()
        try:
            with s.lock:
                try:
                    integrate(s.map, frame, s.cfg.device)
                finally:
                    s.map_gen += 1
                s.version += 1
        except Exception as e:
            log.exception("integrating frame %s/%d failed", st.name, frame.seq)
            s.reject(st.name, "integrate_failed", repr(e))
            return False
        dt = (time.perf_counter() - t0) * 1e3
        s.timings["integrate_ms"].add(dt)
        s.timings["integrate_cpu_ms"].add((time.thread_time() - c0) * 1e3)
        t_send = frame.meta.get("t_send") if isinstance(frame.meta, dict) else None
        if isinstance(t_send, (int, float)):
            s.timings["latency_ms"].add((time.time() - t_send) * 1e3)
        now_w = time.time()
        s.first_mapped_at = s.first_mapped_at or now_w
        s.last_mapped_at = now_w
        cpu = time.process_time()
        s.cpu_mapped = [s.cpu_mapped[0] if s.cpu_mapped else cpu, cpu]
        e_cpu = frame.meta.get("cpu_s") if isinstance(frame.meta, dict) else None
        with s.qlock:
            st.mapped += 1
            if frame.seq <= st.last_seq:
                st.seq_regressions += 1
            st.last_seq = frame.seq
            s.mapped += 1
            if isinstance(e_cpu, (int, float)) and not isinstance(e_cpu, bool):
                if st.edge_cpu is None or e_cpu < st.edge_cpu[1]:   # first, or the edge restarted
                    st.edge_cpu, st.edge_cpu_frames = (float(e_cpu), float(e_cpu)), 0
                else:
                    st.edge_cpu, st.edge_cpu_frames = (st.edge_cpu[0], float(e_cpu)), st.edge_cpu_frames + 1
        if self.rerun is not None:
            self.rerun.frame_mapped(st.name, frame)
        return True

    def flush(self) -> None:
        """Integrate what the map buffers (accumulation periods) when the input is idle."""
        from mapper.service_map import flush

        s = self.state
        with s.lock:
            v = s.version
            try:
                flush(s.map)
            except Exception as e:
                s.warn("flush", "map flush failed: %s", e)
            s.map_gen += 1
            s.flushed_version = v
