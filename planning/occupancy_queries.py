"""Occupancy read-outs for planners (pure computation): dense state grids, 2D costmap
slices, point checks.

States (int8): :data:`FREE` = 0, :data:`OCCUPIED` = 1, :data:`UNKNOWN` = -1. A map voxel is
occupied when its log-odds value is > 0, free when < 0, unknown when 0 or never observed
(:mod:`semantic_map.occupancy.base`). A coarse cell (``stride`` map voxels per axis) is
occupied if any of its voxels is occupied, free if all of them are observed free, else
unknown (conservative for planning).

Geometry: world frame, metres, z up; map voxel ``ijk`` covers ``[ijk·vox, (ijk+1)·vox)``
(:func:`common.conventions.voxel_index`). A box request ``[lo, hi]`` is snapped outward to
whole coarse cells aligned to the map's voxel lattice: cell ``c`` covers voxels
``[i0 + c·stride, i0 + (c+1)·stride)`` with ``i0 = floor(lo / vox)``, and the grid's
``origin`` (the min corner of cell 0) is ``i0·vox``. Arrays are indexed ``[x, y, z]``.

Sizes are bounded: at most ``max_cells`` (default :data:`MAX_CELLS`) output cells, and at
most ``max_cells · 8`` map voxels read per request; beyond that a ``ValueError`` names the
limit (ask for a coarser ``stride`` or a smaller box).
"""
from __future__ import annotations

import math
import weakref
from typing import TYPE_CHECKING, Sequence

import numpy as np
import numpy.typing as npt
import torch

if TYPE_CHECKING:
    from semantic_map import OccupancyView

FREE, OCCUPIED, UNKNOWN = 0, 1, -1
#: default bound on output cells of one request
MAX_CELLS = 4_000_000
#: map voxels read per request, relative to ``max_cells``
READ_FACTOR = 8
#: map voxels queried per backend call
CHUNK = 1 << 20
#: at most this many points per :func:`point_states` request
MAX_POINTS = 100_000


def _values(grid, ijk: np.ndarray) -> np.ndarray:
    """(N,) int8 log-odds of map voxels ``ijk`` (N, 3), queried in chunks."""
    out = np.empty(len(ijk), np.int8)
    for s in range(0, len(ijk), CHUNK):
        v = grid.query(torch.as_tensor(ijk[s:s + CHUNK]))
        out[s:s + CHUNK] = np.asarray(v.cpu() if isinstance(v, torch.Tensor) else v, np.int8)
    return out


def _state_of(values: np.ndarray) -> np.ndarray:
    return np.where(values > 0, OCCUPIED, np.where(values < 0, FREE, UNKNOWN)).astype(np.int8)


