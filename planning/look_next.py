"""Where to look next: ranked exploration goals at frontiers, scored by the semantic ray
frontiers that point toward the targets (pure computation).

World frame, metres, z up; headings are yaw angles in radians in the xy plane,
counter-clockwise from +x (``atan2(dy, dx)``).

For each frontier (coarse cell centre from the map's frontier table):

* ``score`` / ``target``: the best target score of the rays whose origin lies within
  ``ray_radius_m`` of the frontier centre (rays are attached to frontier centres), and the
  target it belongs to (score 0 and target ``None`` without such rays);
* ``ray_z``: the best :func:`ray_outlier_z` of those rays over the targets (0 without such
  rays or without the caller's ``ray_z``): how far a ray's evidence for the target (the
  caller's: the mapper passes its cosine to what sets the target apart from the other
  phrases) stands out among all rays. A far target fills a small part of its rays' mean
  feature, so its probability is ~0 and says nothing; its rays still read more like it than
  the others do;
* ``position``: a viewpoint — the centre of a map voxel within ``standoff_m`` of the
  frontier centre that is **free** in the map and has no occupied voxel among its 26
  neighbours, the closest such voxel to the frontier centre (frontiers without one give no
  goal);
* ``heading_rad``: yaw of the score-weighted mean direction of the supporting rays of the
  target (if it has a horizontal component), else yaw toward the frontier centre; when the
  score rounds to 0 and ``ray_z`` > 0, the rays and weights are those of ``ray_z`` (the
  supporting ``rays`` listed are then the outliers); at most ``max_rays`` rays, best first
  (ties by ray index);
* ``gain_m3``: unknown volume within ``sensing_radius_m`` of the viewpoint, counted on the
  occupancy grid (on a lattice of every ``step``-th voxel when the sphere is large, each
  sample standing for ``(step·vox)^3``);
* ``distance_m``: straight-line distance from ``from_xyz`` (0 without it).

Goals are ranked by score to three decimals (descending: softmax at temperature 100
saturates, and below 0.001 it tells nothing apart), then by ``ray_z`` (descending), then by
``gain_m3 / (1 + distance_m)`` (descending); at most one goal per viewpoint voxel. With
``from_xyz``, ``explore_share`` of the ``max_goals`` places go to the goals with the best
``gain_m3 / (1 + distance_m)`` among those the ranking leaves out: when more frontiers hold
evidence than there are places (a robot amid frontiers that once saw a far landmark), the
list still shows the way on. Only the ``max_candidates`` best frontiers by score (then
distance), the ``max_candidates`` best by ``ray_z`` and, with ``from_xyz``, the
``max_candidates`` nearest are examined.
"""
from __future__ import annotations

import functools
import hashlib
import math
import weakref
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch

if TYPE_CHECKING:
    from semantic_map import OccupancyView

#: per-viewpoint samples for the gain count (the lattice is coarsened above this)
GAIN_SAMPLES_PER_AXIS = 25


@dataclass
class Goal:
    """One exploration goal (see the module docstring for each field's meaning)."""

    position: np.ndarray
    heading_rad: float
    score: float
    gain_m3: float
    distance_m: float
    target: str | None
    frontier: np.ndarray
    rays: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    ray_z: float = 0.0

    def as_dict(self) -> dict:
        """Plain-Python fields (``rays``: list of unit directions [dx, dy, dz])."""
        return dict(position=[float(v) for v in self.position], heading_rad=float(self.heading_rad),
                    score=float(self.score), gain_m3=float(self.gain_m3), distance_m=float(self.distance_m),
                    target=self.target, frontier=[float(v) for v in self.frontier],
                    rays=[[float(v) for v in d] for d in self.rays], ray_z=float(self.ray_z))

    @classmethod
    def from_dict(cls, d: dict) -> "Goal":
        """The goal of its :meth:`as_dict` form (a search reply's ``look_next`` entry); a field
        left out reads 0 (``frontier``: the position, ``rays``: none, ``target``: None)."""
        pos = np.asarray(d["position"], np.float64)
        return cls(pos, float(d.get("heading_rad", 0.0)), float(d.get("score", 0.0)), float(d.get("gain_m3", 0.0)),
                   float(d.get("distance_m", 0.0)), d.get("target"), np.asarray(d.get("frontier", pos), np.float64),
                   np.asarray(d.get("rays", []), np.float32).reshape(-1, 3), float(d.get("ray_z", 0.0)))


