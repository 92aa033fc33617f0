"""The edge process: source → encoder → PCA compression → frame message → Zenoh, composed of
``edge.config`` (the schema), ``edge.encoding`` (encoder + PCA chain, start-up checks),
``edge.connection`` (session, liveliness, status, feature-space queryable) and
``edge.publisher`` (the one-slot queue, the publisher thread, the frame's key).

Threads:

* the main (pipeline) thread reads the source, encodes, compresses and serialises frame
  ``n+1`` while
* the publisher thread sends frame ``n`` with ``CongestionControl.BLOCK``. They meet in a
  one-slot :class:`LatestSlot`: a newer frame replaces an unsent older one (counted as
  ``replaced``), so the encoder never waits on the network and a slow link drops whole old
  frames, never fragments of new ones (docs/key_space.md#topology).
* a connector thread opens the Zenoh session (client mode retries until the base station
  answers) and declares the liveliness token ``robots/<robot>/alive`` and the
  ``robots/<robot>/feature_space`` queryable. Zenoh re-establishes a lost link by itself.

torch runs with ``cfg.threads`` intra-op threads (auto: 1 for the label encoder or a GPU
encoder, whose CPU work is small ops where extra threads only spin against the other
processes; torch's default for a CPU encoder). Each frame's meta carries ``t_send`` (wall
clock at hand-off, for the mapper's latency) and ``cpu_s`` (this process's CPU time, for
the mapper's per-robot edge CPU per frame).

Start-up checks and reporting (``check_setup``): the encoder × ``encoder.output`` × PCA
combination is validated before the first frame is encoded (PCA output dimension within the
encoder's feature dimension, a basis file fitted on the features this encoder/output gives and
with the configured ``pca.out_dim``, enough samples for an online fit); a failing check, a
missing model or basis file, or a source that cannot open is a *refusal*: one error line
naming the combination, exit code 2. An exception while running is a *failure* (exit code 1).
Either way the edge puts its state on ``robots/<robot>/edge_status``
(``common.messages.encode_edge_status``: starting / running / done / refused / failed + the
reason) before it undeclares its liveliness token, so the mapper can name the reason once. The
image-level vector sent with each frame is in the dense features' space
(``encode_with_global(..., global_space="features")``), compressed by the same PCA.

The edge imports neither rerun nor the mapper.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator

from edge.config import EdgeConfig, resolve_threads
from edge.connection import EdgeConnection
from edge.encoding import EdgeRefused, EncoderChain, check_first_features, compress_features
from edge.publisher import EdgeStats, FramePublisher

if TYPE_CHECKING:
    from common.frame import Frame

# EdgeConfig and compress_features live in edge.config / edge.encoding; apps/closed_loop imports them from here
__all__ = ["EdgeRuntime", "EdgeConfig", "compress_features"]

log = logging.getLogger("rayfronts.edge")


@dataclass
class _RunState:
    """What :meth:`EdgeRuntime._run` carries from frame to frame (pacing)."""

    rate: float  # frames per second (0 = as fast as possible)
    next_t: float  # time.monotonic() of the next paced send
    seq: int = 0


class EdgeRuntime:
    """Runs the edge pipeline until the source ends or ``stop`` is set: the source and pacing
    here; the encoder/PCA chain (:attr:`chain`, ``edge.encoding``), the Zenoh session and status
    (:attr:`connection`, ``edge.connection``) and the publisher thread (:attr:`publisher`,
    ``edge.publisher``) each in their module.

    ``frames`` (optional) replaces the configured source (tests, benchmarks);
    ``on_sent(frame, nbytes, t_put)`` is called by the publisher thread after each put."""

    def __init__(self, cfg: EdgeConfig, stop: threading.Event | None = None, frames: Iterable[Frame] | None = None,
                 class_names: list[str] | None = None,
                 on_sent: Callable[[Any, int, float], None] | None = None):
        import dataclasses

        from edge.mapper_status import AutoRate, StatusWatcher

        if not cfg.robot:
            cfg = dataclasses.replace(cfg, robot=cfg.source.robot)
        self.cfg = cfg
        self.stop = stop or threading.Event()
        self._frames = frames
        self._class_names = class_names
        self.stats = EdgeStats()
        # the mapper's per-robot status: logged on change; publish.rate_hz=auto follows its advice
        self.auto_rate = AutoRate() if cfg.publish.rate_hz == "auto" else None
        self.mapper_status = StatusWatcher(cfg.robot, self.auto_rate)
        connected = threading.Event()
        self.publisher = FramePublisher(cfg, self.stop, connected, self.stats, on_sent)
        self.connection = EdgeConnection(cfg, self.stop, connected, self.mapper_status, self.publisher.attach,
                                         self.publisher.detach, lambda: self.phase)
        self.chain = EncoderChain(cfg, self._set_phase, self.connection.ask_map_space,
                                  self.connection.serve_feature_space)
        self.slot = self.publisher.slot
        self._threads: list[threading.Thread] = []
        self._started = False
        self.phase = "waiting for the first source frame"   # what the pipeline is doing (said in
        # the feature-space "not ready" reply and logged on each change)

    def _set_phase(self, phase: str) -> None:
        self.phase = phase
        log.info("edge %s: %s", self.cfg.robot, phase)

    @property
    def feature_space(self) -> Any:
        """The edge's ``FeatureSpace`` once known (else None)."""
        return self.chain.fs

    def set_state(self, state: str, reason: str = "", wait_s: float = 0.0) -> None:
        """Put the edge's state on ``robots/<robot>/edge_status`` (``EdgeConnection.set_state``)."""
        self.connection.set_state(state, reason, wait_s)

    # -------------------------------------------------------------- the source
    def _open_source(self) -> tuple[Iterable[Frame], list[str] | None]:
        if self._frames is not None:
            return self._frames, self._class_names
        from edge.sources import open_source

        extra = {}
        if self.cfg.source.kind in ("ros2", "sim_camera"):  # live: the edge's Zenoh settings and its stop event
            extra = {"zenoh": self.cfg.zenoh, "stop": self.stop}
        src = open_source(self.cfg.source, **extra)
        return src, list(getattr(src, "class_names", None) or []) or None

    def _rate(self) -> float:
        r = self.cfg.publish.rate_hz
        if r == "auto":
            assert self.auto_rate is not None
            return self.auto_rate.current()
        if r >= 0:
            return r
        return 10.0 if getattr(self.cfg.source, "kind", "") == "synthetic" else 0.0

    def _iter_frames(self) -> Iterator[tuple[Frame, list[str] | None]]:
        n = 0
        skipped0 = 0
        while not self.stop.is_set():
            src, names = self._open_source()
            got = False
            for fr in src:
                got = True
                # frames the source skipped as corrupt (FrameSource.skipped) are counted, not fatal
                self.stats.frames_skipped = skipped0 + int(getattr(src, "skipped", {}).get("corrupt frame", 0))
                yield fr, names
                n += 1
                if self.stop.is_set() or (self.cfg.publish.max_frames and n >= self.cfg.publish.max_frames):
                    return
            skipped0 += int(getattr(src, "skipped", {}).get("corrupt frame", 0))
            self.stats.frames_skipped = skipped0
            if not self.cfg.publish.loop or not got or self._frames is not None:
                return

    # -------------------------------------------------------------- the run
    def run(self) -> int:
        """Run to the end of the source (or ``stop``); returns a process exit code: 0 done,
        2 refused at start-up, 1 failed while running (state and reason on ``edge_status``)."""
        from common.config import ConfigError
        from common.model_files import ModelFileError
        from common.pca import PCAError

        try:
            return self._run()
        except (EdgeRefused, ConfigError, PCAError, ModelFileError, FileNotFoundError, ValueError) as e:
            if not self._started:
                reason = str(e).splitlines()[0] if str(e) else type(e).__name__
                log.error("edge %s refused to start: %s", self.cfg.robot, reason)
                self._report_end("refused", reason)
                return 2
            return self._failed(e)
        except Exception as e:
            return self._failed(e)
        finally:
            self.close()

    def _failed(self, e: BaseException) -> int:
        reason = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}".rstrip(": ")
        log.error("edge %s failed after %d frames: %s", self.cfg.robot, self.stats.frames_encoded, reason,
                  exc_info=True)
        self._report_end("failed", reason)
        return 1

    def _report_end(self, state: str, reason: str) -> None:
        """Put the final state (waiting briefly for the session) and give Zenoh a moment to
        send it before the session closes."""
        self.set_state(state, reason, wait_s=self.cfg.publish.status_wait_s)
        if self.connection.connected.is_set():
            time.sleep(0.3)

    def _run(self) -> int:
        import torch

        cfg = self.cfg
        n_threads = resolve_threads(cfg)
        if n_threads and torch.get_num_threads() != n_threads:
            torch.set_num_threads(n_threads)
        self._start_workers()
        self._started = False
        st = _RunState(rate=self._rate(), next_t=time.monotonic())
        chain = self.chain
        try:
            for fr, names in self._iter_frames():
                self.stats.frames_read += 1
                if chain.encoder is None:
                    chain.load(names)
                    self.cfg = chain.cfg
                t0 = time.perf_counter()
                with torch.inference_mode():
                    # one forward pass gives the dense map and the image-level vector
                    feats, gfeat = chain.encoder.encode_with_global(fr.rgb, fr.labels, global_space="features")
                if not self._started:
                    if chain.fitter is not None:
                        check_first_features(self.cfg, feats)
                    self._started = True
                    self.set_state("running")
                self.stats.frames_encoded += 1
                todo = chain.to_send(fr, feats, gfeat)
                if todo is None:  # held while fitting PCA online
                    continue
                self._send_frames(st, todo, t0)
                if self.stop.is_set():
                    break
            self._finish_run()
        finally:
            self.slot.close()  # run() reports a refusal/failure on the still open session, then closes
        self.stats.frames_replaced = self.slot.replaced
        log.info("edge %s done: %s", cfg.robot, self.stats.as_dict())
        return 0

    def _start_workers(self) -> None:
        """Start the connector and publisher threads; open the recording if one is configured."""
        cfg = self.cfg
        conn = threading.Thread(target=self.connection.loop, name="edge-connect", daemon=True)
        pub = threading.Thread(target=self.publisher.loop, name="edge-publisher", daemon=True)
        conn.start()
        pub.start()
        self._threads = [conn, pub]
        if cfg.recording.dir:
            from common.recording import RecordingWriter

            self.publisher.recorder = RecordingWriter(Path(cfg.recording.dir), robot=cfg.robot,
                                                      source=cfg.source.kind, overwrite=cfg.recording.overwrite)

    def _send_frames(self, st: _RunState, todo: list, t0: float) -> None:
        """Compress, encode, pace and hand ``todo`` to the publisher (``t0``: perf_counter at the
        encoder call); returns early when stopped."""
        from common.wire import encode_frame

        cfg = self.cfg
        for fr_i, feats_i, g_i in todo:
            out = self.chain.compressed(fr_i, st.seq, feats_i, g_i)
            data = encode_frame(out, feature_codec=cfg.publish.feature_codec,
                                jpeg_quality=cfg.publish.jpeg_quality)
            self.stats.encode_ms_last = (time.perf_counter() - t0) * 1e3
            st.seq += 1
            if self._pace(st):
                return
            # a backlog held during the PCA fit, or publish.lossless: hand over without replacing
            if len(todo) > 1 or cfg.publish.lossless:
                while self.slot.pending and not self.stop.is_set():
                    self.slot.wait_empty(0.2)
            self.slot.put((out, data))
            self.stats.frames_replaced = self.slot.replaced

    def _pace(self, st: _RunState) -> bool:
        """Wait for the next send time at the current rate (Hz; 0 = no pacing); True if stopped meanwhile."""
        if self.auto_rate is not None:
            st.rate = self.auto_rate.current()
        if st.rate > 0:
            st.next_t += 1.0 / st.rate
            delay = st.next_t - time.monotonic()
            if delay > 0:
                if self.stop.wait(delay):
                    return True
            else:
                st.next_t = time.monotonic()
        return False

    def _finish_run(self) -> None:
        """Drain: let the publisher send the last frame, then linger for late feature-space gets."""
        cfg = self.cfg
        end = time.monotonic() + 30.0
        while self.slot.pending and not self.stop.is_set() and time.monotonic() < end:
            time.sleep(0.05)
        if not self.stop.is_set():
            self.stop.wait(cfg.publish.linger_s)
        if not self._started and not self.stop.is_set():
            raise EdgeRefused(f"the source ({cfg.source.kind}) yielded no frames")
        self.set_state("done")

    def close(self) -> None:
        """Stop the threads and close the Zenoh session (idempotent; never hangs)."""
        self.stop.set()
        self.slot.close()
        for t in self._threads:
            t.join(timeout=5.0)
        self.publisher.close_recording()
        self.connection.close()
