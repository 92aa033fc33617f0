"""Volume of a union of cones (the beyond-range search volume of the best semantic rays).

Pure numpy. Used by the mapper's query answer and by the query client when it merges the
answers of several mapper shards (``query_client.merge``), so both compute the same volume.
"""
from __future__ import annotations

import math

import numpy as np


def _cone_frame(d: np.ndarray) -> np.ndarray:
    """(3, 3) rows: two unit vectors orthogonal to unit ``d``, then ``d``."""
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(d, u), d])


def cone_union_volume(origins: np.ndarray, dirs: np.ndarray, half_angle_deg: float, range_m: float,
                      cell_m: float, max_cells: int = 400_000, method: str = "samples") -> float:
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
        centre = origins.mean(0)
        o = origins - centre
        od = (o * dirs).sum(1)
        oo = (o * o).sum(1)
        total = 0.0
        for i in range(n):
            p = local @ _cone_frame(dirs[i]) + o[i]                 # (m, 3) world (centred)
            tj = p @ dirs.T - od                                    # (m, n) axial distance
            v2 = (p * p).sum(1)[:, None] - 2.0 * (p @ o.T) + oo     # (m, n) |p - o_j|²
            inn = (tj > 0) & (tj <= range_m) & (tj * tj >= v2 * cos2)
            inn[:, i] = True                                        # its own cone, whatever the rounding
            total += float((w / inn.sum(1)).sum())
        return total
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
