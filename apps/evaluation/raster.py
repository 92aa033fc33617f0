"""Exact, fast shape counts on a voxel grid by row intervals (the benchmark's scoring path).

The search-volume shapes (true cones of half-angle < 90°, the reference's hexagonal
pyramids, balls) are convex, so each meets a *row* of voxel centres (a grid line along the
row axis, the grid's longest axis) in one interval. For every (shape, row) pair two
intervals are computed analytically: one of the shape grown by ``pad`` metres (holds every
voxel the exact test accepts) and one of the shape shrunk by ``pad`` (every voxel in it is
accepted). Voxels of the shrunk interval are counted without a test; only the few voxels
between the two (within ``pad`` of the surface) go through the shape's **exact per-point
test** — the very test the block path (:func:`semantic_map.search_volume.membership_counts`)
applies, so the counts are identical to it, bit for bit. Intervals are accumulated as
+1/−1 into a difference array along the rows; a cumulative sum gives the counts.

Cost: O(shapes × rows) closed-form work + O(grid) instead of O(Σ voxels inside the
shapes), e.g. ~1,000 cones over a 220×185×52 grid in well under a second.

Conventions: voxel ``ijk`` has its centre at ``(ijk + 0.5) · vox`` (metres, float64, the
formula of :meth:`apps.evaluation.data.GroundTruth.centres`); counts are int64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Callable

import numpy as np
import numpy.typing as npt
import torch

from semantic_map import search_volume

ExactTest = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
#: interval function: (shape indices (S,), pad metres) -> (lo_out, hi_out, lo_in, hi_in) float64
#: (S, nb, nc), metres along the row from the centre of its first voxel, of the shapes grown
#: (out) and shrunk (in) by pad; empty where lo > hi
IntervalFn = Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]

_PAIRS_PER_CHUNK = 1 << 16
#: largest box (cells) rasterised densely (8 bytes per cell and temporary)
MAX_BOX_CELLS = 1 << 26
_TESTS_PER_CHUNK = 1 << 20


@dataclass
class RowGrid:
    """Dense box ``lo .. lo + dims − 1`` (voxel indices) split into rows along ``axis``
    (default the longest; ``row_axis`` overrides). Row ``r = ib · dims[c] + ic`` (``b, c`` the
    other two axes in increasing order). :meth:`cells` indexes the box in x-major order,
    independent of the row axis."""

    lo: np.ndarray     # (3,) int64
    dims: np.ndarray   # (3,) int64
    vox: float
    row_axis: int | None = None

    @classmethod
    def around(cls, ijk: np.ndarray, vox: float) -> "RowGrid":
        """The bounding box of voxel indices ``ijk`` (V, 3), V >= 1."""
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        if ijk.shape[0] == 0:
            raise ValueError("RowGrid.around needs at least one voxel")
        if not vox > 0:
            raise ValueError(f"voxel size must be > 0, got {vox}")
        lo = ijk.min(0)
        return cls(lo, ijk.max(0) - lo + 1, float(vox))

    def along(self, axis: int) -> "RowGrid":
        """The same box with rows along ``axis``."""
        return RowGrid(self.lo, self.dims, self.vox, int(axis))

    @property
    def axis(self) -> int:
        return int(np.argmax(self.dims)) if self.row_axis is None else int(self.row_axis)

    @property
    def others(self) -> tuple[int, int]:
        b, c = (k for k in range(3) if k != self.axis)
        return b, c

    @property
    def box_cells(self) -> int:
        return int(np.prod(self.dims.astype(np.int64)))

    @property
    def n_rows(self) -> int:
        b, c = self.others
        return int(self.dims[b] * self.dims[c])

    @property
    def row_len(self) -> int:
        return int(self.dims[self.axis])

    def cells(self, ijk: np.ndarray) -> np.ndarray:
        """(V,) flat box index ``(i · ny + j) · nz + k`` of voxels ``ijk`` (must lie in the box)."""
        rel = np.asarray(ijk, dtype=np.int64).reshape(-1, 3) - self.lo
        if rel.size and ((rel < 0).any() or (rel >= self.dims).any()):
            raise ValueError("voxel outside the grid box")
        return (rel[:, 0] * self.dims[1] + rel[:, 1]) * self.dims[2] + rel[:, 2]

    def centres(self, rows: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """(P, 3) float64 voxel centres of (row, position-along-row) pairs."""
        b, c = self.others
        ijk = np.empty((len(rows), 3), dtype=np.int64)
        ijk[:, self.axis] = self.lo[self.axis] + pos
        ijk[:, b] = self.lo[b] + rows // self.dims[c]
        ijk[:, c] = self.lo[c] + rows % self.dims[c]
        return (ijk.astype(np.float64) + 0.5) * self.vox

    def row_bases(self) -> tuple[float, np.ndarray, np.ndarray]:
        """Centre coordinates of the rows' first voxels, separably: along ``axis`` (scalar),
        ``b`` (nb,) and ``c`` (nc,)."""
        b, c = self.others
        v = self.vox
        return ((self.lo[self.axis] + 0.5) * v, (self.lo[b] + np.arange(self.dims[b]) + 0.5) * v,
                (self.lo[c] + np.arange(self.dims[c]) + 0.5) * v)

    def to_box(self, counts: np.ndarray) -> np.ndarray:
        """Row-layout ``(n_rows, row_len)`` values → box order ``(nx, ny, nz)``."""
        b, c = self.others
        a = self.axis
        arr = counts.reshape(int(self.dims[b]), int(self.dims[c]), self.row_len)
        return np.moveaxis(arr, (0, 1, 2), (b, c, a))


def _expand(rows: np.ndarray, start: np.ndarray, length: np.ndarray, shape: np.ndarray):
    """Every (row, position, shape) of the runs ``[start, start + length)``."""
    n = int(length.sum())
    if n == 0:
        e = np.empty(0, dtype=np.int64)
        return e, e, e
    rr = np.repeat(rows, length)
    ss = np.repeat(shape, length)
    off = np.arange(n, dtype=np.int64) - np.repeat(np.cumsum(length) - length, length)
    return rr, np.repeat(start, length) + off, ss


def raster_counts(grid: RowGrid, n_shapes: int, interval: IntervalFn, exact_test: ExactTest, pad: float,
                  cells: np.ndarray | None = None) -> np.ndarray:
    """Number of shapes holding each box voxel: ``(nx, ny, nz)`` int64, or ``(V,)`` at the
    flat box indices ``cells`` (:meth:`RowGrid.cells`). ``interval(sidx, pad)`` gives ``(lo_out,
    hi_out, lo_in, hi_in)``: the rows' intervals of the shapes grown by ``pad`` (a superset
    of the voxels ``exact_test`` accepts) and shrunk by ``pad`` (a subset)."""
    nb, nc = (int(grid.dims[k]) for k in grid.others)
    n_a, width = grid.row_len, grid.row_len + 1
    size = grid.n_rows * width
    plus: list[np.ndarray] = []
    minus: list[np.ndarray] = []
    if n_shapes:
        step = max(1, _PAIRS_PER_CHUNK // max(1, nb * nc))
        rows_all = np.arange(nb * nc, dtype=np.int64).reshape(1, nb, nc)
        t_rows, t_pos, t_shape = [], [], []
        v = grid.vox
        for s0 in range(0, n_shapes, step):
            sidx = np.arange(s0, min(n_shapes, s0 + step))
            lo_o, hi_o, lo_i, hi_i = interval(sidx, pad)
            with np.errstate(invalid="ignore", over="ignore"):
                # NaN (degenerate arithmetic): whole row as candidate, nothing sure
                Lo = np.ceil(np.clip(np.nan_to_num(lo_o / v, nan=-1.0), -1.0, n_a)).astype(np.int64)
                Ho = np.floor(np.clip(np.nan_to_num(hi_o / v, nan=n_a), -1.0, n_a)).astype(np.int64)
            np.maximum(Lo, 0, out=Lo)
            np.minimum(Ho, n_a - 1, out=Ho)
            outer = Lo <= Ho
            if not outer.any():
                continue
            with np.errstate(invalid="ignore", over="ignore"):
                Li = np.ceil(np.clip(np.nan_to_num(lo_i / v, nan=n_a), -1.0, n_a)).astype(np.int64)
                Hi = np.floor(np.clip(np.nan_to_num(hi_i / v, nan=-1.0), -1.0, n_a)).astype(np.int64)
            np.maximum(Li, Lo, out=Li)
            np.minimum(Hi, Ho, out=Hi)
            sure = outer & (Li <= Hi)
            S = len(sidx)
            rows = np.broadcast_to(rows_all, (S, nb, nc))
            shp = np.broadcast_to(sidx.reshape(S, 1, 1), (S, nb, nc))
            r = rows[sure] * width
            plus.append(r + Li[sure])
            minus.append(r + Hi[sure] + 1)
            # voxels to test: [Lo, Li) and (Hi, Ho] where a sure run exists, else [Lo, Ho]
            ns = outer & ~sure
            for m, st, ln in ((sure, Lo, Li - Lo), (sure, Hi + 1, Ho - Hi), (ns, Lo, Ho - Lo + 1)):
                sel = m & (ln > 0)
                if sel.any():
                    a, b_, c_ = _expand(rows[sel], st[sel], ln[sel], shp[sel])
                    t_rows.append(a)
                    t_pos.append(b_)
                    t_shape.append(c_)
        if t_rows:
            tr, tp, ts = np.concatenate(t_rows), np.concatenate(t_pos), np.concatenate(t_shape)
            for k in range(0, len(tr), _TESTS_PER_CHUNK):
                rr, pp, ss = tr[k:k + _TESTS_PER_CHUNK], tp[k:k + _TESTS_PER_CHUNK], ts[k:k + _TESTS_PER_CHUNK]
                ok = exact_test(torch.from_numpy(grid.centres(rr, pp)), torch.from_numpy(ss)).numpy()
                f = rr[ok] * width + pp[ok]
                plus.append(f)
                minus.append(f + 1)
    diff = np.zeros(size, dtype=np.int64)
    if plus:
        diff += np.bincount(np.concatenate(plus), minlength=size)
        diff -= np.bincount(np.concatenate(minus), minlength=size)
    counts = grid.to_box(np.cumsum(diff.reshape(grid.n_rows, width), axis=1)[:, :n_a])
    if cells is not None:
        return counts.reshape(-1)[np.asarray(cells, dtype=np.int64)]
    return counts


# ----------------------------------------------------------------------------- row geometry
def _rel(grid: RowGrid, o: np.ndarray):
    """Row-start minus point, separably: (S,1,1), (S,nb,1), (S,1,nc) for axes (a, b, c)."""
    xa, xb, xc = grid.row_bases()
    a = grid.axis
    b, c = grid.others
    return ((xa - o[:, a])[:, None, None], (xb[None, :] - o[:, b:b + 1])[:, :, None],
            (xc[None, :] - o[:, c:c + 1])[:, None, :])


def cone_intervals(grid: RowGrid, origins: np.ndarray, dirs: np.ndarray, half_angle_deg: float) -> IntervalFn:
    """Rows ∩ infinite cones ``t >= |x − o| cos α`` (``t = (x − o)·d``), α in (0°, 90°). The
    cone grown (shrunk) by ``g`` has its apex moved by ∓g / sin α along the axis (its
    surface moves by ``g``). On a row ``x = x0 + u·e`` the double cone is the quadratic
    ``A u² + 2 B u + C >= 0``; the nappe is chosen by the sign of ``t``."""
    alpha = math.radians(half_angle_deg)
    if not 0 < alpha < math.pi / 2:
        raise ValueError(f"row rasterisation needs a cone half-angle in (0, 90) degrees, got {half_angle_deg}")
    ca, sa = math.cos(alpha), math.sin(alpha)
    c2, s2 = ca * ca, sa * sa
    ax = grid.axis
    b, c = grid.others
    A_all = dirs[:, ax] ** 2 - c2
    eps = 1e-12
    # per shape: 0 = direction inside the cone angle, +e side; 1 = inside, −e side;
    # 2 = outside (a segment); 3 = along a generator (superset: half-row, subset: empty)
    kind = np.where(A_all > eps, np.where(dirs[:, ax] > 0, 0, 1), np.where(A_all < -eps, 2, 3))

    def group(sidx: np.ndarray, pad: float, k: int):
        d = dirs[sidx]
        ra, rb, rc = _rel(grid, origins[sidx])
        da, db, dc = (d[:, j][:, None, None] for j in (ax, b, c))
        A = A_all[sidx][:, None, None]
        ad = ra * da + rb * db + rc * dc                 # (x0 − o)·d
        hb0 = ad * da - c2 * ra
        C0 = ad * ad - c2 * (ra * ra + rb * rb + rc * rc)
        out = []
        for g in (pad, -pad):
            kk = g / sa                                    # apex shift: x0 − o' = (x0 − o) + kk·d
            hb = hb0 + (kk * s2) * da
            C = C0 + (s2 * kk) * (2.0 * ad + kk)
            if k == 3:
                if g > 0:
                    u0 = -(ad + kk) / da
                    inf = np.full(u0.shape, np.inf)
                    out += [u0, inf] if dirs[sidx[0], ax] > 0 else [-inf, u0]
                else:
                    out += [np.full(ad.shape, np.inf), np.full(ad.shape, -np.inf)]
                continue
            disc = hb * hb - A * C
            sq = np.sqrt(np.maximum(disc, 0.0))
            with np.errstate(divide="ignore", invalid="ignore"):
                if k == 0:       # [larger root, inf)
                    r = np.where(hb <= 0, (sq - hb) / A, C / (-(hb + sq)))
                    out += [r, np.full(r.shape, np.inf)]
                elif k == 1:     # (-inf, smaller root]
                    r = np.where(hb >= 0, -(hb + sq) / A, C / (sq - hb))
                    out += [np.full(r.shape, -np.inf), r]
                else:            # [r1, r2] if real and on the positive nappe
                    q = -(hb + np.copysign(sq, hb))
                    r1 = q / A
                    r2 = np.where(q != 0, C / q, r1)
                    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
                    tmid = ad + kk + da * (0.5 * (lo + hi))
                    ok = (disc >= 0) & (tmid > (-1e-9 if g > 0 else 1e-9))
                    out += [np.where(ok, lo, np.inf), np.where(ok, hi, -np.inf)]
        return out

    def fn(sidx: np.ndarray, pad: float):
        ks = kind[sidx]
        if (ks == ks[0]).all():
            return tuple(group(sidx, pad, int(ks[0])))
        nb_, nc_ = (int(grid.dims[j]) for j in (b, c))
        res = [np.empty((len(sidx), nb_, nc_)) for _ in range(4)]
        for k in np.unique(ks):
            m = ks == k
            for r_, v_ in zip(res, group(sidx[m], pad, int(k)), strict=True):
                r_[m] = v_
        return tuple(res)

    return fn


def ball_intervals(grid: RowGrid, centres: np.ndarray, radii: np.ndarray) -> IntervalFn:
    """Rows ∩ balls ``|x − c| <= r`` (grown radius ``r ± pad``)."""
    def fn(sidx: np.ndarray, pad: float):
        ra, rb, rc = _rel(grid, centres[sidx])
        perp2 = rb * rb + rc * rc
        out = []
        for g in (pad, -pad):
            r = (radii[sidx] + g)[:, None, None]
            h2 = r * r - perp2
            ok = (h2 >= 0) & (r >= 0)
            h = np.sqrt(np.where(ok, h2, 0.0))
            out += [np.where(ok, -ra - h, np.inf), np.where(ok, -ra + h, -np.inf)]
        return tuple(out)

    return fn


def halfspace_intervals(grid: RowGrid, points: np.ndarray, G: np.ndarray, h: np.ndarray) -> IntervalFn:
    """Rows ∩ convex polyhedra ``G[s, k]·(x − p[s]) <= h[s, k]`` for all k (``G`` (S, K, 3),
    ``h`` (S, K)); growing by ``g`` adds ``g · |G[s, k]|`` to ``h``."""
    ax = grid.axis
    b, c = grid.others
    gn = np.linalg.norm(G, axis=2)

    def fn(sidx: np.ndarray, pad: float):
        ra, rb, rc = _rel(grid, points[sidx])
        g = G[sidx]
        shape = (len(sidx), int(grid.dims[b]), int(grid.dims[c]))
        out = []
        for grow in (pad, -pad):
            lo = np.full(shape, -np.inf)
            hi = np.full(shape, np.inf)
            for k in range(g.shape[1]):
                ga, gb, gc = (g[:, k, j][:, None, None] for j in (ax, b, c))
                beta = (h[sidx, k] + grow * gn[sidx, k])[:, None, None] - (ga * ra + gb * rb + gc * rc)
                with np.errstate(divide="ignore", invalid="ignore"):
                    lim = beta / ga
                gpos = np.broadcast_to(ga > 0, shape)
                gneg = np.broadcast_to(ga < 0, shape)
                hi = np.where(gpos, np.minimum(hi, lim), hi)
                lo = np.where(gneg, np.maximum(lo, lim), lo)
                dead = ~(gpos | gneg) & (beta < 0)
                lo = np.where(dead, np.inf, lo)
                hi = np.where(dead, -np.inf, hi)
            out += [lo, hi]
        return tuple(out)

    return fn


# ----------------------------------------------------------------------------- shapes
def _pad(grid: RowGrid) -> float:
    return 1e-4 * grid.vox


def _exact_on_rows(exact: ExactTest, rows: torch.Tensor, x: torch.Tensor, si: torch.Tensor) -> torch.Tensor:
    """``exact`` (a test over all shapes) on the shapes ``rows[si]`` (``si`` indexes a subset)."""
    return exact(x, rows[si])


def cone_counts(grid: RowGrid, origins: npt.ArrayLike, dirs: npt.ArrayLike, half_angle_deg: float,
                cells: np.ndarray | None = None) -> np.ndarray:
    """Counts of true cones (apex ``origins``, axes ``dirs``, infinite) — equal to
    :func:`apps.evaluation.shapes.cone_counts` on the voxel centres. A cone whose axis makes
    the angle α with the row axis (a generator along the rows, e.g. (1, 1, 0)/√2 at 45°) is
    rasterised along another axis."""
    o = torch.as_tensor(origins).to(torch.float64).reshape(-1, 3)
    _, exact = search_volume.cone_tests(o, torch.as_tensor(dirs).to(torch.float64).reshape(-1, 3), half_angle_deg)
    d = torch.nn.functional.normalize(torch.as_tensor(dirs).to(torch.float64).reshape(-1, 3), dim=1).numpy()
    on = o.numpy()
    c2 = math.cos(math.radians(half_angle_deg)) ** 2
    order = [grid.axis, *grid.others]
    choice = np.full(len(d), grid.axis)
    for k in reversed(order):                 # the first axis in `order` not along a generator wins
        choice = np.where(np.abs(d[:, k] ** 2 - c2) > 1e-6, k, choice)
    out = None
    for k in order:
        sel = np.flatnonzero(choice == k)
        if not sel.size and out is not None:
            continue
        g = grid.along(k)
        fn = cone_intervals(g, on[sel], d[sel], half_angle_deg)
        rows = torch.from_numpy(sel)
        cnt = raster_counts(g, len(sel), fn, partial(_exact_on_rows, exact, rows), _pad(g), cells)
        out = cnt if out is None else out + cnt
    assert out is not None                 # the first axis of `order` always counts
    return out


def ball_counts(grid: RowGrid, centres: npt.ArrayLike, radii: npt.ArrayLike,
                cells: np.ndarray | None = None) -> np.ndarray:
    """Counts of balls — equal to :func:`apps.evaluation.shapes.ball_counts` on the voxel centres."""
    c = torch.as_tensor(centres).to(torch.float64).reshape(-1, 3)
    r = torch.as_tensor(radii, dtype=torch.float64).reshape(-1)
    if r.numel() == 1 and c.shape[0] != 1:
        r = r.expand(c.shape[0])

    def exact(x: torch.Tensor, si: torch.Tensor) -> torch.Tensor:
        return (x - c[si]).norm(dim=1) <= r[si]

    fn = ball_intervals(grid, c.numpy(), r.numpy())
    return raster_counts(grid, c.shape[0], fn, exact, _pad(grid), cells)


def reference_cone_counts(grid: RowGrid, origins: npt.ArrayLike, dirs: npt.ArrayLike, subsampling: float,
                          half_angle_deg: float, num_segs: int = 6, cells: np.ndarray | None = None) -> np.ndarray:
    """Counts of the reference's hexagonal pyramids (:mod:`apps.evaluation.shapes`) — equal to
    :func:`apps.evaluation.shapes.reference_cone_counts` on the voxel centres."""
    from apps.evaluation.shapes import reference_pyramid_tests, rotation_z_to

    vox = grid.vox
    o = torch.as_tensor(origins).to(torch.float64).reshape(-1, 3)
    dd = torch.as_tensor(dirs).to(torch.float64).reshape(-1, 3)
    _, exact = reference_pyramid_tests(o, dd, vox, subsampling, half_angle_deg, num_segs)
    R = rotation_z_to(dd).numpy()                         # local = R^T (x − o)
    r0 = vox * subsampling
    slope = (5 * vox * math.tan(math.radians(half_angle_deg)) - r0) / (4 * vox)
    ang = 2 * math.pi * (np.arange(num_segs) + 0.5) / num_segs
    apo = math.cos(math.pi / num_segs)
    ex, ey, ez = R[:, :, 0], R[:, :, 1], R[:, :, 2]       # local axes in world coordinates (S, 3)
    G = [-ez]                                              # z >= vox
    H = [np.full(len(R), -vox)]
    for a in ang:
        G.append(math.cos(a) * ex + math.sin(a) * ey - apo * slope * ez)
        H.append(np.full(len(R), apo * (r0 - vox * slope) + 1e-12))
    fn = halfspace_intervals(grid, o.numpy(), np.stack(G, 1), np.stack(H, 1))
    return raster_counts(grid, o.shape[0], fn, exact, max(_pad(grid), 1e-9), cells)
