"""Semantic ray frontiers: association of rays to frontiers, angle binning, weighted merge,
pruning / re-casting and direction inference (paper §III-E; docs/method.md#ray-association).

Association (paper equation, per ray over its own candidate set): a frontier ``p`` (coarse
centre, cell size ``beta``) is a candidate of ray ``(o, d)`` when ``t = (p - o)·d > 0``,
``d_ortho = |p - o - t d| <= beta``, ``d_orig = |p - o| <= max_dist`` (``max_dist =
ray_range_factor * range``; no limit when the range is unknown) and, with the reference's
optional rule, ``d_orig >= 2 beta``. Two cost scales (``MapConfig.ray_cost_norm``, docs/method.md#cost-scale):

* ``paper``: ``c = (d_ortho / max_cand d_ortho + d_orig / max_cand d_orig) / 2`` (a 0/0 term
  is 0), normalised per ray over its own candidates as the paper's equation reads; a lone
  candidate costs 1, so the map floors the weight at ``ray_min_weight``, and adding a worse
  second candidate raises the chosen one's weight.
* ``absolute``: ``c = (d_ortho / beta + d_orig / max_dist) / 2`` — fixed scales, so a ray's
  cost does not depend on which other frontiers happen to be candidates; both terms lie in
  [0, 1] by the candidate test, no floor. With an unknown range (``max_dist <= 0``) the
  ``d_orig`` term keeps the per-ray maximum.

The ray takes the candidate of least cost (ties: lowest frontier index); weight ``1 - c``.
Zero-depth mode (either scale): every frontier is a candidate, cost ``d_orig / max d_orig``
(nearest frontier), no direction test.

Candidates come from a spatial index, never from an R×F matrix: each frontier is
registered in the 27 coarse cells around its own; each ray is walked through the coarse
grid up to ``max_dist`` (:mod:`semantic_map.traversal`) and looks up the cells it touches. Any
frontier within ``beta`` of the ray's closest point lies in that point's 3×3×3 coarse
neighbourhood, so the candidate set is exact. Memory O(rays × cells walked + candidates).
With the C++ kernels (:mod:`semantic_map.kernels`) the walk, the pair test and the per-ray argmin
run in C++ on blocks of coarse cells (a hash of blocks listing the frontiers within one
cell of them), with the same float32 / float64 arithmetic, so both paths give identical
results; the pair metrics use one base point for all rays of a call.

Angles on world axes (z up): ``theta = atan2(d_y, d_x)``, ``phi = acos(d_z)`` (degrees).
Bins: ``n_theta = round(360 / psi)`` bins centred on multiples of ``360 / n_theta`` with
wrap-around (±180° share a bin), ``n_phi = round(180 / psi)`` bins ``[k, k+1) * 180 / n_phi``;
``psi >= 360`` gives one bin per frontier (semantic frontiers).
"""
from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING

import torch

from common.conventions import voxel_center, voxel_index
from semantic_map import cell_keys, kernels
from semantic_map.row_storage import grown_capacity
from semantic_map.traversal import segment_cells

if TYPE_CHECKING:
    from semantic_map.occupancy import OccupancyGrid

#: ray -> frontier association: (ray idx (K,), frontier idx (K,), float64 cost (K,))
Association = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
#: rays to cast: (origins (R, 3), unit directions (R, 3), features (R, C))
RayBatch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]

KERNEL_RAY_CHUNK = 1 << 15  # rays per kernel call in associate(): bounds the candidate-pair memory
_OFFS = torch.tensor([[a, b, c] for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)], dtype=torch.int64)


# --------------------------------------------------------------------------- angles / bins
def angles_deg(dirs: torch.Tensor) -> torch.Tensor:
    """(N, 2) (theta, phi) degrees of unit directions (world axes)."""
    th = torch.rad2deg(torch.atan2(dirs[:, 1], dirs[:, 0]))
    ph = torch.rad2deg(torch.acos(dirs[:, 2].clamp(-1.0, 1.0)))
    return torch.stack([th, ph], 1)


def bin_counts(psi: float) -> tuple[int, int]:
    if psi >= 360:
        return 1, 1
    return max(1, round(360.0 / psi)), max(1, round(180.0 / psi))


