"""Exact voxel traversal of many line segments at once (vectorised, torch).

A segment from ``o`` to ``e`` passes through its start cell and then, each time it crosses
a cell boundary plane ``x_a = b * cell``, enters a new cell. Instead of stepping all rays
together (Amanatides–Woo with a per-step loop), every boundary crossing of every segment
is generated directly: along axis ``a`` a segment crosses ``|floor(e_a/cell) -
floor(o_a/cell)|`` planes, the crossing parameter is ``t = (plane - o_a) / (e_a - o_a)``,
the entered cell's ``a`` index is known exactly and the other two indices are
``floor((o + t (e - o)) / cell)``. The union of the start cell and all entered cells is
exactly the set of cells the segment touches (up to measure-zero grazing of edges and
corners). Work and memory are proportional to the number of (segment, cell) pairs.

Coordinates are taken relative to an integer base cell so float32 stays accurate.
Cell index convention: ``floor(xyz / cell)`` (:func:`common.conventions.voxel_index`).
:func:`unique_cells` runs the same enumeration (same chunks, bases and float32 operations)
in the optional C++ kernel (:mod:`semantic_map.kernels`) when available: identical output.
"""
from __future__ import annotations

import torch

from common.conventions import voxel_index
from semantic_map import cell_keys, kernels

DEFAULT_CHUNK = 1 << 22  # (segment, cell) pairs per chunk


def crossing_counts(origins: torch.Tensor, ends: torch.Tensor, cell: float) -> torch.Tensor:
    """(N,) number of cells each segment touches (start cell + plane crossings)."""
    return 1 + (voxel_index(ends, cell) - voxel_index(origins, cell)).abs().sum(1)


def _chunk_cells(o: torch.Tensor, e: torch.Tensor, cell: float, base: torch.Tensor,
                 include_start: bool, exclude_end: torch.Tensor | None):
    """Cells of segments ``o``→``e`` (float64 world); returns (ray_idx (M,), ijk (M, 3))."""
    dev = o.device
    n = o.shape[0]
    basef = base.to(torch.float64) * cell
    orel = (o - basef).to(torch.float32)
    erel = (e - basef).to(torch.float32)
    s = voxel_index(o, cell) - base  # exact start cells, relative
    f = voxel_index(e, cell) - base
    diff = erel - orel
    ids_all, ijk_all = [], []
    ar = torch.arange(n, device=dev)
    if include_start:
        ids_all.append(ar)
        ijk_all.append(s)
    oc = [orel[:, a].contiguous() for a in range(3)]
    dc = [diff[:, a].contiguous() for a in range(3)]
    sc = [s[:, a].contiguous() for a in range(3)]
    for a in range(3):
        step = f[:, a] - s[:, a]
        cnt = step.abs()
        tot = int(cnt.sum())
        if tot == 0:
            continue
        rid = torch.repeat_interleave(ar, cnt)
        start = torch.cumsum(cnt, 0) - cnt
        sg = torch.sign(step)
        m = torch.arange(tot, device=dev) - torch.repeat_interleave(start, cnt) + 1  # 1..cnt
        sgr = torch.repeat_interleave(sg, cnt)
        entered = torch.repeat_interleave(sc[a], cnt) + m * sgr
        plane = entered + (sgr < 0).to(torch.int64)  # boundary coordinate in cells
        t = (plane.to(torch.float32) * cell - torch.repeat_interleave(oc[a], cnt)) / torch.repeat_interleave(dc[a], cnt)
        ijk = torch.empty((tot, 3), dtype=torch.int64, device=dev)
        ijk[:, a] = entered
        for b in range(3):
            if b != a:
                pos = torch.repeat_interleave(oc[b], cnt) + t * torch.repeat_interleave(dc[b], cnt)
                ijk[:, b] = torch.floor(pos / cell).to(torch.int64)
        ids_all.append(rid)
        ijk_all.append(ijk)
    if not ids_all:
        return (torch.empty(0, dtype=torch.int64, device=dev), torch.empty((0, 3), dtype=torch.int64, device=dev))
    rid = torch.cat(ids_all)
    ijk = torch.cat(ijk_all)
    if exclude_end is not None and bool(exclude_end.any()):
        drop = exclude_end[rid] & (ijk == f[rid]).all(1)
        rid, ijk = rid[~drop], ijk[~drop]
    return rid, ijk + base


