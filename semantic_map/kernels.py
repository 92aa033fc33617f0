"""Optional C++ kernels (``semantic_map._rfkernels``) with their pure-torch twins.

The extension is built by the project's CMake wherever a C++17 compiler exists (it needs
no OpenVDB). When it is missing, or disabled (``RAYFRONTS_KERNELS=0`` in the environment,
:func:`set_enabled` / :func:`disabled`), every caller uses its torch path; both paths give
identical results (the tests run both), except :func:`half_scores`, which rounds less than
its torch twin (float32 instead of float16: within the query copy's ``SCORE_ATOL``), and
:func:`cone_weighted_union`, which sums in another order (equal up to float64 rounding). Kernels
run on CPU tensors only; tensors on other devices always take the torch path.
"""
from __future__ import annotations

import math
import os
from contextlib import contextmanager
from typing import Callable, Iterator

import numpy as np
import torch

from semantic_map import cell_keys

try:  # optional extension
    from semantic_map import _rfkernels  # type: ignore[attr-defined]
    IMPORT_ERROR: Exception | None = None
except ImportError as e:  # pragma: no cover - depends on the build
    _rfkernels = None
    IMPORT_ERROR = e

#: per-ray argmin of candidate costs: (rays, frontier idx, (x1, x2) cost terms, n_rays) -> (rays, fidx, cost)
ArgminCost = Callable[[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor], int],
                      tuple[torch.Tensor, torch.Tensor, torch.Tensor]]

#: coarse cells per block side of the association kernels' ray walk (2: 15-18 % less CPU than 4
#: on ray blocks of the throughput growth run: fewer listed frontiers tested per passing pair)
ASSOCIATION_BLOCK = 2

_enabled = os.environ.get("RAYFRONTS_KERNELS", "1") not in ("0", "false", "off", "no")


#: the float16 query product runs here (an x86-64 CPU with AVX2, FMA and F16C, and a module
#: built with it)
_HALF_SCORES = bool(_rfkernels is not None and hasattr(_rfkernels, "half_scores_available")
                    and _rfkernels.half_scores_available())


def available() -> bool:
    """True if the C++ kernel module imported."""
    return _rfkernels is not None


def enabled(*tensors: torch.Tensor) -> bool:
    """True if the kernels are available, enabled, and all ``tensors`` are on the CPU."""
    return _rfkernels is not None and _enabled and all(t.device.type == "cpu" for t in tensors)


def set_enabled(flag: bool) -> bool:
    """Enable / disable the kernels process-wide; returns the previous setting."""
    global _enabled
    old, _enabled = _enabled, bool(flag)
    return old


@contextmanager
def disabled() -> Iterator[None]:
    """``with disabled(): ...`` runs the torch paths (for comparisons and tests)."""
    old = set_enabled(False)
    try:
        yield
    finally:
        set_enabled(old)


def _np(t: torch.Tensor, dtype: torch.dtype):
    return t.detach().to(dtype).contiguous().numpy()


def components_26_sorted(keys: np.ndarray) -> np.ndarray | None:
    """Kernel-only: (N,) int64 26-connected component of each voxel of strictly ascending
    packed keys ``keys`` (N,) (:mod:`semantic_map.cell_keys` layout), numbered ``0..C-1`` by
    each component's lowest key, on torch's thread count; None when the kernels are missing
    or disabled (the caller takes its own path: ``planning.instances.connected_26``)."""
    if not enabled() or not hasattr(_rfkernels, "components_26_sorted"):
        return None
    return _rfkernels.components_26_sorted(np.ascontiguousarray(keys, np.int64), max(1, torch.get_num_threads()))


def cone_weighted_union() -> Callable[..., float] | None:
    """Kernel-only: the C++ twin of ``common.cones._weighted_union`` (the per-cone step of the
    sampled cone-union volume, for ``cone_union_volume(..., weighted_union=...)``) on torch's
    thread count; None when the kernels are missing or disabled."""
    if not enabled() or not hasattr(_rfkernels, "cone_weighted_union"):
        return None
    threads = max(1, torch.get_num_threads())

    def run(local: np.ndarray, w: np.ndarray, frames: np.ndarray, o: np.ndarray, d: np.ndarray, range_m: float,
            cos2: float) -> float:
        f64 = [np.ascontiguousarray(a, np.float64) for a in (local, w, frames, o, d)]
        return float(_rfkernels.cone_weighted_union(*f64, float(range_m), float(cos2), threads))

    return run


