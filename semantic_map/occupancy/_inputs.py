"""Input checking and key packing shared by both occupancy backends.

Voxel indices are int64 ``(N, 3)`` tensors. Keys pack ``(i, j, k)`` into one int64 whose
integer order equals lexicographic ``(i, j, k)`` order (21 bits per axis, offset
``2**20``), so indices must lie in ``[-2**20, 2**20)`` (±52 km at 5 cm voxels). Both
backends enforce that range so that they accept exactly the same inputs.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from common.conventions import voxel_index

from .base import BBox, GridInput

BITS = 21
OFFSET = 1 << (BITS - 1)
IJK_MIN = -OFFSET
IJK_MAX = OFFSET - 1
_MASK = (1 << BITS) - 1


def as_tensor(x: GridInput, name: str) -> torch.Tensor:
    """numpy array / torch tensor / nested sequence → CPU torch tensor (no copy if possible)."""
    if isinstance(x, torch.Tensor):
        if x.device.type != "cpu":
            raise ValueError(f"{name}: expected a CPU tensor, got device {x.device}")
        return x
    arr = np.asarray(x)
    if arr.dtype == object:
        raise TypeError(f"{name}: cannot convert {type(x).__name__} to an array")
    return torch.from_numpy(np.ascontiguousarray(arr))


def as_ijk(ijk: GridInput, name: str = "ijk") -> torch.Tensor:
    """Validate voxel indices → contiguous int64 (N, 3) CPU tensor."""
    t = as_tensor(ijk, name)
    if t.ndim == 1 and t.numel() == 0:
        t = t.reshape(0, 3)
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {tuple(t.shape)}")
    if t.dtype.is_floating_point or t.dtype == torch.bool or t.dtype.is_complex:
        raise TypeError(f"{name}: expected an integer dtype (int32/int64), got {t.dtype}")
    t = t.to(torch.int64).contiguous()
    if t.numel() and (int(t.min()) < IJK_MIN or int(t.max()) > IJK_MAX):
        raise ValueError(f"{name}: voxel indices must lie in [{IJK_MIN}, {IJK_MAX}], got "
                         f"[{int(t.min())}, {int(t.max())}]")
    return t


def as_inc(inc: GridInput | int, n: int) -> torch.Tensor:
    """Increment per row (scalar or (N,)) → int64 (N,) tensor."""
    if isinstance(inc, (int, np.integer)) and not isinstance(inc, bool):
        t = torch.full((n,), int(inc), dtype=torch.int64)
    else:
        t = as_tensor(inc, "inc")
        if t.dtype.is_floating_point or t.dtype == torch.bool or t.dtype.is_complex:
            raise TypeError(f"inc: expected an integer dtype, got {t.dtype}")
        if t.ndim == 0:
            t = t.reshape(1).expand(n)
        if t.shape != (n,):
            raise ValueError(f"inc: expected shape ({n},) to match ijk, got {tuple(t.shape)}")
        t = t.to(torch.int64).contiguous()
    if n and (int(t.min()) < -(1 << 30) or int(t.max()) > (1 << 30)):
        raise ValueError("inc: increments must lie in [-2**30, 2**30]")
    return t


def check_bounds(vox: float, lo: int, hi: int) -> tuple[float, int, int]:
    vox = float(vox)
    if not math.isfinite(vox) or vox <= 0:
        raise ValueError(f"voxel size must be a finite value > 0, got {vox}")
    lo, hi = int(lo), int(hi)
    if not -128 <= lo <= hi <= 127:
        raise ValueError(f"clamp bounds must satisfy -128 <= lo <= hi <= 127 (int8), got "
                         f"lo={lo}, hi={hi}")
    return vox, lo, hi


def check_tolerance(tolerance: int) -> int:
    tol = int(tolerance)
    if tol != tolerance or not 0 <= tol <= 127:
        raise ValueError(f"prune tolerance must be an integer in [0, 127], got {tolerance!r}")
    return tol


def check_frontier_args(min_unobserved: int, min_free: int, min_occupied: int, radius: int, bbox: BBox | None
                        ) -> tuple[tuple[int, int, int], int, tuple[tuple[int, ...], tuple[int, ...]] | None]:
    """``((min_unobserved, min_free, min_occupied), radius, bbox)`` as ints, the box clipped to
    the representable range; raises ValueError for a bad radius or box."""
    radius = int(radius)
    if not 1 <= radius <= 8:
        raise ValueError(f"frontier radius must be in [1, 8] voxels, got {radius}")
    mins = (int(min_unobserved), int(min_free), int(min_occupied))
    if bbox is not None:
        try:
            lo_b, hi_b = (x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x
                          for x in bbox)
            lo_b = [int(v) for v in np.asarray(lo_b).reshape(3)]
            hi_b = [int(v) for v in np.asarray(hi_b).reshape(3)]
        except Exception as e:  # noqa: BLE001 - re-raised with a clear message
            raise ValueError(f"bbox must be (ijk_min, ijk_max), two 3-vectors of ints: {e}") from e
        return mins, radius, (tuple(max(v, IJK_MIN) for v in lo_b), tuple(min(v, IJK_MAX) for v in hi_b))
    return mins, radius, None


def pack(ijk: torch.Tensor) -> torch.Tensor:
    """(N, 3) int64 → (N,) int64 keys, ordered like lexicographic (i, j, k)."""
    o = ijk + OFFSET
    return (o[:, 0] << (2 * BITS)) | (o[:, 1] << BITS) | o[:, 2]


def unpack(keys: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`pack`."""
    i = (keys >> (2 * BITS)) & _MASK
    j = (keys >> BITS) & _MASK
    k = keys & _MASK
    return torch.stack([i, j, k], dim=1) - OFFSET


def prepare_rays(origins: GridInput, directions: GridInput, max_dist: float, vox: float
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """Validate rays → (origins f64 (N,3), unit directions f64 (N,3), origin voxels int64,
    max_dist). Directions are normalised; a zero or non-finite direction is an error."""
    o = as_tensor(origins, "origins").to(torch.float64)
    d = as_tensor(directions, "directions").to(torch.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins and directions must both be (N, 3), got {tuple(o.shape)} "
                         f"and {tuple(d.shape)}")
    if not bool(torch.isfinite(o).all()) or not bool(torch.isfinite(d).all()):
        raise ValueError("origins and directions must be finite")
    norm = torch.linalg.vector_norm(d, dim=1, keepdim=True)
    if bool((norm == 0).any()):
        raise ValueError("directions must be non-zero")
    d = (d / norm).contiguous()
    max_dist = float(max_dist)
    if math.isnan(max_dist) or max_dist < 0:
        raise ValueError(f"max_dist must be >= 0, got {max_dist}")
    v = voxel_index(o, vox)
    if v.numel() and (int(v.min()) < IJK_MIN or int(v.max()) > IJK_MAX):
        raise ValueError("ray origins lie outside the representable voxel range")
    return o.contiguous(), d, v.contiguous(), max_dist
