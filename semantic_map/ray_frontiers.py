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
              cost: str = "paper", chunk: int = 1 << 22, block: int = 4,
              _base_pt: torch.Tensor | None = None) -> Association:
    """Match rays to coarse frontiers (cells ``frontier_ijk`` (F, 3) of size ``beta``).

    Returns ``(ray_idx (K,), frontier_idx (K,), cost (K,) float64)`` for the rays that found
    a frontier; ``cost`` = ``paper`` | ``absolute`` (module docstring). Exact same result as
    :func:`associate_bruteforce`. Candidates come from the C++ kernel (:mod:`semantic_map.kernels`,
    blocks of ``block``³ coarse cells) when available, else from the torch walk below; the
    exact test and cost are the same torch code."""
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
        parts = [kernels.associate_rays(o[s:s + step], d[s:s + step], L[s:s + step], frontier_ijk, beta, base,
                                        max_dist, reject_close, block, scales=scales,
                                        argmin=lambda r, f, x, n: _argmin_cost(r, f, x, n, scales))
                 for s in range(0, R, step)]
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


# --------------------------------------------------------------------------- store
class RayStore:
    """Binned semantic rays, sorted by (frontier key, bin id).

    Per bin: frontier key (packed coarse ijk), theta/phi bin, feature = weighted mean
    (stored in ``feature_dtype``), accumulated weight, weighted sum of unit directions.

    Incremental: :meth:`merge` finds each new (frontier, bin) by binary search on the sorted
    frontier keys and scans only that frontier's bins; new bins are placed by one ordered
    scatter (no sort of the store); :meth:`prune_keys` drops the bins of given vanished
    frontiers the same way. Results (values and order) equal the full-scan :meth:`prune`
    and the sort-based merge they replace (``tests/test_mapper_incremental.py``)."""

    def __init__(self, beta: float, psi: float, feature_dim: int, feature_dtype: torch.dtype = torch.float32,
                 device: str | torch.device = "cpu") -> None:
        self.beta = float(beta)
        self.psi = float(psi)
        self.dim = int(feature_dim)
        self.dtype = feature_dtype
        self.device = torch.device(device)
        self.nt, self.np_ = bin_counts(psi)
        dev = self.device
        self.fkey = torch.empty(0, dtype=torch.int64, device=dev)
        self.tbin = torch.empty(0, dtype=torch.int64, device=dev)
        self.pbin = torch.empty(0, dtype=torch.int64, device=dev)
        self.feat = torch.empty((0, self.dim), dtype=self.dtype, device=dev)
        self.weight = torch.empty(0, dtype=torch.float32, device=dev)
        self.dsum = torch.empty((0, 3), dtype=torch.float32, device=dev)

    def __len__(self) -> int:
        return self.fkey.numel()

    def _fields(self):
        return ("fkey", "tbin", "pbin", "feat", "weight", "dsum")

    def _take(self, idx) -> None:
        for f in self._fields():
            setattr(self, f, getattr(self, f)[idx])

    def prune(self, frontier_keys: torch.Tensor, requeue: bool) -> RayBatch | None:
        """Drop bins whose frontier is gone; return (origins, dirs, feats) of the dropped
        bins for re-casting when ``requeue`` (origin = old frontier centre, direction = the
        bin's stored weighted mean direction (:meth:`directions`; the bin centre only for a
        zero direction sum), feature = bin mean), else None. The mean, not the bin centre:
        with one 360° bin the centre is always +x (docs/method.md#recast-direction)."""
        alive = torch.isin(self.fkey, frontier_keys)
        out = None
        if requeue and not bool(alive.all()):
            out = self._dead_out(~alive)
        self._take(alive)
        return out

    def _ranges(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """For sorted query frontier ``keys``: (lo (m,), count (m,), query id per row, row) of
        every stored bin of those frontiers."""
        lo = torch.searchsorted(self.fkey, keys)
        cnt = torch.searchsorted(self.fkey, keys, right=True) - lo
        q = torch.repeat_interleave(torch.arange(keys.numel(), device=self.device), cnt)
        start = torch.cumsum(cnt, 0) - cnt
        rows = lo[q] + (torch.arange(q.numel(), device=self.device) - start[q])
        return lo, cnt, q, rows

    def _dead_out(self, dead: torch.Tensor) -> RayBatch:
        o = voxel_center(cell_keys.unpack(self.fkey[dead]), self.beta)
        n = self.dsum[dead].norm(dim=1, keepdim=True)
        bc = bin_centre_dirs(self.tbin[dead], self.pbin[dead], self.psi)
        dd = torch.where(n > 1e-12, self.dsum[dead] / n.clamp_min(1e-12), bc)
        return (o, dd, self.feat[dead].to(torch.float32))

    def prune_keys(self, gone_keys: torch.Tensor, requeue: bool) -> RayBatch | None:
        """:meth:`prune` for a store whose only frontiers missing from the table are among
        ``gone_keys`` (sorted unique): drops the bins of those frontiers, touching only them."""
        if gone_keys.numel() == 0 or self.fkey.numel() == 0:
            return None
        _, _, _, rows = self._ranges(gone_keys)
        if rows.numel() == 0:
            return None
        dead = torch.zeros(self.fkey.numel(), dtype=torch.bool, device=self.device)
        dead[rows] = True
        out = self._dead_out(dead) if requeue else None
        self._take(~dead)
        return out

    def merge(self, fkeys: torch.Tensor, frontier_keys_sorted: torch.Tensor, dirs: torch.Tensor,
              feats: torch.Tensor, w: torch.Tensor) -> None:
        """Bin new rays (frontier key, unit dir, feature, weight) and fuse by weighted mean.
        Every ray's and every stored bin's frontier must be in ``frontier_keys_sorted``."""
        if fkeys.numel() == 0:
            return
        tb, pb = angle_bins(dirs, self.psi)
        nb = self.nt * self.np_
        fi_new = cell_keys.lookup(frontier_keys_sorted, fkeys)
        if bool((fi_new < 0).any()):
            raise ValueError("ray refers to a frontier that is not in the table")
        comp_new = fi_new * nb + tb * self.np_ + pb
        uc, inv = torch.unique(comp_new, return_inverse=True)  # sorted = (frontier key, bin) order
        m = uc.numel()
        w32 = w.to(torch.float32)
        sw = torch.zeros(m, dtype=torch.float32, device=self.device).index_add_(0, inv, w32)
        sf = torch.zeros((m, self.dim), dtype=torch.float32, device=self.device).index_add_(
            0, inv, feats.to(torch.float32) * w32[:, None])
        sd = torch.zeros((m, 3), dtype=torch.float32, device=self.device).index_add_(
            0, inv, dirs.to(torch.float32) * w32[:, None])
        ufi = torch.div(uc, nb, rounding_mode="floor")
        ub = uc - ufi * nb
        ufk = frontier_keys_sorted[ufi]
        # locate each (frontier, bin) among that frontier's stored bins only
        lo, _, q, rows = self._ranges(ufk)
        rb = self.tbin[rows] * self.np_ + self.pbin[rows]
        hit = rb == ub[q]
        pos = torch.full((m,), -1, dtype=torch.int64, device=self.device)
        pos[q[hit]] = rows[hit]
        ex = pos >= 0
        if bool(ex.any()):
            rows_ex = pos[ex]
            W0 = self.weight[rows_ex]
            W1 = W0 + sw[ex]
            self.feat[rows_ex] = ((self.feat[rows_ex].to(torch.float32) * W0[:, None] + sf[ex])
                                  / W1[:, None]).to(self.dtype)
            self.weight[rows_ex] = W1
            self.dsum[rows_ex] = self.dsum[rows_ex] + sd[ex]
        nw = ~ex
        if bool(nw.any()):
            # insertion point of each new bin: after its frontier's smaller bins
            below = torch.bincount(q[rb < ub[q]], minlength=m)
            ins = (lo + below)[nw]                      # non-decreasing (keys sorted)
            k = int(nw.sum())
            R = self.fkey.numel()
            new_rows = ins + torch.arange(k, device=self.device)
            old_rows = torch.arange(R, device=self.device) + torch.searchsorted(
                ins, torch.arange(R, device=self.device), right=True)
            c = uc[nw]
            fidx = torch.div(c, nb, rounding_mode="floor")
            rem = c - fidx * nb
            vals = {"fkey": frontier_keys_sorted[fidx], "tbin": torch.div(rem, self.np_, rounding_mode="floor"),
                    "pbin": rem % self.np_, "feat": (sf[nw] / sw[nw][:, None]).to(self.dtype),
                    "weight": sw[nw], "dsum": sd[nw]}
            for f in self._fields():
                old = getattr(self, f)
                out = torch.empty((R + k,) + tuple(old.shape[1:]), dtype=old.dtype, device=self.device)
                out[old_rows] = old
                out[new_rows] = vals[f].to(old.dtype)
                setattr(self, f, out)

    # -- views -------------------------------------------------------------------------
    def origins(self) -> torch.Tensor:
        return voxel_center(cell_keys.unpack(self.fkey), self.beta)

    def directions(self) -> torch.Tensor:
        n = self.dsum.norm(dim=1, keepdim=True)
        bc = bin_centre_dirs(self.tbin, self.pbin, self.psi)
        return torch.where(n > 1e-12, self.dsum / n.clamp_min(1e-12), bc)

    def set_frontier_directions(self, fkeys: torch.Tensor, dirs: torch.Tensor) -> None:
        """Overwrite the direction of every bin of frontier ``fkeys[i]`` with ``dirs[i]``."""
        pos = cell_keys.lookup(fkeys, self.fkey) if fkeys.numel() else torch.full_like(self.fkey, -1)
        hit = pos >= 0
        self.dsum[hit] = dirs[pos[hit]].to(torch.float32) * self.weight[hit, None]

    def memory_bytes(self) -> int:
        return sum(getattr(self, f).numel() * getattr(self, f).element_size() for f in self._fields())

    def state(self) -> dict:
        return {f: getattr(self, f).clone() for f in self._fields()}

    def load_state(self, st: dict) -> None:
        for f in self._fields():
            t = st[f].to(self.device)
            if f == "feat":
                t = t.to(self.dtype)
            setattr(self, f, t)


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