def argsort_voxel_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Kernel-only: ``(order, keys[order])`` with ``order = np.argsort(keys, kind="stable")``
    for packed voxel keys ``keys`` (N,) (:mod:`semantic_map.cell_keys` layout), by a radix
    sort on torch's thread count; None when the kernels are missing or disabled, or when the
    keys need more than 32 bits re-packed from their smallest index per axis (spans of
    2^11, 2^11 and 2^10 voxels, say; the caller sorts then)."""
    if not enabled() or not hasattr(_rfkernels, "argsort_voxel_keys"):
        return None
    return _rfkernels.argsort_voxel_keys(np.ascontiguousarray(keys, np.int64), max(1, torch.get_num_threads()))


def instance_groups(keys: np.ndarray, labels: np.ndarray, conf: np.ndarray, min_voxels: int) -> tuple | None:
    """Kernel-only: the group step of ``planning.instances.InstanceTracker.update`` for voxels
    of strictly ascending packed ``keys`` with component ``labels`` and confidences ``conf``
    (all in key order): ``(kept, labels, grouped keys, counts, index sums, minima, maxima, max
    conf)`` of the groups of at least ``min_voxels`` (``planning.instances._groups``); None
    when the kernels are missing or disabled."""
    if not enabled() or not hasattr(_rfkernels, "instance_groups"):
        return None
    return _rfkernels.instance_groups(np.ascontiguousarray(keys, np.int64), np.ascontiguousarray(labels, np.int64),
                                      np.ascontiguousarray(conf, np.float64), int(min_voxels))


def unique_keys(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``torch.unique(keys, sorted=True, return_inverse=True, return_counts=True)`` for a
    1-D int64 tensor: (sorted unique, inverse (N,) int64, counts int64)."""
    if enabled(keys) and keys.ndim == 1:
        u, inv, cnt = _rfkernels.unique_i64(_np(keys, torch.int64))
        return torch.from_numpy(u), torch.from_numpy(inv), torch.from_numpy(cnt)
    return torch.unique(keys, sorted=True, return_inverse=True, return_counts=True)