def segment_cells(origins: torch.Tensor, ends: torch.Tensor, cell: float, *,
                  include_start: bool = True, exclude_end: torch.Tensor | None = None,
                  chunk: int = DEFAULT_CHUNK) -> tuple[torch.Tensor, torch.Tensor]:
    """All (segment, cell) pairs for segments ``origins[i]``→``ends[i]`` (float64 (N, 3)).

    ``exclude_end`` (N,) bool drops each flagged segment's end cell. Returns
    ``(seg_idx (M,), ijk (M, 3) int64)``; a cell appears once per segment."""
    out_r, out_c = [], []
    for lo, hi, base in _chunks(origins, ends, cell, chunk):
        r, c = _chunk_cells(origins[lo:hi], ends[lo:hi], cell, base, include_start,
                            None if exclude_end is None else exclude_end[lo:hi])
        out_r.append(r + lo)
        out_c.append(c)
    if not out_r:
        dev = origins.device
        return torch.empty(0, dtype=torch.int64, device=dev), torch.empty((0, 3), dtype=torch.int64, device=dev)
    return torch.cat(out_r), torch.cat(out_c)


def _chunks(origins, ends, cell, chunk):
    n = origins.shape[0]
    if n == 0:
        return
    cnt = crossing_counts(origins, ends, cell)
    csum = torch.cumsum(cnt, 0)
    lo = 0
    while lo < n:
        limit = (csum[lo - 1] if lo > 0 else 0) + chunk
        hi = int(torch.searchsorted(csum, torch.as_tensor(limit, device=csum.device), right=True))
        hi = max(hi, lo + 1)
        base = voxel_index(origins[lo:hi].mean(0), cell)
        yield lo, hi, base
        lo = hi


def unique_cells(origins: torch.Tensor, ends: torch.Tensor, cell: float, *,
                 exclude_end: torch.Tensor | None = None, chunk: int = DEFAULT_CHUNK,
                 max_dense: int = 1 << 25) -> torch.Tensor:
    """Sorted unique (K, 3) int64 cells touched by any of the segments (start cell included).

    De-duplicates with a dense byte mask over the segments' bounding box when it holds at
    most ``max_dense`` cells (O(pairs)), else with ``torch.unique``."""
    dev = origins.device
    if origins.shape[0] == 0:
        return torch.empty((0, 3), dtype=torch.int64, device=dev)
    if kernels.enabled(origins, ends):  # same enumeration and arithmetic in C++, hashed
        return cell_keys.unpack(kernels.segment_cells_unique(origins, ends, cell,
                                                             list(_chunks(origins, ends, cell, chunk)), exclude_end))
    a = voxel_index(origins, cell)
    b = voxel_index(ends, cell)
    lo = torch.minimum(a.min(0).values, b.min(0).values)
    hi = torch.maximum(a.max(0).values, b.max(0).values)
    ext = hi - lo + 1
    vol = int(ext.prod())
    if vol <= max_dense:
        mask = torch.zeros(vol, dtype=torch.bool, device=dev)
        for s, e, base in _chunks(origins, ends, cell, chunk):
            _, c = _chunk_cells(origins[s:e], ends[s:e], cell, base, True,
                                None if exclude_end is None else exclude_end[s:e])
            c = c - lo
            mask[(c[:, 0] * ext[1] + c[:, 1]) * ext[2] + c[:, 2]] = True
        flat = torch.nonzero(mask).squeeze(1)
        k = flat % ext[2]
        j = (flat // ext[2]) % ext[1]
        i = flat // (ext[1] * ext[2])
        return torch.stack([i, j, k], 1) + lo
    _, c = segment_cells(origins, ends, cell, exclude_end=exclude_end, chunk=chunk)
    return cell_keys.unpack(torch.unique(cell_keys.pack(c)))
