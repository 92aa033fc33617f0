"""A simulated robot's camera (``source.kind=sim_camera``): the synthetic world rendered at
camera poses a simulator sends over Zenoh, one message per step.

The closed loop (``rayfronts eval search --distributed``) drives a simulated robot: each step
its planner puts the step's camera poses on ``<p>/robots/<robot>/sim/views``
(:func:`common.messages.encode_sim_views`), and this source renders the world (``source.seed``,
``source.preset``) at each pose, in order, at ``resolution`` (default 224×224) with
horizontal FoV ``hfov``, with exact labels (the label and sim encoders need them) — the
frames the robot's camera would give. Sky pixels get depth ``sky_depth``: ``nan`` (a range
sensor gets no return) or ``inf`` (beyond range), as the in-process loop's edge chain does.

Live behaviour: the subscriber callback only decodes and queues (at most ``QUEUE`` steps; a
full queue drops its oldest step, counted as ``dropped_full``); a message that does not
decode is counted (``bad``) with one rate-limited line and the source keeps serving.
Rendering happens on the edge's pipeline thread. The stream ends when the edge stops.

World frame: the synthetic world's frame, z up (x east, y north), ground at z = 0; poses
camera-to-world, RDF camera axes.
"""
from __future__ import annotations

import logging
import threading
from collections import Counter, deque
from collections.abc import Iterator

import numpy as np

from edge.sources.base import FrameSource, RateLimitedLog, native_frame
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError

log = logging.getLogger("rayfronts.edge.sim_camera")

DEFAULT_HW = (224, 224)
#: steps waiting to be rendered; a full queue drops its oldest step
QUEUE = 16


class SimCameraSource(FrameSource):
    kind = "sim_camera"
    default_fps = 10.0

    def __init__(self, cfg: SourceConfig, zenoh=None, stop: threading.Event | None = None):
        super().__init__(cfg)
        from common.keys import KeySpace
        from common.zenoh_session import ZenohConfig

        if not 0 < cfg.hfov < 180:
            raise SourceError(f"{self.kind}: hfov must be in (0, 180) degrees, got {cfg.hfov}")
        if cfg.sky_depth not in ("inf", "nan"):
            raise SourceError(f"{self.kind}: sky_depth must be 'inf' or 'nan', got {cfg.sky_depth!r}")
        self.world = self._make_world(cfg)
        self.native_hw = self.out_hw or DEFAULT_HW
        self.native_K = np.asarray(self.world.camera(self.native_hw, cfg.hfov), dtype=np.float64)
        self.class_names = list(self.world.classes)
        self.name = f"{self.kind}:seed{cfg.seed}:{cfg.preset}"
        self.world_frame = getattr(self, "world_frame_text",
                                   "synthetic world frame, z up (x east, y north), ground at z = 0")
        self._zcfg = zenoh if zenoh is not None else ZenohConfig(mode="client", connect=["tcp/127.0.0.1:7447"])
        self.key = KeySpace(self._zcfg.prefix).sim_views(cfg.robot)
        self._stop = stop or threading.Event()
        self._cond = threading.Condition()
        self._steps: deque = deque()
        self.counts: Counter = Counter()
        self.frames_out = 0
        self._rlog = RateLimitedLog(5.0, log)

    def _make_world(self, cfg: SourceConfig):
        """The world rendered at the poses (``source.seed``, ``source.preset``)."""
        try:
            from synthetic_world import World

            return World.generate(cfg.seed, cfg.preset)
        except (ImportError, ValueError, KeyError) as e:
            raise SourceError(f"sim_camera: cannot generate world seed={cfg.seed} preset={cfg.preset!r}: {e}") from None

    def _on_sample(self, sample) -> None:
        from common.messages import MessageError, decode_sim_views

        try:
            step, poses = decode_sim_views(sample.payload.to_bytes())
        except MessageError as e:
            self.counts["bad"] += 1
            self._rlog.warn("bad", "sim_camera: ignoring a message on %s (%d so far): %s", self.key,
                            self.counts["bad"], e)
            return
        except Exception as e:  # never raise out of a Zenoh callback
            self.counts["bad"] += 1
            log.warning("sim_camera: ignoring a message on %s: %s", self.key, e)
            return
        with self._cond:
            if len(self._steps) >= QUEUE:
                self._steps.popleft()
                self.counts["dropped_full"] += 1
            self._steps.append((step, poses))
            self.counts["steps"] += 1
            self._cond.notify_all()

    def _render(self, step: int, k: int, pose: np.ndarray):
        r = self.world.render(pose, self.native_K, self.native_hw)
        depth = np.asarray(r.depth, dtype=np.float32)
        if self.cfg.sky_depth == "nan":
            depth = np.where(np.isinf(depth), np.float32(np.nan), depth)
        return native_frame(self.frames_out, self.frames_out / self.fps, pose, self.native_K, depth,
                            np.asarray(r.rgb, dtype=np.uint8), np.asarray(r.labels, dtype=np.int32),
                            step=int(step), view=int(k))

    def __iter__(self) -> Iterator:
        from common.zenoh_session import SessionGuard, ZenohConnectError

        try:
            guard = SessionGuard.open(self._zcfg, stop=self._stop, default_mode="client")
        except ZenohConnectError as e:
            raise SourceError(f"sim_camera: {e}") from None
        guard.add(guard.session.declare_subscriber(self.key, self._on_sample))
        log.info("sim_camera: rendering the views put on %s", self.key)
        try:
            while not self._stop.is_set():
                with self._cond:
                    if not self._steps:
                        self._cond.wait(0.1)
                        continue
                    step, poses = self._steps.popleft()
                for k, pose in enumerate(poses):
                    try:
                        out = self._finish(self._render(step, k, pose), self.frames_out)
                    except SourceError as e:      # e.g. a pose that is not rigid
                        self._skip_corrupt(f"step {step} view {k}", e)
                        continue
                    self.frames_out += 1
                    yield out
                    if self._stop.is_set():
                        return
        finally:
            guard.close()

    def __len__(self) -> int:
        """Live: frames yielded so far."""
        return self.frames_out

    def stats(self) -> dict:
        """Steps received, bad messages, steps dropped from a full queue, frames yielded."""
        return {"frames": self.frames_out, **dict(self.counts), "skipped": dict(self.skipped)}