def points_in_polygon(xy: np.ndarray, polygon: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """(N,) bool: points (N, 2) inside the simple polygon [[x, y], ...] (even-odd rule;
    points on an edge may fall either side)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    inside = np.zeros(len(xy), bool)
    x, y = xy[:, 0], xy[:, 1]
    for a, b in zip(poly, np.roll(poly, -1, 0), strict=True):
        crosses = (a[1] > y) != (b[1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[0] + (y - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        inside ^= crosses & (x < xc)
    return inside


def _values(grid, ijk: np.ndarray) -> np.ndarray:
    v = grid.query(torch.as_tensor(np.ascontiguousarray(ijk, np.int64)))
    return np.asarray(v.cpu() if isinstance(v, torch.Tensor) else v, np.int8)


def _near_cells(points: np.ndarray, origins: np.ndarray, radius: float) -> np.ndarray:
    """(N,) bool: whether a cell of side ``radius`` holding an origin is among the 27 cells
    around each point's cell (necessary for an origin within ``radius``; superset, exact test
    left to the caller)."""
    if radius <= 0 or not np.isfinite(radius):
        return np.ones(len(points), bool)
    cell = radius * (1.0 + 1e-6)                 # a little larger: rounding cannot split a pair by 2 cells
    cp = np.floor(points / cell).astype(np.int64)
    co = np.floor(origins / cell).astype(np.int64)
    lo = np.minimum(cp.min(0), co.min(0)) - 1
    span = np.maximum(cp.max(0), co.max(0)) - lo + 2
    cp -= lo
    co -= lo
    ax = np.array([-1, 0, 1])
    off = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    if float(span[0]) * float(span[1]) * float(span[2]) <= NEAR_DENSE_CELLS:
        grid = np.zeros((int(span[0]), int(span[1]), int(span[2])), bool)
        for d in off:
            grid[co[:, 0] + d[0], co[:, 1] + d[1], co[:, 2] + d[2]] = True
        return grid[cp[:, 0], cp[:, 1], cp[:, 2]]
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0 ** 62:
        return np.ones(len(points), bool)

    def key(c: np.ndarray) -> np.ndarray:
        return (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]

    dil = np.unique(key((np.unique(co, axis=0)[:, None, :] + off[None]).reshape(-1, 3)))
    kp = key(cp)
    pos = np.minimum(np.searchsorted(dil, kp), len(dil) - 1)
    return dil[pos] == kp


#: cells (bytes) up to which :func:`_near_cells` marks the rays' cells on a dense grid
NEAR_DENSE_CELLS = 1 << 25


def ray_pairs(frontiers: np.ndarray, ray_origins: np.ndarray, radius: float,
              rays_tree: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """(frontier index, ray index) int64 of every pair whose ray origin lies within ``radius``
    (m) of the frontier centre: one sparse neighbour search, no per-frontier loop.
    ``rays_tree``: a ``scipy.spatial.cKDTree`` of ``ray_origins`` when the caller has one."""
    f = np.asarray(frontiers, np.float64).reshape(-1, 3)
    o = np.asarray(ray_origins, np.float64).reshape(-1, 3)
    none = np.zeros(0, np.int64)
    if len(f) == 0 or len(o) == 0:
        return none, none
    from scipy.spatial import cKDTree

    # exact pre-filter: a frontier can have a ray within ``radius`` only if one lies in the 27
    # cells (side ``radius``) around its own cell; only those frontiers go to the tree search
    sub = np.flatnonzero(_near_cells(f, o, radius))
    if not len(sub):
        return none, none
    pairs = cKDTree(f[sub]).sparse_distance_matrix(rays_tree if rays_tree is not None else cKDTree(o), radius,
                                                    output_type="ndarray")
    return sub[pairs["i"].astype(np.int64)], pairs["j"].astype(np.int64)


def _support_from_pairs(n_frontiers: int, pairs: tuple[np.ndarray, np.ndarray], s: np.ndarray) -> np.ndarray:
    best = np.zeros((n_frontiers, s.shape[1]))
    fi, ri = pairs
    if len(fi):
        for t in range(s.shape[1]):
            np.maximum.at(best[:, t], fi, s[ri, t])
    return best


def ray_support(frontiers: np.ndarray, ray_origins: np.ndarray, ray_scores: np.ndarray,
                radius: float, rays_tree: Any = None) -> np.ndarray:
    """(F, T) best score per target of the rays whose origin lies within ``radius`` (m) of each
    frontier centre (F, 3); 0 where none (pairs from :func:`ray_pairs`)."""
    f = np.asarray(frontiers, np.float64).reshape(-1, 3)
    o = np.asarray(ray_origins, np.float64).reshape(-1, 3)
    s = np.asarray(ray_scores, np.float64)
    s = s.reshape(len(o), s.shape[-1] if s.ndim == 2 else 1)
    return _support_from_pairs(len(f), ray_pairs(f, o, radius, rays_tree), s)


class LookNextCache:
    """What :func:`look_next` computes without the targets, kept between calls: the rays'
    KD-tree, the frontier–ray pairs within the ray radius (and the frontiers' support from
    the last few ray score sets), each examined frontier's viewpoint and each viewpoint's
    gain, the frontiers' distances from the last few starts. Valid while the frontiers, the
    ray origins, the parameters and the grid (its object and ``revision``) are those it was
    filled with; otherwise
    :meth:`bind` empties what changed: the pairs and tree when the frontiers or rays changed,
    the viewpoints when the frontiers or the grid changed, the gains when the grid changed.
    Results are exactly those of a call without a cache (each is a function of its own
    inputs only). Not thread-safe: one caller at a time."""

    def __init__(self) -> None:
        self.f: np.ndarray | None = None
        self.o: np.ndarray | None = None
        self.geo: tuple = ()
        self.grid: tuple = ()
        self.tree: Any = None
        self.pairs: tuple[np.ndarray, np.ndarray] | None = None
        self.views: dict[int, np.ndarray | None] = {}
        self.gains: dict[tuple, float] = {}
        self.dist: dict[tuple, np.ndarray] = {}      # start -> frontiers' distances from it
        self.f_cols: np.ndarray | None = None         # (3, F) the frontiers' coordinates by axis
        # sha1 of (ray scores, ray z) -> the frontiers' support from them (several robots, one version)
        self.support: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = {}
        self.hits = 0                        # calls that reused the pairs (for tests and timings)

    def bind(self, grid, f: np.ndarray, o: np.ndarray, geo: tuple[float, float, float, float]) -> None:
        """Keep what is still valid for this call's inputs (class docstring); ``geo`` is
        ``(ray radius, standoff, voxel size, sensing radius)``."""
        same_f = self.f is not None and self.f.shape == f.shape and np.array_equal(self.f, f)
        same_o = self.o is not None and self.o.shape == o.shape and np.array_equal(self.o, o)
        rev = int(getattr(grid, "revision", -1))
        same_grid = self.grid != () and self.grid[0]() is grid and self.grid[1] == rev and rev >= 0
        old = self.geo if self.geo else (None,) * 4
        if not same_o:
            self.tree = None
        if not same_f:
            self.dist, self.f_cols = {}, None
        if not (same_f and same_o and old[0] == geo[0]):
            self.pairs = None
            self.support = {}
        else:
            self.hits += 1
        if not (same_f and same_grid and old[1:3] == geo[1:3]):
            self.views = {}
        if not (same_grid and old[2:] == geo[2:]):
            self.gains = {}
        self.f = self.f if same_f else f.copy()
        self.o = self.o if same_o else o.copy()
        self.geo, self.grid = geo, (weakref.ref(grid), rev)

    def frontier_support(self, n_f: int, scores: np.ndarray, zs: np.ndarray | None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """``(best, fscore, bz, fz, pos)`` of :func:`look_next` for the bound pairs: each
        frontier's best ray score per target (F, T) and over targets (F,), the same of the
        rays' z (zeros without ``zs``), and the frontiers with a positive ``fscore`` or ``fz``
        (None if either has a negative value); kept for the last few score sets while the
        pairs stay (the robots of one map version ask with the same scores)."""
        h = hashlib.sha1(np.ascontiguousarray(scores).tobytes())
        h.update(b"-" if zs is None else np.ascontiguousarray(zs).tobytes())
        key = h.digest() + repr((scores.shape, None if zs is None else zs.shape)).encode()
        got = self.support.get(key)
        if got is None:
            assert self.pairs is not None
            best = _support_from_pairs(n_f, self.pairs, scores)
            fscore = best.max(1) if best.shape[1] else np.zeros(n_f)
            bz, fz = np.zeros((n_f, scores.shape[1])), np.zeros(n_f)
            if zs is not None:
                bz = _support_from_pairs(n_f, self.pairs, zs)
                fz = bz.max(1)
            nonneg = n_f > 0 and fscore.min() >= 0 and fz.min() >= 0
            pos = np.flatnonzero((fscore > 0) | (fz > 0)) if nonneg else None
            got = self.support[key] = (best, fscore, bz, fz, pos)
            while len(self.support) > SUPPORT_SETS:
                self.support.pop(next(iter(self.support)))
        return got

    def distances(self, f: np.ndarray, start: np.ndarray) -> np.ndarray:
        """(F,) distances (m) of the bound frontiers ``f`` from ``start``, kept for the last
        few starts while the frontiers stay (a planner's repeated search, several robots)."""
        key = tuple(float(v) for v in start)
        d = self.dist.get(key)
        if d is None:
            if self.f_cols is None or self.f_cols.shape[1] != len(f):
                self.f_cols = np.ascontiguousarray(f.T)            # x, y, z rows: three flat passes
            x = self.f_cols[0] - start[0]
            d = x * x
            for a in (1, 2):
                np.subtract(self.f_cols[a], start[a], out=x)
                d += x * x
            d = self.dist[key] = np.sqrt(d, out=d)
            while len(self.dist) > DISTANCE_STARTS:
                self.dist.pop(next(iter(self.dist)))
        return d

    def fill_views(self, grid, vox: float, f: np.ndarray, order: np.ndarray, standoff: float) -> None:
        """Viewpoints of frontiers ``f[order]`` not kept yet (one grid read for them)."""
        todo = [int(i) for i in order if int(i) not in self.views]
        if todo:
            self.views.update(zip(todo, _viewpoints(grid, vox, f[todo], standoff), strict=True))

    def fill_gains(self, grid, vox: float, goals: list[Goal], radius: float) -> None:
        """Set each goal's ``gain_m3``: a function of its viewpoint's voxel only
        (:func:`unknown_volume`), kept per voxel."""
        if not goals:
            return
        keys = [tuple(np.floor(g.position / vox).astype(np.int64).tolist()) for g in goals]
        new = list(dict.fromkeys(key for key in keys if key not in self.gains))
        if new:
            got = unknown_volume(grid, vox, (np.asarray(new, np.float64) + 0.5) * vox, radius)
            self.gains.update(zip(new, got.tolist(), strict=True))
        for g, key in zip(goals, keys, strict=True):
            g.gain_m3 = float(self.gains[key])


#: starts whose frontier distances :class:`LookNextCache` keeps (robots searching at once)
DISTANCE_STARTS = 8
#: ray score sets whose frontier support :class:`LookNextCache` keeps (the searches of one map version)
SUPPORT_SETS = 8

#: fewer rays than this in the area: no ray_z (a median and spread of a handful say nothing)
MIN_RAYS_FOR_Z = 10


def ray_outlier_z(values: np.ndarray, resolution: float = 0.0) -> np.ndarray:
    """(T, R) modified z-score of each ray's value (a similarity) for each target among the
    ``R`` rays (Iglewicz and Hoaglin): ``0.6745 · (v − median) / MAD`` per target, MAD the
    median absolute deviation; 0 where fewer than :data:`MIN_RAYS_FOR_Z` rays or a zero MAD,
    and where ``|v − median|`` < ``resolution`` (a value within the measurement's resolution
    of the median is not told apart from it, however small the MAD)."""
    c = np.asarray(values, np.float64)
    c = c if c.ndim == 2 else c.reshape(1, -1)
    z = np.zeros(c.shape, np.float32)
    if c.shape[1] < MIN_RAYS_FOR_Z:
        return z
    med = np.median(c, axis=1, keepdims=True)
    mad = np.median(np.abs(c - med), axis=1, keepdims=True)
    ok = mad[:, 0] > 0
    z[ok] = (0.6745 * (c[ok] - med[ok]) / mad[ok]).astype(np.float32)
    z[np.abs(c - med) < resolution] = 0.0
    return z


def _viewpoints(grid, vox: float, centres: np.ndarray, standoff: float) -> list[np.ndarray | None]:
    """Per frontier centre (K, 3): the centre of the free voxel nearest it within
    ``standoff`` whose 26 neighbours are not occupied; None if there is none. One grid read
    for all centres."""
    r = max(1, int(math.ceil(standoff / vox)))
    c = np.floor(np.asarray(centres, np.float64).reshape(-1, 3) / vox).astype(np.int64)
    ax = np.arange(-r - 1, r + 2)
    n = len(ax)
    off = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    vals = _values(grid, (c[:, None, :] + off[None]).reshape(-1, 3)).reshape(len(c), n, n, n)
    occ = vals > 0
    near = occ.copy()                          # occupied among the 26 neighbours (or itself)
    for axis in (1, 2, 3):                     # separable: a 3-wide max along each axis in turn
        grown = near.copy()
        lo = [slice(None)] * 4
        hi = [slice(None)] * 4
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        grown[tuple(lo)] |= near[tuple(hi)]
        grown[tuple(hi)] |= near[tuple(lo)]
        near = grown
    ok = (vals < 0) & ~near
    ok[:, [0, -1]] = False                     # neighbours outside the read
    ok[:, :, [0, -1]] = False
    ok[:, :, :, [0, -1]] = False
    ok = ok.reshape(len(c), -1)
    cells = np.flatnonzero(ok.any(0))          # offsets free somewhere: the only ones to measure
    out: list[np.ndarray | None] = [None] * len(c)
    if not len(cells):
        return out
    cand = (c[:, None, :] + off[None, cells] + 0.5) * vox                  # (K, M, 3) cell centres
    d = np.linalg.norm(cand - np.asarray(centres, np.float64).reshape(-1, 3)[:, None, :], axis=2)
    d[~(ok[:, cells] & (d <= standoff + 1e-9))] = np.inf
    best = np.argmin(d, axis=1)                # the nearest (ties: the first in C order, as argwhere)
    for k in np.flatnonzero(np.isfinite(d[np.arange(len(c)), best])):
        out[int(k)] = cand[k, best[k]]
    return out


@functools.lru_cache(maxsize=8)
def _gain_lattice(vox: float, radius: float) -> tuple[int, np.ndarray]:
    """``(step, offsets)``: :func:`unknown_volume`'s sample lattice (voxel offsets within
    ``radius`` on every ``step``-th voxel; read-only)."""
    r_vox = max(0, int(math.ceil(radius / vox)))
    step = max(1, int(math.ceil((2 * r_vox + 1) / GAIN_SAMPLES_PER_AXIS)))
    ax = np.arange(-(r_vox // step), r_vox // step + 1) * step
    off = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    off = off[np.linalg.norm(off * vox, axis=1) <= radius + 1e-9]
    off.setflags(write=False)
    return step, off


def unknown_volume(grid: OccupancyView, vox: float, centres: np.ndarray, radius: float) -> np.ndarray:
    """(N,) unknown volume (m³) within ``radius`` of each point (N, 3), counted on the map's
    voxels (a lattice of every ``step``-th voxel for large radii, see the module docstring)."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    step, off = _gain_lattice(float(vox), float(radius))
    out = np.zeros(len(c))
    per = max(1, (1 << 20) // max(1, len(off)))
    for s in range(0, len(c), per):
        base = np.floor(c[s:s + per] / vox).astype(np.int64)
        vals = _values(grid, (base[:, None, :] + off[None]).reshape(-1, 3)).reshape(len(base), len(off))
        out[s:s + per] = (vals == 0).sum(1) * (step * vox) ** 3
    return out


def _heading(view: np.ndarray, frontier: np.ndarray, dirs: np.ndarray, w: np.ndarray) -> float:
    if len(dirs):
        m = (dirs * np.maximum(w, 1e-12)[:, None]).sum(0)
        if math.hypot(m[0], m[1]) > 1e-6:
            return math.atan2(m[1], m[0])
    d = frontier - view
    return math.atan2(d[1], d[0]) if math.hypot(d[0], d[1]) > 1e-9 else 0.0


def _best_first(score: np.ndarray, dist: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best entries by score (descending), then distance (ascending), then
    index: ``np.lexsort((dist, -score))[:k]`` without sorting everything (partitions first)."""
    n = len(score)
    if k >= n:
        return np.lexsort((dist, -score))
    if k <= 0:
        return np.zeros((0,), np.int64)
    neg = -score
    kth = np.partition(neg, k - 1)[k - 1]
    better = np.flatnonzero(neg < kth)
    tie = np.flatnonzero(neg == kth)
    need = k - len(better)
    if len(tie) > need:
        dthr = np.partition(dist[tie], need - 1)[need - 1]
        closer = tie[dist[tie] < dthr]
        tie = np.concatenate([closer, tie[dist[tie] == dthr][:need - len(closer)]])
    cand = np.sort(np.concatenate([better, tie]))
    return cand[np.lexsort((dist[cand], neg[cand]))]


def _nearest(dist: np.ndarray, k: int) -> np.ndarray:
    """``_best_first(np.zeros(len(dist)), dist, k)``: the ``k`` nearest by distance, then index."""
    if k >= len(dist):
        return np.argsort(dist, kind="stable")
    if k <= 0:
        return np.zeros((0,), np.int64)
    dthr = np.partition(dist, k - 1)[k - 1]
    closer = np.flatnonzero(dist < dthr)
    cand = np.concatenate([closer, np.flatnonzero(dist == dthr)[:k - len(closer)]])
    return cand[np.lexsort((cand, dist[cand]))]


def _candidates(fscore: np.ndarray, fz: np.ndarray, fdist: np.ndarray, k: int, pos: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(_best_first(fscore, fdist, k), _best_first(fz, fdist, k), _best_first(0, fdist, k))``
    with one pass over all frontiers: scores are >= 0 and few are > 0, so past the positive
    ones each list continues with the nearest zero-score frontiers, which lie among the
    ``k + (number of positives)`` nearest of all (by distance, then index). ``pos``: those
    positives when known (both scores then >= 0)."""
    n = len(fdist)
    if pos is None and (n == 0 or fscore.min() < 0 or fz.min() < 0):
        return _best_first(fscore, fdist, k), _best_first(fz, fdist, k), _best_first(np.zeros(n), fdist, k)
    if pos is None:
        pos = np.flatnonzero((fscore > 0) | (fz > 0))
    near = _nearest(fdist, k + len(pos))

    def best(sc: np.ndarray) -> np.ndarray:
        p = pos[sc[pos] > 0]
        top = p[_best_first(sc[p], fdist[p], k)]
        if len(top) >= k:
            return top
        return np.concatenate([top, near[sc[near] == 0][:k - len(top)]])

    return best(fscore), best(fz), near[:k]


def _one_per_voxel(order: np.ndarray, views: dict[int, np.ndarray | None], vox: float
                   ) -> tuple[list[int], list[np.ndarray]]:
    """The frontiers of ``order`` with a viewpoint, the first of each viewpoint voxel, and
    their viewpoints."""
    picked, out = [], []
    seen: set = set()
    for i in order.tolist():
        v = views[i]
        if v is None:
            continue
        key = tuple(np.floor(v / vox).astype(np.int64).tolist())
        if key not in seen:
            seen.add(key)
            picked.append(i)
            out.append(v)
    return picked, out


def look_next(grid: OccupancyView, vox: float, frontiers: np.ndarray, ray_origins: np.ndarray, ray_dirs: np.ndarray,
              ray_scores: np.ndarray, targets: list[str], from_xyz: Sequence[float] | np.ndarray | None = None, *,
              ray_z: np.ndarray | None = None,
              ray_radius_m: float = 1.0, standoff_m: float = 1.0, sensing_radius_m: float = 3.0,
              max_goals: int = 10, max_candidates: int = 64, max_rays: int = 5,
              explore_share: float = 0.25, cache: LookNextCache | None = None) -> list[Goal]:
    """Ranked exploration goals (module docstring). ``frontiers`` (F, 3) frontier centres
    (already filtered to the area of interest), rays ``(R, 3)`` origins and unit directions,
    ``ray_scores`` (R, T) per target in [0, 1], ``targets`` the T names, ``ray_z`` (R, T)
    :func:`ray_outlier_z` of the rays (None: every goal's ``ray_z`` is 0). ``cache``: the
    target-free work of earlier calls (:class:`LookNextCache`; the same goals either way)."""
    f = np.asarray(frontiers, np.float64).reshape(-1, 3)
    dirs = np.asarray(ray_dirs, np.float64).reshape(-1, 3)
    scores = np.asarray(ray_scores, np.float64)
    if scores.size != len(dirs) * len(targets):
        raise ValueError(f"ray_scores has shape {scores.shape}, expected ({len(dirs)}, {len(targets)})")
    scores = scores.reshape(len(dirs), len(targets))
    if len(f) == 0 or max_goals <= 0:
        return []
    from scipy.spatial import cKDTree

    o = np.asarray(ray_origins, np.float64).reshape(-1, 3)
    c = cache if cache is not None else LookNextCache()
    c.bind(grid, f, o, (float(ray_radius_m), float(standoff_m), float(vox), float(sensing_radius_m)))
    if c.tree is None and len(o):
        c.tree = cKDTree(o)
    rays_tree = c.tree
    if c.pairs is None:
        c.pairs = ray_pairs(f, o, ray_radius_m, rays_tree)
    zs = np.zeros((len(dirs), len(targets)))
    with_z = ray_z is not None and len(o) and len(targets)
    if with_z:
        zs = np.asarray(ray_z, np.float64)
        if zs.size != len(dirs) * len(targets):
            raise ValueError(f"ray_z has shape {zs.shape}, expected ({len(dirs)}, {len(targets)})")
        zs = zs.reshape(len(dirs), len(targets))
    best, fscore, bz, fz, pos = c.frontier_support(len(f), scores, zs if with_z else None)
    start = None if from_xyz is None else np.asarray(from_xyz, np.float64).reshape(3)
    fdist = np.zeros(len(f)) if start is None else c.distances(f, start)
    k = max(max_candidates, max_goals)
    order, by_z, nearest = _candidates(fscore, fz, fdist, k, pos)
    extra = [by_z] if fz.any() else []
    if start is not None:
        extra.append(nearest)                                     # the nearest: the way on
    if extra:
        order = np.asarray(list(dict.fromkeys(np.concatenate([order, *extra]).tolist())), np.int64)
    goals: list[Goal] = []
    c.fill_views(grid, vox, f, order, standoff_m)
    picked, views = _one_per_voxel(order, c.views, vox)
    if picked:
        pv = np.asarray(views, np.float64).reshape(-1, 3)
        dist = np.zeros(len(picked)) if start is None else np.linalg.norm(pv - start, axis=1)
        near = (rays_tree.query_ball_point(f[picked], r=ray_radius_m, return_sorted=True)
                if rays_tree is not None else [[] for _ in picked])
    zpos = None
    for n, i in enumerate(picked):
        v = views[n]
        t = int(np.argmax(best[i])) if best.shape[1] and fscore[i] > 0 else -1
        by = scores
        if round(float(fscore[i]), 3) == 0 and fz[i] > 0:      # no probability to speak of: the outlier rays
            zpos = np.maximum(zs, 0.0) if zpos is None else zpos
            t, by = int(np.argmax(bz[i])), zpos
        sup = np.asarray(near[n], np.int64)
        if t >= 0 and len(sup):
            sup = sup[np.argsort(-by[sup, t], kind="stable")][:max_rays]
            sd, sw = dirs[sup], by[sup, t]
        else:
            sd, sw = np.zeros((0, 3)), np.zeros((0,))
        goals.append(Goal(v, _heading(v, f[i], sd, sw), float(fscore[i]), 0.0, float(dist[n]),
                          targets[t] if t >= 0 else None, f[i], sd.astype(np.float32), float(fz[i])))
    c.fill_gains(grid, vox, goals, sensing_radius_m)
    return _ranked(goals, max_goals, int(max_goals * explore_share) if start is not None else 0)


def _rank(g: Goal) -> tuple:
    return -round(g.score, 3), -g.ray_z, -g.gain_m3 / (1.0 + g.distance_m)


def _ranked(goals: list[Goal], max_goals: int, n_explore: int) -> list[Goal]:
    """The ``max_goals`` best by :func:`_rank`, of which the last ``n_explore`` places go to
    the best by gain per distance among the rest (module docstring), in rank order."""
    goals = sorted(goals, key=_rank)
    if len(goals) > max_goals and n_explore > 0:
        rest = sorted(goals[max_goals - n_explore:], key=lambda g: -g.gain_m3 / (1.0 + g.distance_m))
        goals = sorted(goals[:max_goals - n_explore] + rest[:n_explore], key=_rank)
    return goals[:max_goals]
