"""Pure-PyTorch occupancy grid: sorted int64 voxel keys + int8 log-odds values.

Same semantics as the OpenVDB extension (see :mod:`semantic_map.occupancy.base`), bit for bit:

* ``update`` reproduces sequential clamping exactly. ``x -> clamp(x + a, lo, hi)`` maps are
  closed under composition (``clamp(clamp(x+s1, L1, H1) + s2, L2, H2) =
  clamp(x + s1 + s2, clamp(L1+s2, L2, H2), clamp(H1+s2, L2, H2))``), so the rows of each
  voxel are reduced pairwise in ``ceil(log2(max duplicates))`` vectorised rounds.
* ``prune`` emulates ``openvdb::tools::prune`` on a ``Tree4<int8, 5, 4, 3>`` (leaf 8³, then
  internal nodes of 16³ leaves and of 32³ such nodes): bottom-up, a node collapses when all
  its children are (collapsed) fully active and ``max - min <= tolerance``; the tile value
  is the lower median (sorted element ``(n - 1) >> 1``) of the child values. Voxels are
  kept, holding the tile value, so later writes "re-densify" for free.
* ``frontiers`` counts neighbourhoods on dense bricks (16³ + halo) around candidates.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ._inputs import (
    IJK_MAX,
    IJK_MIN,
    as_ijk,
    as_inc,
    check_bounds,
    check_frontier_args,
    check_tolerance,
    pack,
    prepare_rays,
    unpack,
)
from .base import BBox, ChangeLog, GridInput

_BRICK_LOG2 = 4
_BRICK = 1 << _BRICK_LOG2   # frontier brick edge (voxels); must exceed 2 * max radius
_MAX_BRICK_CELLS = 1 << 24   # padded cells per frontier chunk (bounds memory)
# OpenVDB Tree4<int8,5,4,3>: log2 child count per level, bottom-up.
_LEVEL_LOG2 = (3, 4, 5)


class TorchOccupancy:
    """Occupancy grid in pure torch (CPU). See :class:`semantic_map.occupancy.base.OccupancyGrid`."""

    backend = "torch"

    def __init__(self, vox: float, lo: int = -5, hi: int = 30, device: str | torch.device = "cpu") -> None:
        self.vox, self.lo, self.hi = check_bounds(vox, lo, hi)
        # The map lives and is computed on `device`; inputs/outputs are CPU tensors.
        self.device = torch.device(device)
        self._keys = torch.empty(0, dtype=torch.int64, device=self.device)  # sorted, unique
        self._vals = torch.empty(0, dtype=torch.int8, device=self.device)
        self.revision = 0  # counts calls that may change values (update, prune, load_state)
        self.changes = ChangeLog()

    # ------------------------------------------------------------------ basic access
    @property
    def num_active(self) -> int:
        return int(self._keys.numel())

    def memory_bytes(self) -> int:
        return int(self._keys.numel() * 8 + self._vals.numel())

    def _lookup(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions of ``keys`` in the map and whether they are present."""
        n = self._keys.numel()
        if n == 0:
            return (torch.zeros_like(keys), torch.zeros_like(keys, dtype=torch.bool))
        pos = torch.searchsorted(self._keys, keys)
        posc = pos.clamp_max(n - 1)
        found = self._keys[posc] == keys
        return posc, found

    def _values_at_keys(self, keys: torch.Tensor) -> torch.Tensor:
        pos, found = self._lookup(keys)
        out = torch.zeros_like(keys, dtype=torch.int8)
        if self._vals.numel():
            out[found] = self._vals[pos[found]]
        return out

    def query(self, ijk: GridInput) -> torch.Tensor:
        ijk = as_ijk(ijk).to(self.device)
        return self._values_at_keys(pack(ijk)).cpu()

    def active(self) -> tuple[torch.Tensor, torch.Tensor]:
        return unpack(self._keys).cpu(), self._vals.clone().cpu()

    def occupied(self) -> np.ndarray:
        return unpack(self._keys[self._vals > 0]).cpu().numpy().astype(np.int64)

    def state(self) -> dict:
        ijk, vals = self.active()
        return {"vox": self.vox, "lo": self.lo, "hi": self.hi,
                "ijk": ijk.numpy(), "values": vals.numpy()}

    def load_state(self, state: dict) -> None:
        """Replace the map by ``state`` (see :meth:`state`)."""
        ijk = as_ijk(state["ijk"], "state['ijk']").to(self.device)
        vals = torch.as_tensor(state["values"]).reshape(-1).to(self.device)
        if vals.shape[0] != ijk.shape[0]:
            raise ValueError("state: 'ijk' and 'values' lengths differ")
        if vals.numel() and (int(vals.min()) < -128 or int(vals.max()) > 127):
            raise ValueError("state: values must fit int8")
        keys = pack(ijk)
        keys, order = torch.sort(keys)
        if keys.numel() > 1 and bool((keys[1:] == keys[:-1]).any()):
            raise ValueError("state: duplicate voxel indices")
        self._keys = keys.contiguous()
        self._vals = vals.to(torch.int8)[order].contiguous()
        self.revision += 1
        self.changes.everything()

    # ------------------------------------------------------------------ update
    def update(self, ijk: GridInput, inc: GridInput | int) -> None:
        self.revision += 1
        dev = self.device
        ijk = as_ijk(ijk).to(dev)
        self.changes.add(ijk)
        n = ijk.shape[0]
        inc = as_inc(inc, n).to(dev)
        if n == 0:
            return
        keys = pack(ijk)
        # Stable sort keeps row order within each voxel (the order clamping is applied in).
        skeys, order = torch.sort(keys, stable=True)
        s = inc[order]
        uk, counts = torch.unique_consecutive(skeys, return_counts=True)
        seg = torch.repeat_interleave(torch.arange(uk.numel(), device=dev), counts)
        starts = torch.cumsum(counts, 0) - counts
        rank = torch.arange(n, device=dev) - starts[seg]
        lo_t = torch.full((n,), self.lo, dtype=torch.int64, device=dev)
        hi_t = torch.full((n,), self.hi, dtype=torch.int64, device=dev)
        # Pairwise composition within each voxel: (s, L, H) means x -> clamp(x+s, L, H).
        while rank.numel() > uk.numel():
            nxt = torch.empty_like(rank, dtype=torch.bool)
            nxt[:-1] = seg[1:] == seg[:-1]
            nxt[-1] = False
            first = (rank % 2 == 0)
            pair = first & nxt                      # element p combines with p + 1
            p = torch.nonzero(pair).squeeze(1)
            s2, l2, h2 = s[p + 1], lo_t[p + 1], hi_t[p + 1]
            lo_t[p] = torch.clamp(lo_t[p] + s2, l2, h2)
            hi_t[p] = torch.clamp(hi_t[p] + s2, l2, h2)
            s[p] = s[p] + s2
            keep = first
            s, lo_t, hi_t, seg, rank = s[keep], lo_t[keep], hi_t[keep], seg[keep], rank[keep] // 2
        cur = self._values_at_keys(uk).to(torch.int64)
        new = torch.minimum(torch.maximum(cur + s, lo_t), hi_t).to(torch.int8)
        self._merge(uk, new)

    def _merge(self, uk: torch.Tensor, new: torch.Tensor) -> None:
        """Write values for sorted unique keys ``uk`` (existing keys overwritten)."""
        pos, found = self._lookup(uk)
        if bool(found.any()):
            self._vals[pos[found]] = new[found]
        if bool(found.all()):
            return
        ak, av = uk[~found], new[~found]
        old = self._keys
        m, a = old.numel(), ak.numel()
        dev = self.device
        keys = torch.empty(m + a, dtype=torch.int64, device=dev)
        vals = torch.empty(m + a, dtype=torch.int8, device=dev)
        pos_new = torch.searchsorted(old, ak) + torch.arange(a, device=dev)
        pos_old = torch.searchsorted(ak, old) + torch.arange(m, device=dev)
        keys[pos_new], vals[pos_new] = ak, av
        keys[pos_old], vals[pos_old] = old, self._vals
        self._keys, self._vals = keys, vals

    # ------------------------------------------------------------------ prune
    def prune(self, tolerance: int) -> None:
        tol = check_tolerance(tolerance)
        self.revision += 1
        self.changes.everything()
        if self._keys.numel() == 0:
            return
        ijk = unpack(self._keys)
        vals = self._vals.to(torch.int64)
        # Units of the current level: their value, whether they are (collapsed) constant,
        # and each voxel's unit index. Level 0 units are voxels.
        unit_val = vals
        unit_const = torch.ones_like(vals, dtype=torch.bool)
        dev = self.device
        voxel_unit = torch.arange(vals.numel(), device=dev)
        shift = 0
        assign = []  # per level: (voxel -> node index, node collapsed mask, node value)
        for log2 in _LEVEL_LOG2:
            shift += log2
            nchild = 1 << (3 * log2)
            # Node of each unit: take any voxel of the unit (units are uniform in this).
            unit_ijk = torch.empty((unit_val.numel(), 3), dtype=torch.int64, device=dev)
            unit_ijk[voxel_unit] = ijk
            node_keys = pack(unit_ijk >> shift)
            uk, node_of_unit, counts = torch.unique(node_keys, return_inverse=True,
                                                    return_counts=True)
            nn = uk.numel()
            nconst = torch.zeros(nn, dtype=torch.int64, device=dev).index_add_(
                0, node_of_unit, unit_const.to(torch.int64))
            vmin = torch.full((nn,), 1 << 20, dtype=torch.int64, device=dev).scatter_reduce_(
                0, node_of_unit, unit_val, "amin")
            vmax = torch.full((nn,), -(1 << 20), dtype=torch.int64, device=dev).scatter_reduce_(
                0, node_of_unit, unit_val, "amax")
            collapse = (counts == nchild) & (nconst == nchild) & (vmax - vmin <= tol)
            if not bool(collapse.any()):
                break
            # Lower median of each node's child values: sort by (node, value).
            order = torch.argsort(node_of_unit * 512 + (unit_val + 256))
            starts = torch.cumsum(counts, 0) - counts
            mid = (nchild - 1) >> 1
            cidx = torch.nonzero(collapse).squeeze(1)
            node_val = unit_val.new_zeros(nn)
            node_val[cidx] = unit_val[order[starts[cidx] + mid]]
            voxel_node = node_of_unit[voxel_unit]
            assign.append((voxel_node, collapse, node_val))
            # Next level's units are this level's nodes.
            unit_val = torch.where(collapse, node_val, unit_val.new_zeros(nn))
            unit_const = collapse
            voxel_unit = voxel_node
        for voxel_node, collapse, node_val in assign:
            sel = collapse[voxel_node]
            vals = torch.where(sel, node_val[voxel_node], vals)
        self._vals = vals.to(torch.int8)

    # ------------------------------------------------------------------ frontiers
    def frontiers(self, min_unobserved: int, min_free: int, min_occupied: int = 0,
                  radius: int = 1, bbox: BBox | None = None) -> torch.Tensor:
        (mu, mf, mo), r, bbox = check_frontier_args(min_unobserved, min_free, min_occupied,
                                                    radius, bbox)
        dev = self.device
        empty = torch.empty((0, 3), dtype=torch.int64)
        s0, s1 = (0, self._keys.numel()) if bbox is None else self._i_slice(bbox[0][0],
                                                                            bbox[1][0])
        keys, vals = self._keys[s0:s1], self._vals[s0:s1]
        cand_mask = vals < 0
        if not bool(cand_mask.any()):
            return empty
        cand = unpack(keys[cand_mask])
        if bbox is not None:
            lo_b = torch.tensor(bbox[0], dtype=torch.int64, device=dev)
            hi_b = torch.tensor(bbox[1], dtype=torch.int64, device=dev)
            cand = cand[((cand >= lo_b) & (cand <= hi_b)).all(dim=1)]
            if cand.shape[0] == 0:
                return empty
        size = (2 * r + 1) ** 3
        if mu <= 0 and mf <= 1 and mo <= 0:
            return cand.cpu()  # every free voxel counts itself as free
        if mu > size or mf > size or mo > size:
            return empty
        B = _BRICK
        P = B + 2 * r
        cbrick = cand >> _BRICK_LOG2                     # floor division by B
        bkeys, cand_b = torch.unique(pack(cbrick), return_inverse=True)
        nb = bkeys.numel()
        # Each observed map voxel (value != 0; the volume starts as "unobserved") lands in
        # its own brick and, when within r of a brick face, in the neighbours' halos.
        # Only voxels within r of the candidates' bounding box can be neighbours.
        cmin, cmax = cand.min(0).values - r, cand.max(0).values + r
        s0, s1 = self._i_slice(int(cmin[0]), int(cmax[0]))
        keys, vals = self._keys[s0:s1], self._vals[s0:s1]
        nz = vals != 0
        ijk = unpack(keys[nz])
        inside = ((ijk >= cmin) & (ijk <= cmax)).all(dim=1)
        ijk = ijk[inside]
        sign = torch.sign(vals[nz][inside])
        vbrick = ijk >> _BRICK_LOG2
        local = ijk & (B - 1)
        ext = (local >= B - r).to(torch.int64) - (local < r).to(torch.int64)  # -1/0/+1 per axis
        border = torch.nonzero((ext != 0).any(dim=1)).squeeze(1)
        ext_b = ext[border]
        parts_v: list[torch.Tensor] = []
        parts_b: list[torch.Tensor] = []
        parts_flat: list[torch.Tensor] = []

        def add(idx: torch.Tensor, dvec: torch.Tensor | None) -> None:
            tb = vbrick[idx] if dvec is None else vbrick[idx] + dvec
            tk = pack(tb.clamp(IJK_MIN >> _BRICK_LOG2, IJK_MAX >> _BRICK_LOG2))
            pos = torch.searchsorted(bkeys, tk).clamp_max(nb - 1)
            ok = bkeys[pos] == tk
            idx, pos = idx[ok], pos[ok]
            loc = local[idx] + r if dvec is None else local[idx] - dvec[ok] * B + r
            parts_v.append(idx)
            parts_b.append(pos)
            parts_flat.append((loc[:, 0] * P + loc[:, 1]) * P + loc[:, 2])

        add(torch.arange(ijk.shape[0], device=dev), None)
        for sub in range(1, 8):   # non-empty subsets of the axes that get the halo offset
            axes = torch.tensor([(sub >> a) & 1 for a in range(3)], dtype=torch.bool, device=dev)
            m = (ext_b[:, axes] != 0).all(dim=1)
            sel = torch.nonzero(m).squeeze(1)
            if sel.numel():
                add(border[sel], ext_b[sel] * axes)
        pv, pb, pflat = torch.cat(parts_v), torch.cat(parts_b), torch.cat(parts_flat)
        cl = cand - cbrick * B
        cflat = (cl[:, 0] * B + cl[:, 1]) * B + cl[:, 2]
        keep = torch.zeros(cand.shape[0], dtype=torch.bool, device=dev)
        chunk = max(1, _MAX_BRICK_CELLS // (P ** 3))
        psel: slice | torch.Tensor
        csel: slice | torch.Tensor
        for b0 in range(0, nb, chunk):
            b1 = min(nb, b0 + chunk)
            if b0 == 0 and b1 == nb:
                psel, csel = slice(None), slice(None)
            else:
                psel = (pb >= b0) & (pb < b1)
                csel = (cand_b >= b0) & (cand_b < b1)
            vol = torch.zeros((b1 - b0) * P ** 3, dtype=torch.int8, device=dev)
            vol[(pb[psel] - b0) * P ** 3 + pflat[psel]] = sign[pv[psel]]
            vol = vol.view(b1 - b0, P, P, P)
            at = (cand_b[csel] - b0) * B ** 3 + cflat[csel]
            nfree = _box_count(vol == -1, r).view(-1)[at]
            nocc = _box_count(vol == 1, r).view(-1)[at] if (mo > 0 or mu > 0) else 0
            nun = size - nfree - nocc
            keep[csel] = (nun >= mu) & (nfree >= mf) & (nocc >= mo)
        return cand[keep].cpu()

    def _i_slice(self, i_lo: int, i_hi: int) -> tuple[int, int]:
        """Range of positions in the sorted keys whose i lies in [i_lo, i_hi]."""
        i_lo, i_hi = max(i_lo, IJK_MIN), min(i_hi, IJK_MAX)
        if i_lo > i_hi:
            return 0, 0
        b = pack(torch.tensor([[i_lo, IJK_MIN, IJK_MIN], [i_hi, IJK_MAX, IJK_MAX]],
                              device=self.device))
        s0 = int(torch.searchsorted(self._keys, b[0]))
        s1 = int(torch.searchsorted(self._keys, b[1], right=True))
        return s0, s1

    # ------------------------------------------------------------------ rays
    def first_blocked(self, origins: GridInput, directions: GridInput, max_dist: float) -> torch.Tensor:
        o, d, v, max_dist = prepare_rays(origins, directions, max_dist, self.vox)
        dev = self.device
        return _dda_first_blocked(self._values_at_ijk, o.to(dev), d.to(dev), v.to(dev),
                                  max_dist, self.vox).cpu()

    def _values_at_ijk(self, ijk: torch.Tensor) -> torch.Tensor:
        inside = ((ijk >= IJK_MIN) & (ijk <= IJK_MAX)).all(dim=1)
        out = torch.zeros(ijk.shape[0], dtype=torch.int8, device=ijk.device)
        if bool(inside.any()):
            out[inside] = self._values_at_keys(pack(ijk[inside]))
        return out


def _box_count(mask: torch.Tensor, r: int) -> torch.Tensor:
    """(nb, P, P, P) bool → (nb, P-2r, P-2r, P-2r) counts over the (2r+1)³ cube (exact)."""
    k = 2 * r + 1
    x = mask.to(torch.float32).unsqueeze(1)
    x = torch.nn.functional.avg_pool3d(x, (k, 1, 1), stride=1, divisor_override=1)
    x = torch.nn.functional.avg_pool3d(x, (1, k, 1), stride=1, divisor_override=1)
    x = torch.nn.functional.avg_pool3d(x, (1, 1, k), stride=1, divisor_override=1)
    return x.squeeze(1).round().to(torch.int32)


def _dda_first_blocked(values_at, o, d, v, max_dist: float, vox: float) -> torch.Tensor:
    """Vectorised Amanatides–Woo traversal; same arithmetic as the C++ extension.

    Per axis the next boundary index is ``v + 1`` (d > 0) or ``v`` (d < 0) and its
    distance ``(nb * vox - o) / d`` (float64), ``inf`` for d == 0; ties step the lowest
    axis first. Returns ``max(entry distance, 0)`` of the first voxel with value >= 0."""
    n = o.shape[0]
    dev = o.device
    out = torch.full((n,), math.inf, dtype=torch.float64, device=dev)
    if n == 0:
        return out
    step = torch.sign(d).to(torch.int64)
    nb = v + (step > 0).to(torch.int64)
    inf = torch.tensor(math.inf, dtype=torch.float64, device=dev)

    def tnext(nb_, o_, d_):
        return torch.where(d_ != 0, (nb_.to(torch.float64) * vox - o_) / d_, inf)

    tmax = tnext(nb, o, d)
    tent = torch.zeros(n, dtype=torch.float64, device=dev)
    rid = torch.arange(n, device=dev)
    while rid.numel():
        blocked = values_at(v) >= 0
        if bool(blocked.any()):
            out[rid[blocked]] = tent[blocked].clamp_min(0.0)
            keep = ~blocked
            rid, v, nb, tmax, tent, o, d, step = (x[keep] for x in
                                                  (rid, v, nb, tmax, tent, o, d, step))
            if rid.numel() == 0:
                break
        ax = torch.argmin(tmax, dim=1)  # first minimal index on ties
        tmin = tmax.gather(1, ax[:, None]).squeeze(1)
        alive = tmin <= max_dist
        if not bool(alive.all()):
            rid, v, nb, tmax, tmin, ax, o, d, step = (x[alive] for x in
                                                      (rid, v, nb, tmax, tmin, ax, o, d, step))
            if rid.numel() == 0:
                break
        rows = torch.arange(rid.numel(), device=dev)
        st = step[rows, ax]
        v[rows, ax] += st
        nb[rows, ax] += st
        tmax[rows, ax] = tnext(nb[rows, ax], o[rows, ax], d[rows, ax])
        tent = tmin
    return out