def _reduce(states: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """Coarse state over ``axes``: occupied if any occupied, free if all free, else unknown."""
    occ = (states == OCCUPIED).any(axis=axes)
    free = (states == FREE).all(axis=axes)
    return np.where(occ, OCCUPIED, np.where(free, FREE, UNKNOWN)).astype(np.int8)


def _cell_range(lo: float, hi: float, vox: float, stride: int) -> tuple[int, int]:
    """(first map voxel, number of coarse cells) covering ``[lo, hi]`` along one axis."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
        raise ValueError(f"bad range [{lo}, {hi}]: need finite lo <= hi")
    i0 = math.floor(lo / vox)
    i1 = math.floor(hi / vox)               # last voxel touched (inclusive)
    return i0, (i1 - i0) // stride + 1


def _check_stride(stride: int) -> int:
    s = int(stride)
    if s < 1 or s != stride:
        raise ValueError(f"stride must be a positive integer, got {stride!r}")
    return s


def _check_size(cells: int, read: int, max_cells: int) -> None:
    if cells > max_cells:
        raise ValueError(f"request of {cells} cells exceeds the limit of {max_cells} cells; "
                         "use a coarser stride or a smaller area")
    if read > max_cells * READ_FACTOR:
        raise ValueError(f"request reads {read} map voxels, over the limit of {max_cells * READ_FACTOR}; "
                         "use a smaller area")


def _block_states(grid, i0: tuple[int, int, int], n: tuple[int, int, int]) -> np.ndarray:
    """(nx, ny, nz) states of the map voxels of the box starting at ``i0``, read in x slabs."""
    nx, ny, nz = n
    out = np.empty((nx, ny, nz), np.int8)
    yy, zz = np.meshgrid(np.arange(ny) + i0[1], np.arange(nz) + i0[2], indexing="ij")
    plane = np.stack([np.zeros(ny * nz, np.int64), yy.ravel(), zz.ravel()], 1)
    per = max(1, CHUNK // max(1, ny * nz))
    for s in range(0, nx, per):
        e = min(nx, s + per)
        ijk = np.repeat(plane[None], e - s, 0)
        ijk[:, :, 0] = (np.arange(s, e) + i0[0])[:, None]
        out[s:e] = _state_of(_values(grid, ijk.reshape(-1, 3))).reshape(e - s, ny, nz)
    return out


def state_grid(grid: OccupancyView, vox: float, box_min: npt.ArrayLike, box_max: npt.ArrayLike, stride: int = 1,
               max_cells: int = MAX_CELLS) -> tuple[np.ndarray, np.ndarray, float]:
    """Dense states of the box ``[box_min, box_max]`` (m) at ``stride·vox`` resolution.

    Returns ``(states (nx, ny, nz) int8, origin (3,) float64 min corner of cell 0 in metres,
    cell size in metres)``; see the module docstring for the states and the snapping."""
    s = _check_stride(stride)
    lo, hi = np.asarray(box_min, np.float64).reshape(3), np.asarray(box_max, np.float64).reshape(3)
    rng = [_cell_range(lo[a], hi[a], vox, s) for a in range(3)]
    n = (rng[0][1], rng[1][1], rng[2][1])
    cells = n[0] * n[1] * n[2]
    _check_size(cells, cells * s ** 3, max_cells)
    i0 = (rng[0][0], rng[1][0], rng[2][0])
    fine = _block_states(grid, i0, (n[0] * s, n[1] * s, n[2] * s))
    if s > 1:
        fine = _reduce(fine.reshape(n[0], s, n[1], s, n[2], s), (1, 3, 5))
    return fine, np.asarray(i0, np.float64) * vox, float(vox * s)


def costmap_slice(grid: OccupancyView, vox: float, xy_min: npt.ArrayLike, xy_max: npt.ArrayLike,
                  z_band: Sequence[float] | np.ndarray, stride: int = 1,
                  max_cells: int = MAX_CELLS) -> tuple[np.ndarray, np.ndarray, float]:
    """2D costmap of the z band ``[z0, z1]`` (m) over ``[xy_min, xy_max]`` at ``stride·vox``.

    A column cell is occupied if any map voxel of the band in it is occupied, free if all
    are observed free, else unknown. Returns ``(states (nx, ny) int8, origin (2,) min corner
    of cell 0 in metres, cell size in metres)``."""
    s = _check_stride(stride)
    z0, z1 = float(z_band[0]), float(z_band[1])
    lo, hi = np.asarray(xy_min, np.float64).reshape(2), np.asarray(xy_max, np.float64).reshape(2)
    rx, ry = _cell_range(lo[0], hi[0], vox, s), _cell_range(lo[1], hi[1], vox, s)
    k0, nz = _cell_range(z0, z1, vox, 1)
    cells = rx[1] * ry[1]
    _check_size(cells, cells * s * s * nz, max_cells)
    fine = _block_states(grid, (rx[0], ry[0], k0), (rx[1] * s, ry[1] * s, nz))
    out = _reduce(fine.reshape(rx[1], s, ry[1], s, nz), (1, 3, 4))
    return out, np.array([rx[0], ry[0]], np.float64) * vox, float(vox * s)


class _Occupied:
    """The occupied cells of one grid at ``revision``: sorted packed keys, ijk (M, 3) int64 in
    key order, a ``cKDTree`` of their centres (None when M == 0); ``debt``: map voxels read by
    window reads since it went stale (:func:`point_states`)."""

    def __init__(self) -> None:
        self.revision = -1
        self.keys = np.zeros(0, np.int64)
        self.ijk = np.zeros((0, 3), np.int64)
        self.tree: object = None
        self.debt = 0
        self.based = False                   # keys hold a base the grid's change log follows
        self._active = (-1, 0)               # (revision, grid.num_active at it)

    def active_count(self, grid) -> int:
        """``grid.num_active`` (a walk over the whole tree), asked once per revision."""
        if self._active[0] != grid.revision:
            self._active = (int(grid.revision), int(grid.num_active))
        return self._active[1]


#: per grid (:class:`_Occupied`)
_OCCUPIED: "weakref.WeakKeyDictionary[object, _Occupied]" = weakref.WeakKeyDictionary()
#: a stale index is rebuilt from all occupied voxels once the window reads since it went stale
#: have read this share of the grid's active voxels (so neither path costs more than about
#: twice the cheaper one)
REBUILD_SHARE = 0.25


def _pack(ijk: np.ndarray) -> np.ndarray:
    b = np.int64(1 << 20)
    return ((ijk[:, 0] + b) << 42) | ((ijk[:, 1] + b) << 21) | (ijk[:, 2] + b)


def occupied_cells(grid: OccupancyView, rebuild: bool = True) -> _Occupied | None:
    """The grid's occupied cells at its current ``revision`` (:class:`_Occupied`), kept per
    grid: after writes, only the written voxels are read again (the grid's ``changes`` log);
    after a prune or a reload, or with no log, all occupied voxels are read (``rebuild``;
    None when that is needed and ``rebuild`` is False)."""
    from scipy.spatial import cKDTree

    idx = _OCCUPIED.get(grid)
    if idx is None:
        idx = _OCCUPIED[grid] = _Occupied()
    rev = int(grid.revision)
    if idx.revision == rev:
        return idx
    changed = grid.changes.take() if idx.based else None
    if changed is None:
        if not rebuild:
            idx.based = False
            return None
        grid.changes.take()                                          # the log starts from this base
        ijk = np.asarray(grid.occupied(), np.int64).reshape(-1, 3)
        keys = _pack(ijk)
    else:
        ck = np.unique(_pack(changed))
        now = ck[_values(grid, _unpack(ck)) > 0] if len(ck) else ck
        keys = np.union1d(idx.keys[~np.isin(idx.keys, ck, assume_unique=True)], now)
        ijk = _unpack(keys)
    order = np.argsort(keys, kind="stable")
    idx.keys, idx.ijk = keys[order], ijk[order]
    idx.tree = cKDTree((idx.ijk + 0.5) * float(grid.vox)) if len(keys) else None
    idx.revision, idx.debt, idx.based = rev, 0, True
    return idx


def index_current(grid: OccupancyView) -> bool:
    """True if the grid's occupied-cell index (:func:`occupied_cells`) is at the grid's current
    ``revision``: :func:`point_states` then reads it without a rebuild."""
    idx = _OCCUPIED.get(grid)
    return idx is not None and idx.revision == int(grid.revision)


def _unpack(keys: np.ndarray) -> np.ndarray:
    b, m = 1 << 20, (1 << 21) - 1
    return np.stack([(keys >> 42) - b, ((keys >> 21) & m) - b, (keys & m) - b], 1).astype(np.int64)


def _clearance_brute(grid, vox: float, p: np.ndarray, ijk: np.ndarray, r: int, radius: float) -> np.ndarray:
    """Distance (m) to the nearest occupied cube within ``radius``, else inf: every cell of the
    ``(2r+1)^3`` window around each point's voxel read from the grid."""
    dist = np.full(len(p), np.inf)
    off = np.stack(np.meshgrid(*(np.arange(-r, r + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
    per = max(1, CHUNK // len(off))
    for s in range(0, len(p), per):
        e = min(len(p), s + per)
        cells = (ijk[s:e, None, :] + off[None]).reshape(-1, 3)
        occ = (_values(grid, cells) > 0).reshape(e - s, len(off))
        if not occ.any():
            continue
        lo = cells.reshape(e - s, len(off), 3) * vox
        d = np.maximum(np.maximum(lo - p[s:e, None, :], p[s:e, None, :] - (lo + vox)), 0.0)
        dd = np.where(occ, np.sqrt((d * d).sum(-1)), np.inf).min(1)
        dist[s:e] = np.where(dd <= radius, dd, np.inf)
    return dist


def _clearance_indexed(occ: np.ndarray, tree, vox: float, p: np.ndarray, ijk: np.ndarray, r: int,
                       radius: float) -> np.ndarray:
    """As :func:`_clearance_brute`, from the grid's occupied cells: the cells whose centre lies
    within ``radius`` + half a voxel diagonal of a point (a superset of those whose cube lies
    within ``radius``) and inside the point's window, each cube's distance computed as there."""
    from scipy.spatial import cKDTree

    dist = np.full(len(p), np.inf)
    if tree is None or len(p) == 0:
        return dist
    pairs = cKDTree(p).sparse_distance_matrix(tree, radius + vox * math.sqrt(3.0) / 2 + 1e-9 * (1 + radius),
                                              output_type="ndarray")
    if not len(pairs):
        return dist
    pi, ci = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    cells = occ[ci]
    win = (np.abs(cells - ijk[pi]) <= r).all(1)
    pi, cells = pi[win], cells[win]
    lo = cells * vox
    d = np.maximum(np.maximum(lo - p[pi], p[pi] - (lo + vox)), 0.0)
    dd = np.sqrt((d * d).sum(-1))
    np.minimum.at(dist, pi, dd)
    return np.where(dist <= radius, dist, np.inf)


def point_states(grid: OccupancyView, vox: float, points: npt.ArrayLike, radius: float,
                 max_cells: int = MAX_CELLS) -> tuple[np.ndarray, np.ndarray]:
    """State of the map voxel holding each point (N, 3) (m) and the distance (m) from the
    point to the nearest occupied voxel (its cube, so 0 inside one) within ``radius``;
    ``inf`` when there is none within ``radius``. Returns ``(states (N,) int8, dist (N,)
    float64)``.

    The distances come from the grid's occupied cells (:func:`occupied_cells`, kept per grid
    and brought up to date from the voxels written since) or, while that index would need a
    full rebuild not yet worth its cost (:data:`REBUILD_SHARE`), from reading each point's
    window: the same cells, the same float operations, the same answer."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) > MAX_POINTS:
        raise ValueError(f"{len(p)} points exceed the limit of {MAX_POINTS} points")
    if not np.isfinite(p).all():
        raise ValueError("points must be finite")
    if not (radius >= 0 and math.isfinite(radius)):
        raise ValueError(f"radius must be finite and >= 0, got {radius}")
    r = int(math.ceil(radius / vox))
    w = 2 * r + 1
    _check_size(len(p) * w ** 3, len(p) * w ** 3, max_cells)
    ijk = np.floor(p / vox).astype(np.int64)
    states = _state_of(_values(grid, ijk))
    if len(p) == 0:
        return states, np.full(0, np.inf)
    if float(grid.vox) == float(vox) and hasattr(grid, "changes"):
        idx = _OCCUPIED.setdefault(grid, _Occupied())
        cells = len(p) * w ** 3
        # (num_active walks the whole tree: only asked when a rebuild is the question)
        rebuild = idx.revision == grid.revision or (idx.based and grid.changes.complete) or \
            idx.debt + cells >= REBUILD_SHARE * idx.active_count(grid)
        got = occupied_cells(grid, rebuild)
        if got is not None:
            return states, _clearance_indexed(got.ijk, got.tree, vox, p, ijk, r, radius)
        _OCCUPIED[grid].debt += cells
    return states, _clearance_brute(grid, vox, p, ijk, r, radius)
