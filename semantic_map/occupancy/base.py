"""The occupancy-grid interface both backends implement (OpenVDB extension and torch).

Values are int8 log-odds per voxel: ``> 0`` occupied, ``< 0`` free, ``0`` or inactive =
unobserved. Voxel indices are int ``(N, 3)`` arrays from :func:`common.conventions.voxel_index`
(``floor(xyz / vox)``), within ``[-2**20, 2**20)`` per axis (±52 km at 5 cm; outside it a
``ValueError``). Inputs may be numpy arrays or CPU torch tensors (int32/int64 indices);
outputs are torch tensors on the CPU (the mapper moves them to its device): ijk int64,
values int8, distances float64. Bad input raises ``ValueError``/``TypeError`` before the
map is touched.

Both backends must give identical maps, query results and frontier sets for the same
sequence of calls; the tests use the torch backend as the oracle for the extension.
"""
from __future__ import annotations

from typing import Protocol, Union

import numpy as np
import numpy.typing as npt
import torch

#: what the grid methods accept: a CPU torch tensor, a numpy array or a nested sequence
GridInput = Union[torch.Tensor, npt.ArrayLike]
#: a frontier box ``(ijk_min, ijk_max)``, inclusive, each a 3-vector of ints
BBox = tuple[GridInput, GridInput]


class ChangeLog:
    """The voxels written since its last :meth:`take`, for one reader's cache of the grid's
    values (:func:`planning.occupancy_queries.occupied_cells`). Bounded: past ``cap``
    voxels, and after a call that may change values anywhere (prune, load_state), it only
    says "anything may have changed" (:meth:`take` returns None) until taken again."""

    def __init__(self, cap: int = 1 << 20) -> None:
        self.cap = int(cap)
        self._parts: list[np.ndarray] = []
        self._n = 0
        self._all = True                     # no reader has a base yet

    def add(self, ijk: torch.Tensor) -> None:
        """Record the (N, 3) voxels of a write."""
        if self._all:
            return
        self._n += int(ijk.shape[0])
        if self._n > self.cap:
            self.everything()
        else:
            self._parts.append(ijk.detach().cpu().numpy().astype(np.int64, copy=True))

    @property
    def complete(self) -> bool:
        """Whether :meth:`take` would list the written voxels (not "anything may have changed")."""
        return not self._all

    def everything(self) -> None:
        """Any voxel may have changed."""
        self._all, self._parts, self._n = True, [], 0

    def take(self) -> np.ndarray | None:
        """(M, 3) int64 voxels written since the last take (repeats possible), or None when
        anything may have changed; starts a new log."""
        out = None if self._all else (np.concatenate(self._parts) if self._parts else np.zeros((0, 3), np.int64))
        self._all, self._parts, self._n = False, [], 0
        return out


class OccupancyGrid(Protocol):
    vox: float
    lo: int  # clamp lower bound (e.g. -5); the paper's -max_empty_cnt
    hi: int  # clamp upper bound (e.g. 30); the paper's max_occ_cnt (<= 127)
    #: grows with every call that may change values (update, prune, load_state): a reader's
    #: cache of values is valid while it is unchanged
    revision: int
    #: the voxels written since a reader last looked (:class:`ChangeLog`)
    changes: ChangeLog

    def update(self, ijk: GridInput, inc: GridInput | int) -> None:
        """``value = clamp(value + inc, lo, hi)`` per row, activating the voxel.

        ``ijk`` (N, 3) int; ``inc`` (N,) int or a scalar int. Rows are applied in order,
        clamping after each (duplicates allowed and applied sequentially)."""

    def query(self, ijk: GridInput) -> torch.Tensor:
        """(N,) int8 values; 0 where unobserved/inactive. Sees pruned tiles."""

    def frontiers(self, min_unobserved: int, min_free: int, min_occupied: int = 0,
                  radius: int = 1, bbox: BBox | None = None) -> torch.Tensor:
        """(K, 3) int64 indices of free voxels (value < 0) whose (2r+1)^3 neighbourhood,
        **self included**, holds >= min_unobserved unobserved, >= min_free free and
        >= min_occupied occupied cells. ``bbox = (ijk_min, ijk_max)`` inclusive limits the
        candidate voxels (neighbours outside it are still read). Voxels inside pruned
        tiles are candidates too. Rows sorted lexicographically (i, j, k). ``radius`` in
        [1, 8]."""

    def prune(self, tolerance: int) -> None:
        """Collapse uniform regions into tiles (OpenVDB ``tools::prune`` semantics on a
        ``Tree4<int8, 5, 4, 3>``): bottom-up, an 8³ leaf, then a node of 16³ leaves, then
        a node of 32³ such nodes collapses when all its children are (collapsed) and fully
        active and ``max - min <= tolerance``; the tile value is the lower median
        (sorted element ``(n - 1) >> 1``) of the children's values, so voxel values in a
        collapsed region change. A later write into a tile re-densifies it. The torch
        backend keeps voxels but holds the same values. ``tolerance`` in [0, 127]."""

    def active(self) -> tuple[torch.Tensor, torch.Tensor]:
        """All active voxels expanded from tiles: ((M, 3) int64 ijk sorted, (M,) int8)."""

    def occupied(self) -> np.ndarray:
        """(M, 3) int64 indices of the voxels with value > 0, in no particular order (tiles
        expanded); cheaper than :meth:`active` on maps of mostly free space."""

    def first_blocked(self, origins: GridInput, directions: GridInput, max_dist: float) -> torch.Tensor:
        """For each ray (world origins (N, 3), unit directions (N, 3), metres), the distance
        along the ray at which it first enters a voxel with value >= 0 (unobserved or
        occupied), by exact voxel traversal (Amanatides–Woo) starting in the origin's
        voxel (``voxel_index(origin)``; 0 if that voxel is blocked); ``inf`` if it stays
        in free space up to ``max_dist``. Directions are normalised (zero components are
        fine, an all-zero direction is an error); float64 (N,); on exact ties the lower
        axis (x, then y, then z) is stepped first."""

    @property
    def num_active(self) -> int:
        """Active voxel count (tiles counted by their voxel volume)."""

    def memory_bytes(self) -> int:
        """Bytes held by the map structure (OpenVDB ``memUsage``; torch: keys + values)."""

    def state(self) -> dict:
        """Backend-neutral exact state for snapshots: {"vox", "lo", "hi", "ijk", "values"}
        (numpy arrays, ijk int64 (M, 3) sorted, values int8 (M,); tiles expanded)."""

    def load_state(self, state: dict) -> None:
        """Replace the map's voxels by ``state`` (as produced by :meth:`state`); use
        :func:`semantic_map.occupancy.from_state` to build a grid from a snapshot."""


