"""The synthetic world (``synthetic_world``) as a frame source.

Renders the world along one of its trajectories, directly at the requested resolution
(``resolution``, default 240×320 when null) with horizontal FoV ``hfov``; frames carry
exact ground-truth labels (``class_names = world.classes``, 0 = sky). Stamps are
``index / fps`` (fps default 10).

World frame: the synthetic world's frame, z up (x east, y north), ground at z = 0.
"""
from __future__ import annotations

import numpy as np

from edge.sources.base import FrameSource, filter_poses, native_frame
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError

DEFAULT_HW = (240, 320)


class SyntheticSource(FrameSource):
    kind = "synthetic"
    default_fps = 10.0

    def __init__(self, cfg: SourceConfig, world=None):
        """``world``: an already built ``synthetic_world.World`` (else ``World.generate(seed, preset)``)."""
        super().__init__(cfg)
        if cfg.n_frames < 0:
            raise SourceError(f"synthetic: n_frames must be >= 0, got {cfg.n_frames}")
        if not 0 < cfg.hfov < 180:
            raise SourceError(f"synthetic: hfov must be in (0, 180) degrees, got {cfg.hfov}")
        if world is None:
            try:
                from synthetic_world import World
            except ImportError as e:
                raise SourceError(f"synthetic: the synthetic world (synthetic_world) is not available: {e}") from None
            try:
                world = World.generate(cfg.seed, cfg.preset)
            except (ValueError, KeyError) as e:
                raise SourceError(f"synthetic: cannot generate world seed={cfg.seed} preset={cfg.preset!r}: "
                                  f"{e}") from None
        self.world = world
        try:
            self.poses = np.asarray(world.trajectory(cfg.trajectory, cfg.n_frames, seed=cfg.trajectory_seed),
                                    dtype=np.float64).reshape(-1, 4, 4)
        except (ValueError, KeyError) as e:
            raise SourceError(f"synthetic: bad trajectory {cfg.trajectory!r}: {e}") from None
        self.native_hw = self.out_hw or DEFAULT_HW
        self.native_K = np.asarray(world.camera(self.native_hw, cfg.hfov), dtype=np.float64)
        self.class_names = list(world.classes)
        self.name = f"synthetic:seed{cfg.seed}:{cfg.preset}:{cfg.trajectory}"
        self.world_frame = "synthetic world frame, z up (x east, y north), ground at z = 0"
        self._select(filter_poses(self.poses, "world trajectory", self))
        self._report_skips()

    def _load(self, i: int):
        r = self.world.render(self.poses[i], self.native_K, self.native_hw)
        return native_frame(i, i / self.fps, self.poses[i], self.native_K,
                            np.asarray(r.depth, dtype=np.float32), np.asarray(r.rgb, dtype=np.uint8),
                            np.asarray(r.labels, dtype=np.int32))
