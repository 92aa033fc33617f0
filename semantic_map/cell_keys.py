"""Packed int64 keys for integer 3D cell indices (voxels, coarse frontier cells).

``key = (i + 2^20) << 42 | (j + 2^20) << 21 | (k + 2^20)``: 21 bits per axis, so indices
must lie in ``[-2^20, 2^20)`` (±1 048 576 cells: ±52 km at 5 cm voxels). Packing keeps the
lexicographic order of ``(i, j, k)``, so sorted keys are sorted ijk rows.
"""
from __future__ import annotations

import torch

BITS = 21
OFFSET = 1 << (BITS - 1)
MASK = (1 << BITS) - 1
LIMIT = OFFSET


def pack(ijk: torch.Tensor) -> torch.Tensor:
    """(N, 3) int → (N,) int64 keys. Raises ``ValueError`` for indices out of range."""
    ijk = ijk.to(torch.int64)
    if ijk.numel():
        lo, hi = torch.aminmax(ijk)
        check_range(int(lo), int(hi))
    s = ijk + OFFSET
    return (s[:, 0] << (2 * BITS)) | (s[:, 1] << BITS) | s[:, 2]


def check_range(lo: int, hi: int) -> None:
    """Raise ``ValueError`` unless every index in ``[lo, hi]`` is packable (an empty range,
    ``lo > hi``, passes)."""
    if lo <= hi and (lo < -OFFSET or hi >= OFFSET):
        raise ValueError(f"cell index {lo if lo < -OFFSET else hi} outside the packable range "
                         f"[-{OFFSET}, {OFFSET}); coordinates too far from the origin for this voxel size")


def unpack(keys: torch.Tensor) -> torch.Tensor:
    """(N,) int64 keys → (N, 3) int64 indices."""
    keys = keys.to(torch.int64)
    return torch.stack([(keys >> (2 * BITS)) & MASK, (keys >> BITS) & MASK, keys & MASK], dim=1) - OFFSET


def lookup(sorted_keys: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """Position of each ``query`` key in the ascending ``sorted_keys``; -1 where absent."""
    if sorted_keys.numel() == 0 or query.numel() == 0:
        return torch.full(query.shape, -1, dtype=torch.int64, device=query.device)
    pos = torch.searchsorted(sorted_keys, query)
    pc = pos.clamp(max=sorted_keys.numel() - 1)
    found = sorted_keys[pc] == query
    return torch.where(found, pc, torch.full_like(pc, -1))
