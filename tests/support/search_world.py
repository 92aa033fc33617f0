"""A small map with frontiers and rays for the search tests: ``apps.bench.query.build_map``'s
random-feature voxels plus small frames of synthetic world 0's ground trajectory (random
features of the same dimension), integrated on demand."""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch


def search_world(dim: int, voxels: int, rays: int) -> tuple[object, object, object, Callable[[int, int], None]]:
    """``(feature space, mapper config, map, frames)``: ``frames(a, b)`` integrates poses
    ``a .. b-1`` of a 6-pose trajectory (24 × 32 pixels, 8 m depth limit) and flushes."""
    from apps.bench.query import _space, build_map
    from synthetic_world import World

    fs = _space(dim)
    cfg, m = build_map(voxels, dim, rays, fs)
    m.cfg.depth_limit = 8.0                     # small frames: a few frontiers and rays
    w = World.generate(0)
    hw = (24, 32)
    K = w.camera(hw, 90.0)
    poses = w.trajectory("ground", 6, seed=0)
    g = torch.Generator().manual_seed(2)

    def frames(a: int, b: int) -> None:
        for p in poses[a:b]:
            r = w.render(p, K, hw)
            m.integrate(p, K, r.depth.astype(np.float32), r.rgb, torch.randn((dim, 6, 8), generator=g))
        m.flush()

    return fs, cfg, m, frames