def angle_bins(dirs: torch.Tensor, psi: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(theta_bin, phi_bin) int64 per direction (see module docstring)."""
    nt, npb = bin_counts(psi)
    if nt == 1 and npb == 1:
        z = torch.zeros(dirs.shape[0], dtype=torch.int64, device=dirs.device)
        return z, z.clone()
    a = angles_deg(dirs.to(torch.float64))
    tb = torch.remainder(torch.round(a[:, 0] / (360.0 / nt)).to(torch.int64), nt)
    pb = torch.floor(a[:, 1] / (180.0 / npb)).to(torch.int64).clamp(0, npb - 1)
    return tb, pb


def bin_centre_dirs(tb: torch.Tensor, pb: torch.Tensor, psi: float) -> torch.Tensor:
    """(N, 3) float32 unit direction of each bin centre."""
    nt, npb = bin_counts(psi)
    th = torch.deg2rad(tb.to(torch.float64) * (360.0 / nt))
    ph = torch.deg2rad((pb.to(torch.float64) + 0.5) * (180.0 / npb))
    return torch.stack([torch.sin(ph) * torch.cos(th), torch.sin(ph) * torch.sin(th), torch.cos(ph)],
                       1).to(torch.float32)


# --------------------------------------------------------------------------- association
def _base(o: torch.Tensor) -> torch.Tensor:
    """Common base point of the float32 pair metrics: the rounded mean ray origin."""
    return torch.round(o.mean(0)) if o.shape[0] else torch.zeros(3, dtype=o.dtype, device=o.device)


def _select(ri: torch.Tensor, fi: torch.Tensor, o, d, p, beta, max_dist, reject_close, n_rays, base=None,
            cost: str = "paper"):
    """Filter candidate pairs, cost (see module docstring), argmin. Returns (rays, frontiers, cost).

    Per pair, in float32 relative to a common base point (:func:`_base` of all rays):
    ``t = v·d``, ``d_orig² = v·v``, ``d_ortho² = max(v·v - t², 0)`` with ``v = p - o``."""
    if base is None:
        base = _base(o)
    o32 = (o - base).to(torch.float32)
    p32 = (p - base).to(torch.float32)
    d32 = d.to(torch.float32)
    v = torch.index_select(p32, 0, fi) - torch.index_select(o32, 0, ri)
    t = (v * torch.index_select(d32, 0, ri)).sum(1)
    vv = (v * v).sum(1)
    del v
    oo = (vv - t * t).clamp_min(0)
    ok = (t > 0) & (oo <= beta * beta)
    if max_dist > 0:
        ok &= vv <= max_dist * max_dist
    if reject_close:
        ok &= vv >= 4 * beta * beta
    ri, fi = ri[ok], fi[ok]
    return _argmin_cost(ri, fi, (oo[ok].sqrt().to(torch.float64), vv[ok].sqrt().to(torch.float64)), n_rays,
                        _scales(cost, beta, max_dist))


def _scales(cost: str, beta: float, max_dist: float):
    """Fixed per-term scales of the ``absolute`` cost (``None`` = per-ray max), or None for ``paper``."""
    if cost == "paper":
        return None
    if cost != "absolute":
        raise ValueError(f"ray cost normalisation must be 'paper' or 'absolute', got {cost!r}")
    return (float(beta), float(max_dist) if max_dist > 0 else None)


def _argmin_cost(ri, fi, terms, n_rays, scales=None):
    dev = ri.device
    cost = torch.zeros(ri.shape[0], dtype=torch.float64, device=dev)
    for j, x in enumerate(terms):
        if scales is not None and scales[j] is not None:
            cost += x / scales[j]
            continue
        mx = torch.zeros(n_rays, dtype=torch.float64, device=dev).scatter_reduce(0, ri, x, "amax", include_self=True)
        den = mx[ri]
        cost += torch.where(den > 0, x / torch.where(den > 0, den, torch.ones_like(den)), torch.zeros_like(x))
    cost /= len(terms)
    big = torch.full((n_rays,), math.inf, dtype=torch.float64, device=dev)
    cmin = big.scatter_reduce(0, ri, cost, "amin", include_self=True)
    at = cost == cmin[ri]
    fbig = torch.full((n_rays,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=dev)
    fmin = fbig.scatter_reduce(0, ri[at], fi[at], "amin", include_self=True)
    rays = torch.nonzero(torch.isfinite(cmin)).squeeze(1)
    return rays, fmin[rays], cmin[rays]


def associate(origins: torch.Tensor, dirs: torch.Tensor, frontier_ijk: torch.Tensor, beta: float, *,
              max_dist: float = -1.0, reject_close: bool = False, zero_depth: bool = False,
              cost: str = "paper", chunk: int = 1 << 22, block: int = kernels.ASSOCIATION_BLOCK,
              fan_off: bool = False, _base_pt: torch.Tensor | None = None) -> Association:
    """Match rays to coarse frontiers (cells ``frontier_ijk`` (F, 3) of size ``beta``).

    Returns ``(ray_idx (K,), frontier_idx (K,), cost (K,) float64)`` for the rays that found
    a frontier; ``cost`` = ``paper`` | ``absolute`` (module docstring). Exact same result as
    :func:`associate_bruteforce`. Candidates come from the C++ kernels (:mod:`semantic_map.kernels`)
    when available — with ``max_dist`` > 0 and rays from a few origins, per origin the rays
    binned by direction (``associate_rays_fan``; ``fan_off`` skips it), else a walk through
    blocks of ``block``³ coarse cells — and otherwise from the torch walk below; the exact test
    and cost are the same torch code."""
    dev = origins.device
    R, F = origins.shape[0], frontier_ijk.shape[0]
    e = torch.empty(0, dtype=torch.int64, device=dev)
    if R == 0 or F == 0:
        return e, e.clone(), torch.empty(0, dtype=torch.float64, device=dev)
    o = origins.to(torch.float64)
    d = dirs.to(torch.float64)
    p = (frontier_ijk.to(torch.float64) + 0.5) * beta
    if zero_depth:
        return _nearest(o, p)
    scales = _scales(cost, beta, max_dist)
    base = _base(o) if _base_pt is None else _base_pt
    # ray length: the distance cutoff, or the farthest frontier-bbox corner
    if max_dist > 0:
        L = torch.full((R,), float(max_dist), dtype=torch.float64, device=dev)
    else:
        lo, hi = p.min(0).values, p.max(0).values
        far = torch.maximum((o - lo).abs(), (o - hi).abs())
        L = far.norm(dim=1)
    if kernels.enabled(o, d, frontier_ijk):
        step = KERNEL_RAY_CHUNK
        amin = lambda r, f, x, n: _argmin_cost(r, f, x, n, scales)  # noqa: E731

        def chunk_pairs(s: int) -> Association:
            got = None
            if max_dist > 0 and not fan_off:
                got = kernels.associate_rays_fan(o[s:s + step], d[s:s + step], frontier_ijk, beta, base, max_dist,
                                                 reject_close, scales=scales, argmin=amin)
            if got is None:
                got = kernels.associate_rays(o[s:s + step], d[s:s + step], L[s:s + step], frontier_ijk, beta, base,
                                             max_dist, reject_close, block, scales=scales, argmin=amin)
            return got

        parts = [chunk_pairs(s) for s in range(0, R, step)]
        if len(parts) == 1:
            return parts[0]
        return (torch.cat([a[0] + s for a, s in zip(parts, range(0, R, step), strict=True)]),
                torch.cat([a[1] for a in parts]), torch.cat([a[2] for a in parts]))
    ray_chunk = 8192  # per-ray results are independent: chunking over rays bounds memory
    if R > ray_chunk:
        parts = [associate(origins[s:s + ray_chunk], dirs[s:s + ray_chunk], frontier_ijk, beta, max_dist=max_dist,
                           reject_close=reject_close, cost=cost, chunk=chunk, _base_pt=base)
                 for s in range(0, R, ray_chunk)]
        return (torch.cat([a[0] + s for a, s in zip(parts, range(0, R, ray_chunk), strict=True)]),
                torch.cat([a[1] for a in parts]), torch.cat([a[2] for a in parts]))
    ends = o + d * L[:, None]
    # dilated frontier table: cell key -> frontier index
    dil = frontier_ijk.to(torch.int64)[:, None, :] + _OFFS.to(dev)[None]
    dk = cell_keys.pack(dil.reshape(-1, 3))
    df = torch.arange(F, device=dev).repeat_interleave(27)
    order = torch.argsort(dk)
    dk, df = dk[order], df[order]
    ri_all, fi_all = [], []
    # lookup structure for walked cells: dense (start, count) table over the dilated
    # frontier box when small, else binary search in the sorted dilated keys
    dil_ijk = cell_keys.unpack(dk)
    lo_c = frontier_ijk.min(0).values.to(torch.int64) - 1
    ext = frontier_ijk.max(0).values.to(torch.int64) + 2 - lo_c
    dense = int(ext.prod()) <= (1 << 22)  # two int32 tables of at most 16 MiB each
    if dense:
        loc = dil_ijk - lo_c
        flat = (loc[:, 0] * ext[1] + loc[:, 1]) * ext[2] + loc[:, 2]
        uf, cnt_u = torch.unique_consecutive(flat, return_counts=True)
        tab_start = torch.zeros(int(ext.prod()), dtype=torch.int32, device=dev)
        tab_cnt = torch.zeros(int(ext.prod()), dtype=torch.int32, device=dev)
        tab_start[uf] = (torch.cumsum(cnt_u, 0) - cnt_u).to(torch.int32)
        tab_cnt[uf] = cnt_u.to(torch.int32)
    rid, cells = segment_cells(o, ends, beta, chunk=chunk)
    if dense:
        loc = cells - lo_c
        ins = ((loc >= 0) & (loc < ext)).all(1)
        rid, loc = rid[ins], loc[ins]
        flat = (loc[:, 0] * ext[1] + loc[:, 1]) * ext[2] + loc[:, 2]
        n = tab_cnt[flat].to(torch.int64)
        lo_i = tab_start[flat].to(torch.int64)
    else:
        ck = cell_keys.pack(cells)
        lo_i = torch.searchsorted(dk, ck)
        n = torch.searchsorted(dk, ck, right=True) - lo_i
    hit = n > 0
    rid, lo_i, n = rid[hit], lo_i[hit], n[hit]
    if rid.numel():
        pr = torch.repeat_interleave(rid, n)
        start = torch.cumsum(n, 0) - n
        pos = torch.arange(int(n.sum()), device=dev) + torch.repeat_interleave(lo_i - start, n)
        # duplicates (a frontier reached from several walked cells) are harmless: they
        # carry identical metrics, so maxima, minima and tie-breaks are unchanged
        ri_all.append(pr)
        fi_all.append(df[pos])
    if not ri_all:
        return e, e.clone(), torch.empty(0, dtype=torch.float64, device=dev)
    ri, fi = torch.cat(ri_all), torch.cat(fi_all)
    return _select(ri, fi, o, d, p, beta, max_dist, reject_close, R, base, cost)


def frontiers_in_box(keys: torch.Tensor, lo_m: torch.Tensor, hi_m: torch.Tensor, beta: float) -> torch.Tensor:
    """Ascending indices into the ascending packed coarse ``keys`` (cell size ``beta``) of every
    frontier whose cell lies in the box ``[lo_m, hi_m]`` (world metres, (3,)) grown by one
    more cell. Reads only the keys of the box (per i-plane of the box, the run of its j-rows,
    found by binary search), so the cost follows the box, not the table."""
    e = torch.empty(0, dtype=torch.int64, device=keys.device)
    if keys.numel() == 0:
        return e
    lo = torch.floor(lo_m.to(torch.float64) / beta).to(torch.int64) - 1
    hi = torch.floor(hi_m.to(torch.float64) / beta).to(torch.int64) + 1
    lo = lo.clamp(-cell_keys.OFFSET, cell_keys.OFFSET - 1).to(keys.device) + cell_keys.OFFSET
    hi = hi.clamp(-cell_keys.OFFSET, cell_keys.OFFSET - 1).to(keys.device) + cell_keys.OFFSET
    b = cell_keys.BITS
    planes = torch.arange(int(lo[0]), int(hi[0]) + 1, dtype=torch.int64, device=keys.device) << (2 * b)
    first = torch.searchsorted(keys, planes | (lo[1] << b))
    last = torch.searchsorted(keys, planes | (hi[1] << b) | cell_keys.MASK, right=True)
    _, pos = _expand(first, last - first)
    k = keys[pos] & cell_keys.MASK
    return pos[(k >= lo[2]) & (k <= hi[2])]


def associate_near(origins: torch.Tensor, dirs: torch.Tensor, keys: torch.Tensor, beta: float, max_dist: float,
                   **kw) -> Association:
    """:func:`associate` of the rays against the frontiers of the ascending packed coarse
    ``keys``, each ray looking only at the frontiers near its own segment: the rays are grouped
    by origin (cells of ``max_dist`` metres, one group when all origins lie within
    ``2 * max_dist`` of each other) and each group is cast against the frontiers in the box of
    its segments ``origin -> origin + max_dist * dir`` grown by ``1.5 beta``
    (:func:`frontiers_in_box`). Same result as against the whole table: a candidate's centre
    lies within ``max_dist`` of the origin and within ``beta`` of the ray, ahead of the origin,
    so within ``beta`` of the segment (one base point for all groups keeps the float32 pair
    metrics the same; frontier indices into ``keys``). The box of one camera's frustum is a
    fraction of the box around its origin, and a ray block's rays re-queued from pruned
    frontiers can come from anywhere on the map."""
    if max_dist <= 0:
        raise ValueError(f"associate_near needs a positive max_dist, got {max_dist}")
    o = origins.to(torch.float64)
    base = _base(o)
    e = torch.empty(0, dtype=torch.int64, device=o.device)
    R = o.shape[0]
    if R and float((o.max(0).values - o.min(0).values).max()) > 2 * max_dist:
        _, group = torch.unique(cell_keys.pack(torch.floor(o / max_dist).to(torch.int64)), return_inverse=True)
        members: list[torch.Tensor | None] = [torch.nonzero(group == g).squeeze(1)
                                              for g in range(int(group.max()) + 1)]
    else:
        members = [None]
    ri_all, fi_all, c_all = [], [], []
    for idx in members:
        oo, dd = (o, dirs) if idx is None else (o[idx], dirs[idx])
        ends = oo + dd.to(torch.float64) * max_dist
        ok = torch.isfinite(ends).all(1)          # the kernel skips non-finite rays
        if not bool(ok.any()):
            continue
        pts = torch.cat([oo[ok], ends[ok]])
        near = frontiers_in_box(keys, pts.min(0).values - 1.5 * beta, pts.max(0).values + 1.5 * beta, beta)
        ri, fi, c = associate(oo, dd, cell_keys.unpack(keys[near]), beta, max_dist=max_dist, _base_pt=base, **kw)
        ri_all.append(ri if idx is None else idx[ri])
        fi_all.append(near[fi])
        c_all.append(c)
    if not ri_all:
        return e, e.clone(), torch.empty(0, dtype=torch.float64, device=o.device)
    if len(ri_all) == 1:
        return ri_all[0], fi_all[0], c_all[0]
    ri, fi, c = torch.cat(ri_all), torch.cat(fi_all), torch.cat(c_all)
    order = torch.argsort(ri)
    return ri[order], fi[order], c[order]


def _nearest(o: torch.Tensor, p: torch.Tensor) -> Association:
    """Zero-depth association: nearest frontier per ray (computed per unique origin)."""
    uo, inv = torch.unique(o, dim=0, return_inverse=True)
    best_f = torch.empty(uo.shape[0], dtype=torch.int64, device=o.device)
    best_c = torch.empty(uo.shape[0], dtype=torch.float64, device=o.device)
    step = max(1, (1 << 22) // max(1, p.shape[0]))
    for s in range(0, uo.shape[0], step):
        dist = torch.cdist(uo[s:s + step], p)
        mx = dist.max(1, keepdim=True).values
        c = torch.where(mx > 0, dist / torch.where(mx > 0, mx, torch.ones_like(mx)), torch.zeros_like(dist))
        cv, ci = c.min(1)
        best_f[s:s + step], best_c[s:s + step] = ci, cv
    rays = torch.arange(o.shape[0], device=o.device)
    return rays, best_f[inv], best_c[inv]


def associate_bruteforce(origins: torch.Tensor, dirs: torch.Tensor, frontier_ijk: torch.Tensor, beta: float, *,
                         max_dist: float = -1.0, reject_close: bool = False, zero_depth: bool = False,
                         cost: str = "paper") -> Association:
    """O(R×F) reference of :func:`associate` (tests only)."""
    R, F = origins.shape[0], frontier_ijk.shape[0]
    o = origins.to(torch.float64)
    d = dirs.to(torch.float64)
    p = (frontier_ijk.to(torch.float64) + 0.5) * beta
    if zero_depth:
        return _nearest(o, p)
    ri = torch.arange(R).repeat_interleave(F)
    fi = torch.arange(F).repeat(R)
    return _select(ri, fi, o, d, p, beta, max_dist, reject_close, R, cost=cost)


def bin_rays(fkeys: torch.Tensor, frontier_keys_sorted: torch.Tensor, dirs: torch.Tensor, feats: torch.Tensor,
             w: torch.Tensor, psi: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Group rays by (frontier, angle bin): ``(codes, sum w, sum w·feat, sum w·dir)`` per group,
    float32 sums, codes ascending = ``frontier index · n_bins + theta bin · n_phi + phi bin``
    with the frontier's index in ``frontier_keys_sorted`` (so in (frontier key, bin) order).
    Raises ``ValueError`` for a ray whose frontier key is not in the table."""
    nt, npb = bin_counts(psi)
    tb, pb = angle_bins(dirs, psi)
    fi = cell_keys.lookup(frontier_keys_sorted, fkeys)
    if bool((fi < 0).any()):
        raise ValueError("ray refers to a frontier that is not in the table")
    uc, inv = torch.unique(fi * (nt * npb) + tb * npb + pb, return_inverse=True)
    m, dev = uc.numel(), fkeys.device
    w32 = w.to(torch.float32)
    sw = torch.zeros(m, dtype=torch.float32, device=dev).index_add_(0, inv, w32)
    sf = torch.zeros((m, feats.shape[1]), dtype=torch.float32, device=dev).index_add_(
        0, inv, feats.to(torch.float32) * w32[:, None])
    sd = torch.zeros((m, 3), dtype=torch.float32, device=dev).index_add_(0, inv, dirs.to(torch.float32) * w32[:, None])
    return uc, sw, sf, sd


# --------------------------------------------------------------------------- store
#: per-field dtype of a store row (``feat`` in the store's ``feature_dtype``)
_ROW_DTYPES = {"fkey": torch.int64, "tbin": torch.int64, "pbin": torch.int64, "weight": torch.float32,
               "dsum": torch.float32}


def _lexsort(k: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Permutation that sorts pairs ``(k, b)`` lexicographically (stable)."""
    o = torch.argsort(b, stable=True)
    return o[torch.argsort(k[o], stable=True)]


def _expand(lo: torch.Tensor, cnt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(query id, position) of every position in the ranges ``[lo[q], lo[q] + cnt[q])``."""
    q = torch.repeat_interleave(torch.arange(cnt.numel(), device=cnt.device), cnt)
    start = torch.cumsum(cnt, 0) - cnt
    return q, lo[q] + (torch.arange(q.numel(), device=cnt.device) - start[q])


def _view_field(name: str, doc: str) -> property:
    """A read-only property: a fresh copy of the store's field ``name`` in canonical order."""
    return property(lambda self: self._field(name), doc=doc)


class _Run:
    """One sorted run of the store's index: frontier key ``k`` (int64), bin ``b`` (``tbin *
    n_phi + pbin``) and row ``r`` per entry (both stored as int32), sorted by ``(k, b)``;
    ``r = -1`` is a tombstone."""

    __slots__ = ("k", "b", "r")

    def __init__(self, k: torch.Tensor, b: torch.Tensor, r: torch.Tensor) -> None:
        self.k, self.b, self.r = k, b.to(torch.int32), r.to(torch.int32)

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.k, self.b, self.r))

    def __len__(self) -> int:
        return self.k.numel()

    def ranges(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(query id, entry position) of every entry whose key is in ``keys``."""
        lo = torch.searchsorted(self.k, keys)
        return _expand(lo, torch.searchsorted(self.k, keys, right=True) - lo)

    def find(self, keys: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
        """Entry position of each pair ``(keys[i], bins[i])`` (tombstones included), -1 if absent."""
        q, pos = self.ranges(keys)
        hit = self.b[pos] == bins[q]
        out = torch.full((keys.numel(),), -1, dtype=torch.int64, device=keys.device)
        out[q[hit]] = pos[hit]
        return out


class RayStore:
    """Binned semantic rays: one row per (frontier key, angle bin).

    Per bin: frontier key (packed coarse ijk), theta/phi bin, feature = weighted mean
    (stored in ``feature_dtype``), accumulated weight, weighted sum of unit directions.

    Storage (a ray block costs O(changed bins · log store) amortised, never a rewrite of the store):

    * rows are append-only (a full table grows by ~1/32, :mod:`semantic_map.row_storage`); a
      pruned bin's row is a tombstone (``live`` false) until a compaction drops the dead rows,
      once they are a ninth of the rows;
    * an index from ``(frontier key, bin)`` to row, kept across ray blocks as a few sorted
      runs (a log-structured merge: a block's new bins form a new run, runs of similar size
      are merged, so every entry is merged O(log) times); pruning a frontier marks its
      entries as tombstones (a bin that comes back reuses its entry), dropped when runs merge
      or when they are a fifth of the index.

    The observable store is the *canonical view*: the live bins sorted by ``(frontier key,
    theta bin, phi bin)``, the order the previous sorted-array store kept. The attributes
    ``fkey``, ``tbin``, ``pbin``, ``feat``, ``weight``, ``dsum``, :meth:`state`, :meth:`origins`,
    :meth:`directions` and the rays :meth:`prune` / :meth:`prune_keys` return all follow it (the
    order is built on first read after a change, O(store), and cached; each field read gathers a
    fresh copy, so the store holds no second copy of its features), so values, order and snapshots equal
    the sorted store's (``tests/test_ray_store.py`` checks against that algorithm)."""

    _FIELDS = ("fkey", "tbin", "pbin", "feat", "weight", "dsum")
    _RUN_RATIO = 4        # a run is merged into the previous one while that one is at most this many times larger
    _MIN_COMPACT = 4096   # below this many dead rows / index tombstones nothing is compacted
    _DEAD_ROW_SHARE = 8   # dead rows are compacted once they exceed live rows / this
    _TOMB_SHARE = 4       # index tombstones are dropped once they exceed live rows / this

    def __init__(self, beta: float, psi: float, feature_dim: int, feature_dtype: torch.dtype = torch.float32,
                 device: str | torch.device = "cpu") -> None:
        self.beta = float(beta)
        self.psi = float(psi)
        self.dim = int(feature_dim)
        self.dtype = feature_dtype
        self.device = torch.device(device)
        self.nt, self.np_ = bin_counts(psi)
        self._reset(0)

    # -- storage -------------------------------------------------------------------------
    def _reset(self, cap: int) -> None:
        dev = self.device
        self._n = 0                 # rows in use (live + dead)
        self._n_dead = 0            # dead rows among them
        self._n_tomb = 0            # tombstones in the index
        self._rk = torch.zeros(cap, dtype=torch.int64, device=dev)           # frontier key
        self._rb = torch.zeros(cap, dtype=torch.int32, device=dev)           # bin = tbin * n_phi + pbin
        self._rf = torch.zeros((cap, self.dim), dtype=self.dtype, device=dev)  # feature
        self._rw = torch.zeros(cap, dtype=torch.float32, device=dev)         # weight
        self._rd = torch.zeros((cap, 3), dtype=torch.float32, device=dev)    # direction sum
        self._live = torch.zeros(cap, dtype=torch.bool, device=dev)
        self._runs: list[_Run] = []
        self._view: dict[str, torch.Tensor] = {}

    def _grow(self, need: int) -> None:
        cap = self._rk.shape[0]
        if need <= cap:
            return
        cap = grown_capacity(cap, need)
        for name in ("_rk", "_rb", "_rf", "_rw", "_rd", "_live"):
            old = getattr(self, name)
            new = torch.zeros((cap,) + tuple(old.shape[1:]), dtype=old.dtype, device=self.device)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def _changed(self) -> None:
        self._view = {}

    def _add_run(self, run: _Run) -> None:
        """Append a sorted run; merge runs of similar size (the log-structured merge)."""
        self._runs.append(run)
        while len(self._runs) >= 2 and len(self._runs[-2]) <= self._RUN_RATIO * len(self._runs[-1]):
            b = self._runs.pop()
            a = self._runs.pop()
            self._n_tomb -= int((a.r < 0).sum()) + int((b.r < 0).sum())
            self._runs.append(self._merge_runs([a, b]))

    def _merge_runs(self, runs: list[_Run]) -> _Run:
        """One run of the live entries of ``runs`` (tombstones dropped)."""
        k = torch.cat([r.k for r in runs])
        b = torch.cat([r.b for r in runs])
        r = torch.cat([x.r for x in runs])
        tomb = r < 0
        if bool(tomb.any()):
            k, b, r = k[~tomb], b[~tomb], r[~tomb]
        o = _lexsort(k, b)
        return _Run(k[o], b[o], r[o])

    def _compact_index(self) -> None:
        """Merge all runs into one without tombstones."""
        if len(self._runs) > 1 or self._n_tomb:
            self._runs = [self._merge_runs(self._runs)] if self._runs else []
            self._n_tomb = 0

    def _compact_rows(self) -> None:
        """Drop the dead rows (row numbers in the index are renumbered)."""
        n = self._n
        live = self._live[:n]
        new_row = torch.cumsum(live, 0) - 1
        for run in self._runs:
            ok = run.r >= 0
            run.r = torch.where(ok, new_row[run.r.clamp_min(0)], run.r).to(torch.int32)
        keep = torch.nonzero(live).squeeze(1)
        m = keep.numel()
        for name in ("_rk", "_rb", "_rf", "_rw", "_rd"):
            t = getattr(self, name)
            t[:m] = t[keep]
        self._live[:m] = True
        self._live[m:n] = False
        self._n, self._n_dead = m, 0

    def _maybe_compact(self) -> None:
        live = self._n - self._n_dead
        if self._n_tomb > max(self._MIN_COMPACT, live // self._TOMB_SHARE):
            self._compact_index()
        if self._n_dead > max(self._MIN_COMPACT, live // self._DEAD_ROW_SHARE):
            self._compact_rows()

    def _find(self, keys: torch.Tensor, bins: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per pair: (run number or -1, entry position in that run, row: -1 when absent or a tombstone)."""
        m = keys.numel()
        run_of = torch.full((m,), -1, dtype=torch.int64, device=self.device)
        pos = torch.full((m,), -1, dtype=torch.int64, device=self.device)
        for i, run in enumerate(self._runs):
            p = run.find(keys, bins)
            hit = p >= 0
            run_of[hit] = i
            pos[hit] = p[hit]
        row = torch.full((m,), -1, dtype=torch.int64, device=self.device)
        for i, run in enumerate(self._runs):
            sel = run_of == i
            row[sel] = run.r[pos[sel]].to(torch.int64)
        return run_of, pos, row

    def _rows_of(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
        """(query id, row) of every live bin of the frontiers ``keys``, and per run the
        positions of those bins' index entries."""
        qs, rows, hits = [], [], []
        for run in self._runs:
            q, pos = run.ranges(keys)
            r = run.r[pos]
            ok = r >= 0
            qs.append(q[ok])
            rows.append(r[ok])
            hits.append(pos[ok])
        if not qs:
            e = torch.empty(0, dtype=torch.int64, device=self.device)
            return e, e.clone(), []
        return torch.cat(qs), torch.cat(rows).to(torch.int64), hits

    # -- canonical view --------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n - self._n_dead

    def _fields(self) -> tuple[str, ...]:
        return self._FIELDS

    def _view_rows(self) -> torch.Tensor:
        """Rows of the live bins in canonical (frontier key, bin) order (cached)."""
        rows = self._view.get("rows")
        if rows is None:
            self._compact_index()
            rows = (self._runs[0].r.to(torch.int64) if self._runs
                    else torch.empty(0, dtype=torch.int64, device=self.device))
            self._view["rows"] = rows
        return rows

    def _field(self, f: str) -> torch.Tensor:
        """A fresh copy of field ``f`` in canonical order."""
        rows = self._view_rows()
        if f == "tbin":
            return torch.div(self._rb[rows].to(torch.int64), self.np_, rounding_mode="floor")
        if f == "pbin":
            return self._rb[rows].to(torch.int64) % self.np_
        return {"fkey": self._rk, "feat": self._rf, "weight": self._rw, "dsum": self._rd}[f][rows]

    fkey = _view_field("fkey", "(R,) int64 frontier key per bin (canonical order; a copy).")
    tbin = _view_field("tbin", "(R,) int64 theta bin.")
    pbin = _view_field("pbin", "(R,) int64 phi bin.")
    feat = _view_field("feat", "(R, C) weighted mean feature (``feature_dtype``).")
    weight = _view_field("weight", "(R,) float32 accumulated weight.")
    dsum = _view_field("dsum", "(R, 3) float32 weighted sum of unit directions.")

    # -- updates ---------------------------------------------------------------------------
    def prune(self, frontier_keys: torch.Tensor, requeue: bool) -> RayBatch | None:
        """Drop bins whose frontier is gone; return (origins, dirs, feats) of the dropped
        bins for re-casting when ``requeue`` (origin = old frontier centre, direction = the
        bin's stored weighted mean direction (:meth:`directions`; the bin centre only for a
        zero direction sum), feature = bin mean), else None. The mean, not the bin centre:
        with one 360° bin the centre is always +x (docs/method.md#recast-direction).
        Full scan (O(store)): for a store whose frontier history is unknown."""
        if len(self) == 0:
            return None
        alive = torch.isin(self.fkey, frontier_keys)
        if bool(alive.all()):
            return None
        rows = self._view_rows()
        out = self._dead_out(rows[~alive]) if requeue else None
        self._kill(rows[~alive])
        for run in self._runs:
            if run.r.numel():
                run.r = torch.where((run.r >= 0) & self._live[run.r.clamp_min(0)], run.r, -1)
        self._n_tomb = sum(int((run.r < 0).sum()) for run in self._runs)
        self._changed()
        self._maybe_compact()
        return out

    def _kill(self, rows: torch.Tensor) -> None:
        self._live[rows] = False
        self._n_dead += int(rows.numel())

    def _dead_out(self, rows: torch.Tensor) -> RayBatch:
        """Re-cast rays of ``rows`` (in canonical order), see :meth:`prune`."""
        fk, bn = self._rk[rows], self._rb[rows].to(torch.int64)
        o = voxel_center(cell_keys.unpack(fk), self.beta)
        ds = self._rd[rows]
        n = ds.norm(dim=1, keepdim=True)
        bc = bin_centre_dirs(torch.div(bn, self.np_, rounding_mode="floor"), bn % self.np_, self.psi)
        dd = torch.where(n > 1e-12, ds / n.clamp_min(1e-12), bc)
        return (o, dd, self._rf[rows].to(torch.float32))

    def prune_keys(self, gone_keys: torch.Tensor, requeue: bool) -> RayBatch | None:
        """:meth:`prune` for a store whose only frontiers missing from the table are among
        ``gone_keys`` (sorted unique): drops the bins of those frontiers, touching only them
        (O(dropped + len(gone_keys) · log store))."""
        if gone_keys.numel() == 0 or len(self) == 0:
            return None
        _, rows, hits = self._rows_of(gone_keys)
        if rows.numel() == 0:
            return None
        rows = rows[_lexsort(self._rk[rows], self._rb[rows])]   # canonical order of the re-cast rays
        out = self._dead_out(rows) if requeue else None
        for run, pos in zip(self._runs, hits, strict=True):
            run.r[pos] = -1
            self._n_tomb += int(pos.numel())
        self._kill(rows)
        self._changed()
        self._maybe_compact()
        return out

    def merge(self, fkeys: torch.Tensor, frontier_keys_sorted: torch.Tensor, dirs: torch.Tensor,
              feats: torch.Tensor, w: torch.Tensor) -> None:
        """Bin new rays (frontier key, unit dir, feature, weight) and fuse by weighted mean.
        Every ray's and every stored bin's frontier must be in ``frontier_keys_sorted``.
        O(new rays + touched bins · log store)."""
        if fkeys.numel() == 0:
            return
        nb = self.nt * self.np_
        uc, sw, sf, sd = bin_rays(fkeys, frontier_keys_sorted, dirs, feats, w, self.psi)
        ufi = torch.div(uc, nb, rounding_mode="floor")
        ub = uc - ufi * nb
        ufk = frontier_keys_sorted[ufi]
        run_of, pos, row = self._find(ufk, ub)
        ex = row >= 0
        if bool(ex.any()):
            rows_ex = row[ex]
            W0 = self._rw[rows_ex]
            W1 = W0 + sw[ex]
            self._rf[rows_ex] = ((self._rf[rows_ex].to(torch.float32) * W0[:, None] + sf[ex])
                                 / W1[:, None]).to(self.dtype)
            self._rw[rows_ex] = W1
            self._rd[rows_ex] = self._rd[rows_ex] + sd[ex]
        nw = ~ex
        k = int(nw.sum())
        if k:
            n0 = self._n
            self._grow(n0 + k)
            new_rows = torch.arange(n0, n0 + k, device=self.device)
            self._rk[n0:n0 + k] = ufk[nw]
            self._rb[n0:n0 + k] = ub[nw]
            self._rf[n0:n0 + k] = (sf[nw] / sw[nw][:, None]).to(self.dtype)
            self._rw[n0:n0 + k] = sw[nw]
            self._rd[n0:n0 + k] = sd[nw]
            self._live[n0:n0 + k] = True
            self._n = n0 + k
            # a bin that comes back takes its tombstoned index entry, the others form a new run
            ro, po = run_of[nw], pos[nw]
            back = ro >= 0
            for i, run in enumerate(self._runs):
                sel = ro == i
                if bool(sel.any()):
                    run.r[po[sel]] = new_rows[sel].to(torch.int32)
            self._n_tomb -= int(back.sum())
            fresh = ~back
            if bool(fresh.any()):   # ufk, ub are in (key, bin) order: already a sorted run
                self._add_run(_Run(ufk[nw][fresh], ub[nw][fresh], new_rows[fresh]))
        self._changed()

    # -- views -------------------------------------------------------------------------
    def origins(self) -> torch.Tensor:
        return voxel_center(cell_keys.unpack(self.fkey), self.beta)

    def directions(self) -> torch.Tensor:
        n = self.dsum.norm(dim=1, keepdim=True)
        bc = bin_centre_dirs(self.tbin, self.pbin, self.psi)
        return torch.where(n > 1e-12, self.dsum / n.clamp_min(1e-12), bc)

    def set_frontier_directions(self, fkeys: torch.Tensor, dirs: torch.Tensor) -> None:
        """Overwrite the direction of every bin of frontier ``fkeys[i]`` with ``dirs[i]``
        (``fkeys`` unique)."""
        if fkeys.numel() == 0 or len(self) == 0:
            return
        q, rows, _ = self._rows_of(fkeys)
        self._rd[rows] = dirs[q].to(torch.float32) * self._rw[rows, None]
        self._changed()

    def memory_bytes(self) -> int:
        """Bytes held: row storage (capacity) and index."""
        rows = sum(t.numel() * t.element_size() for t in (self._rk, self._rb, self._rf, self._rw, self._rd, self._live))
        return int(rows + sum(r.nbytes() for r in self._runs))

    def state(self) -> dict:
        """Copies of the canonical view's fields (``_fields()``)."""
        return {f: self._field(f) for f in self._FIELDS}

    def load_state(self, st: dict) -> None:
        """Replace the content by ``st`` (as :meth:`state` gives; any row order, unique (key, bin))."""
        fk = st["fkey"].to(self.device, torch.int64)
        n = fk.numel()
        bn = st["tbin"].to(self.device, torch.int64) * self.np_ + st["pbin"].to(self.device, torch.int64)
        o = _lexsort(fk, bn)
        ks, bs = fk[o], bn[o]
        if n > 1 and bool(((ks[1:] == ks[:-1]) & (bs[1:] == bs[:-1])).any()):
            raise ValueError("ray store state holds a (frontier key, bin) pair twice")
        self._reset(n)
        self._rk[:] = fk
        self._rb[:] = bn
        self._rf[:] = st["feat"].to(self.device, self.dtype).reshape(n, self.dim)
        self._rw[:] = st["weight"].to(self.device, torch.float32)
        self._rd[:] = st["dsum"].to(self.device, torch.float32).reshape(n, 3)
        self._live[:] = True
        self._n = n
        if n:
            self._runs = [_Run(ks, bs, o)]


def infer_directions(grid: OccupancyGrid, frontier_keys: torch.Tensor, beta: float, vox: float,
                     scale: str = "fine") -> torch.Tensor:
    """Unidirectional baseline: per frontier, ``normalise(sum_n w_n * offset_n)`` over the 26
    neighbours at offsets ``offset * h`` (h = vox for "fine", the reference's spacing; beta for
    "coarse") around the frontier centre, with ``w = +1`` if the occupancy there is unobserved
    (0) and -1 otherwise. A zero sum gives a zero vector (caller keeps the old direction)."""
    if frontier_keys.numel() == 0:
        return torch.empty((0, 3), dtype=torch.float32)
    h = beta if scale == "coarse" else vox
    offs = _OFFS[(_OFFS != 0).any(1)].to(frontier_keys.device)  # 26
    c = voxel_center(cell_keys.unpack(frontier_keys), beta).to(torch.float64)
    pts = c[:, None, :] + offs[None].to(torch.float64) * h
    vals = torch.as_tensor(grid.query(voxel_index(pts.reshape(-1, 3), vox).cpu())).to(frontier_keys.device)
    w = torch.where(vals.reshape(-1, 26) == 0, 1.0, -1.0)
    s = (w[..., None] * offs[None].to(torch.float32)).sum(1)
    n = s.norm(dim=1, keepdim=True)
    return torch.where(n > 0, s / n.clamp_min(1e-12), torch.zeros_like(s))


def warn_infer_direction(psi: float) -> None:
    if psi < 360:
        warnings.warn("infer_direction with angle_bin_size < 360: all bins of a frontier get the same direction",
                      stacklevel=2)
