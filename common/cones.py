"""Volume of a union of cones (the beyond-range search volume of the best semantic rays).

Pure numpy. Used by the mapper's query answer and by the query client when it merges the
answers of several mapper shards (``query_client.merge``), so both compute the same volume.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np


def _cone_frame(d: np.ndarray) -> np.ndarray:
    """(3, 3) rows: two unit vectors orthogonal to unit ``d``, then ``d``."""
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(d, u), d])


#: ``weighted_union(local, w, frames, origins, dirs, range_m, cos2)``: the per-cone step of
#: :func:`cone_union_volume`'s samples (a faster twin of :func:`_weighted_union` may be given)
WeightedUnion = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float], float]


def _weighted_union(local: np.ndarray, w: np.ndarray, frames: np.ndarray, o: np.ndarray, dirs: np.ndarray,
                    range_m: float, cos2: float) -> float:
    """Σ over cones i and lattice points l of ``w[l] / c``: ``local`` (m, 3) lattice points
    in a cone's frame, ``w`` (m,) their weights, ``frames`` (n, 3, 3) each cone's rows
    (:func:`_cone_frame`), ``o`` (n, 3) apexes (centred), ``dirs`` (n, 3) unit axes; ``c`` the
    number of cones holding point ``l @ frames[i] + o[i]`` (axial distance in (0, range_m],
    ``cos² ≥ cos2``; its own cone always counts)."""
    od = (o * dirs).sum(1)
    oo = (o * o).sum(1)
    total = 0.0
    for i in range(len(o)):
        p = local @ frames[i] + o[i]                            # (m, 3) world (centred)
        tj = p @ dirs.T - od                                    # (m, n) axial distance
        v2 = (p * p).sum(1)[:, None] - 2.0 * (p @ o.T) + oo     # (m, n) |p - o_j|²
        inn = (tj > 0) & (tj <= range_m) & (tj * tj >= v2 * cos2)
        inn[:, i] = True                                        # its own cone, whatever the rounding
        total += float((w / inn.sum(1)).sum())
    return total


def cone_union_volume(origins: np.ndarray, dirs: np.ndarray, half_angle_deg: float, range_m: float,
                      cell_m: float, max_cells: int = 400_000, method: str = "samples",
                      weighted_union: WeightedUnion | None = None) -> float:
    """Volume (m³) of the union of cones (apex ``origins``, unit axes ``dirs``, half-angle,
    cut at axial distance ``range_m``). One cone: exact.

    ``method="samples"`` (default): every cone is filled with the same lattice of points
    (spacing ``max(cell_m, (V/m)^(1/3))``, ``m = max_cells / n`` points per cone; the points
    of an axial layer share the exact volume of that slab of the cone, so a cone's weights
    sum to its exact volume ``V``); a point inside
    ``c`` of the cones contributes ``weight/c``, so the sum is the union's volume. Exact for
    disjoint and for identical cones; otherwise the error is that of the lattice on the
    overlaps only (< 1 % at the defaults, see tests/test_query_latency.py). Cost
    ``O(max_cells · n)``.

    ``method="grid"``: cell centres of an axis-aligned grid over the cones' bounding box
    (cell ``max(cell_m, (box/max_cells)^(1/3))``) that fall in any cone — the reference.

    ``weighted_union``: the samples' per-cone step (:func:`_weighted_union`'s arguments and
    result), e.g. the mapper's C++ twin; the same volume up to float rounding.
    """
    if len(origins) == 0 or range_m <= 0:
        return 0.0
    th = math.radians(min(max(half_angle_deg, 0.1), 89.0))
    v1 = math.pi * range_m ** 3 * math.tan(th) ** 2 / 3.0
    if len(origins) == 1:  # exact
        return float(v1)
    origins = np.asarray(origins, np.float64)
    dirs = np.asarray(dirs, np.float64)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True).clip(1e-12)
    cos2 = math.cos(th) ** 2
    if method == "samples":
        n = len(origins)
        h = max(cell_m, (v1 / max(8, max_cells // n)) ** (1 / 3))
        tan = math.tan(th)
        ax = np.arange(-range_m * tan + h / 2, range_m * tan, h)
        t_layers = np.arange(h / 2, range_m, h)
        pts, wts = [], []
        uu, vv = np.meshgrid(ax, ax, indexing="ij")
        for tl in t_layers:
            sel = uu * uu + vv * vv <= (tl * tan) ** 2
            u, v = (uu[sel], vv[sel]) if sel.any() else (np.zeros(1), np.zeros(1))   # the axis, near the apex
            a, b = tl - h / 2, min(tl + h / 2, range_m)
            layer_vol = math.pi * tan * tan * (b ** 3 - a ** 3) / 3.0                  # exact slab of the cone
            pts.append(np.stack([u, v, np.full(len(u), tl)], 1))
            wts.append(np.full(len(u), layer_vol / len(u)))
        local, w = np.concatenate(pts), np.concatenate(wts)                          # sum(w) == v1
        frames = np.stack([_cone_frame(d) for d in dirs])
        o = origins - origins.mean(0)
        return float((weighted_union or _weighted_union)(local, w, frames, o, dirs, float(range_m), float(cos2)))
    if method != "grid":
        raise ValueError(f"unknown cone union method {method!r} (samples, grid)")
    r_base = range_m * math.tan(th)
    ends = origins + dirs * range_m
    lo = np.minimum(origins, ends).min(0) - r_base
    hi = np.maximum(origins, ends).max(0) + r_base
    vol_box = float(np.prod(hi - lo))
    cell = max(cell_m, (vol_box / max_cells) ** (1 / 3))
    axes = [np.arange(lo[i] + cell / 2, hi[i], cell, dtype=np.float32) for i in range(3)]
    cells = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.zeros(len(cells), bool)
    cos_t = math.cos(th)
    for o, d in zip(origins.astype(np.float32), dirs.astype(np.float32), strict=False):
        v = cells - o
        t = v @ d
        nrm = np.linalg.norm(v, axis=1)
        inside |= (t > 0) & (t <= range_m) & (t >= nrm * cos_t)
    return float(inside.sum() * cell ** 3)