def sample_pairs(group: torch.Tensor, pix: torch.Tensor, hw: tuple[int, int], h: int, w: int, mode: str,
                 n_groups: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Kernel-only :func:`group_pairs` of the sampling corners of flat pixels ``pix`` of an
    ``hw`` image on an (h, w) map (``semantic_map.depth_geometry._corners`` computed in C++)."""
    g, s, wt = _rfkernels.sample_pairs(_np(group, torch.int64), _np(pix, torch.int64), int(hw[0]), int(hw[1]),
                                       int(h), int(w), mode == "nearest", int(n_groups))
    return torch.from_numpy(g), torch.from_numpy(s), torch.from_numpy(wt)


def segment_cells_unique(origins: torch.Tensor, ends: torch.Tensor, cell: float, chunks: list,
                         exclude_end: torch.Tensor | None, include_start: bool = True) -> torch.Tensor:
    """Kernel-only: sorted unique packed keys of the cells of ``semantic_map.traversal``'s chunked
    crossing enumeration; ``chunks`` = [(lo, hi, base (3,) int64), ...] from its ``_chunks``."""
    lo = torch.tensor([c[0] for c in chunks], dtype=torch.int64)
    hi = torch.tensor([c[1] for c in chunks], dtype=torch.int64)
    base = (torch.stack([c[2].reshape(3).to(torch.int64) for c in chunks]) if chunks
            else torch.empty((0, 3), dtype=torch.int64))
    ex = torch.empty(0, dtype=torch.bool) if exclude_end is None else exclude_end.to(torch.bool)
    keys, klo, khi = _rfkernels.segment_cells_unique(_np(origins, torch.float64), _np(ends, torch.float64), float(cell),
                                                      lo.numpy(), hi.numpy(), base.contiguous().numpy(),
                                                      ex.contiguous().numpy(), bool(include_start))
    cell_keys.check_range(klo, khi)
    return torch.from_numpy(keys)


def group_pairs(group: torch.Tensor, idx: torch.Tensor, wt: torch.Tensor, n_groups: int, n_src: int,
                max_dense: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Non-zeros of the sparse (n_groups × n_src) matrix ``A[group[p], idx[p, c]] += wt[p, c]``
    (``idx``, ``wt`` (P, k); float32 weights): ``(g, src, weight float32)`` in ascending
    ``(g, src)`` order. Each sum is accumulated in float32 in input order, as the dense
    torch path (``torch.bincount``) does; without the kernel a matrix larger than
    ``max_dense`` goes through ``torch.unique`` + ``index_add_`` instead."""
    wt = wt.to(torch.float32)
    if enabled(group, idx, wt):
        g, s, w = _rfkernels.group_pairs(_np(group, torch.int64), _np(idx, torch.int64), wt.contiguous().numpy(),
                                         int(n_groups), int(n_src))
        return torch.from_numpy(g), torch.from_numpy(s), torch.from_numpy(w)
    flat = (group[:, None] * n_src + idx).reshape(-1)
    if n_groups * n_src <= max_dense:
        A = torch.bincount(flat, weights=wt.reshape(-1), minlength=n_groups * n_src)
        nz = torch.nonzero(A).squeeze(1)
        w = A[nz]
    else:
        nz, inv = torch.unique(flat, return_inverse=True)
        w = torch.zeros(nz.numel(), dtype=torch.float32, device=group.device).index_add_(0, inv, wt.reshape(-1))
    g = torch.div(nz, n_src, rounding_mode="floor")
    return g, nz - g * n_src, w


def associate_rays(o: torch.Tensor, d: torch.Tensor, lengths: torch.Tensor, frontier_ijk: torch.Tensor,
                   beta: float, base: torch.Tensor, max_dist: float, reject_close: bool,
                   block: int = ASSOCIATION_BLOCK, scales: tuple[float, float | None] | None = None,
                   argmin: ArgminCost | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Kernel-only ray -> frontier association: (rays, frontier idx, float64 cost), equal to
    :func:`semantic_map.ray_frontiers.associate`'s torch path (see the C++ source). With fixed
    cost ``scales`` (the ``absolute`` cost) the kernel gives the candidate pairs and
    ``argmin(rays, fidx, (x1, x2), n_rays)`` (the torch code) picks per ray."""
    ri, fi, oo, vv = _rfkernels.associate_rays(_np(o, torch.float64), _np(d, torch.float64),
                                               _np(lengths, torch.float64), _np(frontier_ijk, torch.int64),
                                               float(beta), int(block), _np(base, torch.float64),
                                               float(max_dist), bool(reject_close))
    return _pick(ri, fi, oo, vv, int(o.shape[0]), scales, argmin)


def _pick(ri, fi, oo, vv, n_rays: int, scales: tuple[float, float | None] | None,
          argmin: ArgminCost | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-ray choice among a kernel's candidate pairs (numpy ``ri``, ``fi``, float32 ``oo`` =
    d_ortho², ``vv`` = d_orig²): the kernel's argmin, or with fixed cost ``scales`` the
    caller's torch ``argmin``."""
    # square roots in torch: bit-identical to the torch path's float32 sqrt
    x1 = torch.from_numpy(oo).sqrt().to(torch.float64)
    x2 = torch.from_numpy(vv).sqrt().to(torch.float64)
    if scales is not None:
        assert argmin is not None  # the absolute cost picks per ray with the caller's torch code
        return argmin(torch.from_numpy(ri), torch.from_numpy(fi), (x1, x2), n_rays)
    r, f, c = _rfkernels.argmin_cost(ri, fi, x1.numpy(), x2.numpy())
    return torch.from_numpy(r), torch.from_numpy(f), torch.from_numpy(c)


#: direction bin of the fan association (radians): its measured best on the growth run's ray blocks
FAN_BIN_RAD = math.radians(1.0)
#: the fan association serves rays whose origins all lie within beta of their mean (one fan,
#: its cones widened by that spread), else at most this many distinct origins (a fan each:
#: each reads every frontier passed); more (rays re-queued from all over the map) walk
FAN_MAX_ORIGINS = 16


def associate_rays_fan(o: torch.Tensor, d: torch.Tensor, frontier_ijk: torch.Tensor, beta: float,
                       base: torch.Tensor, max_dist: float, reject_close: bool,
                       scales: tuple[float, float | None] | None = None, argmin: ArgminCost | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """:func:`associate_rays` (every ray of length ``max_dist`` > 0) for rays leaving from
    within ``beta`` of their mean origin or from at most :data:`FAN_MAX_ORIGINS` points, with
    unit directions (to 1e-6): the rays binned by direction, each frontier tests the rays of
    its cone of candidate directions (see the C++ source). None when the rays do not qualify
    (then walk: :func:`associate_rays`)."""
    if o.shape[0] == 0 or not bool(((d.to(torch.float64).norm(dim=1) - 1.0).abs() <= 1e-6).all()):
        return None
    got = _rfkernels.associate_rays_fan(_np(o, torch.float64), _np(d, torch.float64), _np(frontier_ijk, torch.int64),
                                        float(beta), _np(base, torch.float64), float(max_dist), bool(reject_close),
                                        FAN_BIN_RAD, float(beta), FAN_MAX_ORIGINS)
    if got is None:
        return None
    ri, fi, oo, vv = got
    return _pick(ri, fi, oo, vv, int(o.shape[0]), scales, argmin)


def voxel_keys(xyz: torch.Tensor, vox: float) -> torch.Tensor:
    """``keys.pack(voxel_index(xyz.to(float64), vox))`` for (N, 3) float32/float64 points."""
    if enabled(xyz) and xyz.dtype in (torch.float32, torch.float64) and xyz.ndim == 2 and xyz.shape[1] == 3:
        fn = _rfkernels.voxel_keys_f32 if xyz.dtype == torch.float32 else _rfkernels.voxel_keys_f64
        k, lo, hi = fn(xyz.detach().contiguous().numpy(), float(vox))
        cell_keys.check_range(lo, hi)
        return torch.from_numpy(k)
    from common.conventions import voxel_index
    return cell_keys.pack(voxel_index(xyz.to(torch.float64), vox))


def surface_samples(origin: torch.Tensor, D: torch.Tensor, depth_flat: torch.Tensor, pix: torch.Tensor,
                    offs: torch.Tensor, vox: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Kernel-only: (points (P, 3) float32 = origin + D[pix] * depth[pix], sorted unique packed
    keys of the occupied samples origin + D[pix] * (depth[pix] + offs[k]) with positive depth)."""
    pts, keys, lo, hi = _rfkernels.surface_samples(_np(origin, torch.float64), _np(D, torch.float64),
                                                    _np(depth_flat, torch.float32), _np(pix, torch.int64),
                                                    _np(offs, torch.float64), float(vox))
    cell_keys.check_range(lo, hi)
    return torch.from_numpy(pts), torch.from_numpy(keys)


def half_scores_enabled(h: torch.Tensor) -> bool:
    """True if :func:`half_scores` runs for float16 rows ``h`` (kernels enabled, a CPU with
    AVX2/FMA/F16C, rows on the CPU)."""
    return _HALF_SCORES and enabled(h) and h.dtype == torch.float16 and h.ndim == 2


def half_scores(h: torch.Tensor, q: torch.Tensor, a: torch.Tensor, b: torch.Tensor | None, qm: float,
                threads: int) -> torch.Tensor:
    """Kernel-only ``(h.float() @ q) * a + qm * b`` (N,) float32 for float16 rows ``h`` (N, D),
    a float32 query ``q`` (D,) and per-row float32 ``a``, ``b`` (``b`` None: no mean term), the
    products and sums in float32 in one order per row (a row scores the same in any subset),
    on ``threads`` threads. The torch twin (``torch.mv`` in float16, then the terms) rounds
    the query and the sum to float16; both lie within ``SCORE_ATOL`` of the exact cosine."""
    out = torch.empty(h.shape[0], dtype=torch.float32)
    bb = torch.empty(0, dtype=torch.float32) if b is None else b
    _rfkernels.half_scores(h.contiguous().view(torch.int16).numpy(), _np(q, torch.float32),
                           _np(a, torch.float32), _np(bb, torch.float32), float(qm), out.numpy(), int(threads))
    return out
