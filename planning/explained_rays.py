"""Rays the map has explained: a ray's line meets a voxel the map now holds as occupied
(pure computation).

A ray of the RayFronts map was cast from a pixel with no depth return within range: what
the pixel saw lies on along the ray, at its first surface. When the map later holds an
occupied voxel on that line (the robot came near and mapped it), the ray saw that surface;
its evidence is explained by what is mapped there. Were that surface the target, the search
would name it where it is mapped (a found instance); a far look-alike, mapped and not
named, keeps drawing the robot only through rays like these.

World frame, metres; voxel ``ijk = floor(xyz / vox)``; occupied: value > 0.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from semantic_map import OccupancyView

#: ray samples per query call (bounds the memory of one call: 24 bytes each)
SAMPLES_PER_CALL = 1 << 20


def explained_rays(grid: OccupancyView, vox: float, origins: np.ndarray, dirs: np.ndarray, max_m: float,
                   min_m: float | None = None) -> np.ndarray:
    """(R,) bool: whether ray ``(origins[i], dirs[i])`` (unit directions) meets an occupied
    voxel between ``min_m`` (default one voxel: past the voxel of its own origin) and
    ``max_m`` along it. The line is sampled every half voxel, so a voxel it only grazes at a
    corner may be missed."""
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    if len(o) != len(d):
        raise ValueError(f"{len(o)} ray origins but {len(d)} directions")
    lo = float(vox) if min_m is None else float(min_m)
    out = np.zeros(len(o), bool)
    if len(o) == 0 or max_m <= lo:
        return out
    t = np.arange(lo, float(max_m) + 1e-9, 0.5 * float(vox))
    per = max(1, SAMPLES_PER_CALL // len(t))
    for a in range(0, len(o), per):
        p = o[a:a + per, None, :] + t[None, :, None] * d[a:a + per, None, :]
        ijk = np.floor(p / vox).astype(np.int64).reshape(-1, 3)
        v = grid.query(ijk).numpy().reshape(len(p), len(t))
        out[a:a + per] = (v > 0).any(axis=1)
    return out