def _grid_field(name: str, doc: str) -> property:
    """A read-only property: the viewed grid's attribute ``name``."""
    return property(lambda self: getattr(self._grid, name), doc=doc)


class OccupancyView:
    """Read-only access to one occupancy grid (what planners and exports read): the read
    methods and fields of :class:`OccupancyGrid` (same units and conventions: int8 log-odds,
    ``> 0`` occupied, ``< 0`` free, ``0`` unobserved; voxel ``ijk = floor(xyz / vox)``), none of
    its writes. :meth:`semantic_map.map.RayFrontsMap.occupancy_view` hands out one view per
    grid, so a reader may cache by the view object and its :attr:`revision`.
    :attr:`changes` is the grid's change log for that one reader's cache (taking from it
    changes no voxel)."""

    __slots__ = ("_grid", "__weakref__")

    def __init__(self, grid: OccupancyGrid) -> None:
        self._grid = grid

    vox = _grid_field("vox", "Voxel size (m).")
    lo = _grid_field("lo", "Clamp lower bound of the values.")
    hi = _grid_field("hi", "Clamp upper bound of the values.")
    revision = _grid_field("revision", "Grows with every change of values (:attr:`OccupancyGrid.revision`).")
    changes = _grid_field("changes", "The voxels written since this view's reader last took them (:class:`ChangeLog`).")
    num_active = _grid_field("num_active", "Active voxel count (tiles counted by their voxel volume; a walk "
                                           "over the grid).")

    def query(self, ijk: GridInput) -> torch.Tensor:
        """(N,) int8 values of voxels ``ijk`` (N, 3); 0 where unobserved."""
        return self._grid.query(ijk)

    def frontiers(self, min_unobserved: int, min_free: int, min_occupied: int = 0,
                  radius: int = 1, bbox: BBox | None = None) -> torch.Tensor:
        """(K, 3) int64 fine frontier voxels (:meth:`OccupancyGrid.frontiers`)."""
        return self._grid.frontiers(min_unobserved, min_free, min_occupied, radius, bbox)

    def active(self) -> tuple[torch.Tensor, torch.Tensor]:
        """All active voxels: ((M, 3) int64 ijk sorted, (M,) int8 values)."""
        return self._grid.active()

    def occupied(self) -> np.ndarray:
        """(M, 3) int64 voxels with value > 0, in no particular order."""
        return self._grid.occupied()

    def first_blocked(self, origins: GridInput, directions: GridInput, max_dist: float) -> torch.Tensor:
        """(N,) float64 distance (m) along each ray to its first non-free voxel, ``inf`` past
        ``max_dist`` (:meth:`OccupancyGrid.first_blocked`)."""
        return self._grid.first_blocked(origins, directions, max_dist)

    def memory_bytes(self) -> int:
        """Bytes held by the grid."""
        return self._grid.memory_bytes()

    def state(self) -> dict:
        """A copy of the grid's exact state: {"vox", "lo", "hi", "ijk" (M, 3) int64 sorted,
        "values" (M,) int8} (tiles expanded)."""
        return self._grid.state()
