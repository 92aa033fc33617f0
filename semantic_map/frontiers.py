"""Frontiers: fine frontier voxels from the occupancy grid, subsampled into coarse cells.

A coarse cell of size ``beta = vox * s`` (s = ``fronti_subsampling``) is a frontier when it
holds **more than** ``min_fronti`` fine frontier voxels (strict, as the reference). Its
position is the coarse cell centre ``(c + 0.5) * beta`` and its identity is the packed
coarse index (:mod:`semantic_map.cell_keys`), so rays reference frontiers by exact integer keys.

With ``s = 1`` there is no subsampling, as in the reference (which clusters only when
``s > 1``): every fine frontier voxel is a frontier and ``min_fronti`` is not used (a 1-voxel
cell holds at most one fine frontier, so the count test would silently remove them all:
docs/method.md#subsampling-1).

The table is persistent and updated incrementally: after an occupancy update with fine
bounding box ``[lo, hi]`` every fine voxel whose frontier status can have changed lies in
``[lo - r, hi + r]``; that box is widened to whole coarse cells, the fine frontiers in it are
recomputed, and exactly the coarse cells inside it are replaced. Cells outside keep their
(unchanged) counts. This fixes the reference's replacement of coarse centres against the
fine box, which duplicated or lost cells straddling the box edge.

Replacing a region touches only the keys of its x-slab (keys are sorted ``(i, j, k)``, so
the cells with ``i`` in the box are one contiguous run found by binary search) and merges
the new cells into that run: the cost follows the region, not the table. Every key a
replacement removes is logged; :meth:`FrontierTable.take_removed` hands the log to the ray
store, which then prunes only the rays of those frontiers (``None`` after
:meth:`load_state`: the history is unknown and the caller prunes against the whole table).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import torch

from common.conventions import voxel_center
from semantic_map import cell_keys

if TYPE_CHECKING:
    from semantic_map.occupancy import OccupancyGrid


class FrontierTable:
    """Persistent coarse frontier cells: sorted packed ``keys`` (F,) and fine ``counts`` (F,)."""

    def __init__(self, vox: float, subsampling: int, min_fronti: int, device: str | torch.device = "cpu") -> None:
        self.vox = float(vox)
        self.s = int(subsampling)
        # s = 1: no subsampling (reference), every fine frontier is kept (see module docstring)
        self.min_fronti = int(min_fronti) if self.s > 1 else 0
        self.device = torch.device(device)
        self.keys = torch.empty(0, dtype=torch.int64, device=self.device)
        self.counts = torch.empty(0, dtype=torch.int64, device=self.device)
        self._removed: list[torch.Tensor] = []
        self._removed_known = True
        self._centres: tuple | None = None      # (keys tensor, (its version, beta), its centres)

    @property
    def beta(self) -> float:
        return self.vox * self.s

    def __len__(self) -> int:
        return self.keys.numel()

    def centres(self) -> torch.Tensor:
        """(F, 3) float32 coarse cell centres (m), a new tensor; computed once per key tensor
        (the table replaces its keys, it never writes into them; a write in place is seen by
        the tensor's version counter)."""
        k = self.keys
        c = self._centres
        if c is None or c[0] is not k or c[1] != (k._version, self.beta):
            c = self._centres = (k, (k._version, self.beta), voxel_center(cell_keys.unpack(k), self.beta))
        return c[2].clone()

    def region(self, lo: torch.Tensor, hi: torch.Tensor, r: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Fine inclusive box covering whole coarse cells around fine box [lo, hi] grown by r."""
        clo = torch.div(lo - r, self.s, rounding_mode="floor")
        chi = torch.div(hi + r, self.s, rounding_mode="floor")
        return clo * self.s, chi * self.s + self.s - 1

    def update(self, grid: OccupancyGrid, lo: torch.Tensor, hi: torch.Tensor, *, min_unobserved: int, min_free: int,
               min_occupied: int = 0, radius: int = 1) -> None:
        """Recompute frontiers for the fine voxel box ``[lo, hi]`` (int64 (3,), inclusive)."""
        flo, fhi = self.region(lo.to(torch.int64).cpu(), hi.to(torch.int64).cpu(), radius)
        fine = grid.frontiers(min_unobserved, min_free, min_occupied, radius,
                              bbox=(flo.tolist(), fhi.tolist()))
        fine = torch.as_tensor(fine, dtype=torch.int64).to(self.device)
        self.replace_region(torch.div(flo, self.s, rounding_mode="floor"),
                            torch.div(fhi, self.s, rounding_mode="floor"), fine)

    def replace_region(self, clo: torch.Tensor | Sequence[int], chi: torch.Tensor | Sequence[int],
                       fine_ijk: torch.Tensor) -> None:
        """Replace all coarse cells in the coarse box [clo, chi] by the subsampling of
        ``fine_ijk`` (fine frontier voxels, all inside the box)."""
        clo = torch.as_tensor(clo, dtype=torch.int64, device=self.device)
        chi = torch.as_tensor(chi, dtype=torch.int64, device=self.device)
        if fine_ijk.numel():
            coarse = torch.div(fine_ijk, self.s, rounding_mode="floor")
            uk, cnt = torch.unique(cell_keys.pack(coarse), return_counts=True)
            keep = cnt > self.min_fronti
            new_k, new_n = uk[keep], cnt[keep]
        else:
            new_k = torch.empty(0, dtype=torch.int64, device=self.device)
            new_n = torch.empty(0, dtype=torch.int64, device=self.device)
        if self.keys.numel() == 0:
            self.keys, self.counts = new_k, new_n
            return
        # the x-slab [clo_i, chi_i] of the sorted keys: one contiguous run
        lo_i = min(max(int(clo[0]) + cell_keys.OFFSET, 0), cell_keys.MASK)
        hi_i = min(max(int(chi[0]) + cell_keys.OFFSET, 0), cell_keys.MASK)
        shift = 2 * cell_keys.BITS
        bounds = torch.tensor([lo_i << shift, (hi_i << shift) | ((1 << shift) - 1)],
                              dtype=torch.int64, device=self.device)
        a = int(torch.searchsorted(self.keys, bounds[:1]))
        b = int(torch.searchsorted(self.keys, bounds[1:], right=True))
        b = max(a, b)  # empty slab: the new cells go in at a
        slab_k, slab_n = self.keys[a:b], self.counts[a:b]
        c = cell_keys.unpack(slab_k)
        inside = ((c >= clo) & (c <= chi)).all(1)
        old_in = slab_k[inside]
        if old_in.numel():
            gone = old_in[~torch.isin(old_in, new_k)] if new_k.numel() else old_in
            if gone.numel():
                self._removed.append(gone)
        rest_k, rest_n = slab_k[~inside], slab_n[~inside]
        if new_k.numel():
            mk = torch.cat([rest_k, new_k])
            mn = torch.cat([rest_n, new_n])
            o = torch.argsort(mk)
            mk, mn = mk[o], mn[o]
        else:
            mk, mn = rest_k, rest_n
        if not old_in.numel() and not new_k.numel():
            return
        self.keys = torch.cat([self.keys[:a], mk, self.keys[b:]])
        self.counts = torch.cat([self.counts[:a], mn, self.counts[b:]])

    def take_removed(self) -> torch.Tensor | None:
        """Sorted unique keys removed by :meth:`replace_region` since the last call (some may
        be back in the table since), and clear the log; ``None`` when the log is incomplete
        (after :meth:`load_state`)."""
        known, self._removed_known = self._removed_known, True
        parts, self._removed = self._removed, []
        if not known:
            return None
        if not parts:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        return torch.unique(torch.cat(parts))

    def memory_bytes(self) -> int:
        """Bytes held: the keys and their fine-frontier counts."""
        return sum(t.numel() * t.element_size() for t in (self.keys, self.counts))

    def contains(self, keys: torch.Tensor) -> torch.Tensor:
        return cell_keys.lookup(self.keys, keys) >= 0

    def state(self) -> dict:
        return {"keys": self.keys.clone(), "counts": self.counts.clone()}

    def load_state(self, st: dict) -> None:
        self.keys = st["keys"].to(self.device, torch.int64)
        self.counts = st["counts"].to(self.device, torch.int64)
        self._removed, self._removed_known = [], False


def subsample(fine_ijk: torch.Tensor, s: int, min_fronti: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Stand-alone coarse subsampling: (coarse ijk (F, 3) sorted, counts (F,)) of cells with
    more than ``min_fronti`` fine frontiers; ``s = 1``: all fine frontiers (no subsampling)."""
    if s <= 1:
        min_fronti = 0
    coarse = torch.div(fine_ijk.to(torch.int64), s, rounding_mode="floor")
    uk, cnt = torch.unique(cell_keys.pack(coarse), return_counts=True)
    keep = cnt > min_fronti
    return cell_keys.unpack(uk[keep]), cnt[keep]
