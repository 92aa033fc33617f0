"""Reference ray store for the tests: the sorted-array algorithm the package's
:class:`semantic_map.ray_frontiers.RayStore` replaced, in its simplest full-scan form.

Bins are kept as plain arrays sorted by (frontier key, theta bin, phi bin); a prune keeps
the bins whose key is in the table (``isin`` over the whole store); a merge looks up every
stored bin, fuses existing bins, appends the new ones and re-sorts the whole store. Same
arithmetic per bin as the package (weighted mean in float32, stored in the feature dtype).
"""
from __future__ import annotations

import torch

from common.conventions import voxel_center
from semantic_map import cell_keys
from semantic_map.ray_frontiers import bin_centre_dirs, bin_counts, bin_rays


class SortedRayStore:
    """Sorted-array ray store (full scans): the oracle of ``RayStore``'s observable state."""

    def __init__(self, beta, psi, feature_dim, feature_dtype=torch.float32, device="cpu"):
        self.beta, self.psi, self.dim, self.dtype = float(beta), float(psi), int(feature_dim), feature_dtype
        self.device = torch.device(device)
        self.nt, self.np_ = bin_counts(psi)
        e = torch.empty(0, dtype=torch.int64)
        self.fkey, self.tbin, self.pbin = e, e.clone(), e.clone()
        self.feat = torch.empty((0, self.dim), dtype=self.dtype)
        self.weight = torch.empty(0, dtype=torch.float32)
        self.dsum = torch.empty((0, 3), dtype=torch.float32)

    def __len__(self):
        return self.fkey.numel()

    def _fields(self):
        return ("fkey", "tbin", "pbin", "feat", "weight", "dsum")

    def _take(self, idx):
        for f in self._fields():
            setattr(self, f, getattr(self, f)[idx])

    def _dead_out(self, dead):
        o = voxel_center(cell_keys.unpack(self.fkey[dead]), self.beta)
        n = self.dsum[dead].norm(dim=1, keepdim=True)
        bc = bin_centre_dirs(self.tbin[dead], self.pbin[dead], self.psi)
        dd = torch.where(n > 1e-12, self.dsum[dead] / n.clamp_min(1e-12), bc)
        return (o, dd, self.feat[dead].to(torch.float32))

    def prune(self, frontier_keys, requeue):
        alive = torch.isin(self.fkey, frontier_keys)
        out = None
        if requeue and not bool(alive.all()):
            out = self._dead_out(~alive)
        self._take(alive)
        return out

    def prune_keys(self, gone_keys, requeue):
        dead = torch.isin(self.fkey, gone_keys)
        if not bool(dead.any()):
            return None
        out = self._dead_out(dead) if requeue else None
        self._take(~dead)
        return out

    def merge(self, fkeys, frontier_keys_sorted, dirs, feats, w):
        if fkeys.numel() == 0:
            return
        nb = self.nt * self.np_
        uc, sw, sf, sd = bin_rays(fkeys, frontier_keys_sorted, dirs, feats, w, self.psi)   # grouping is shared
        fi_old = cell_keys.lookup(frontier_keys_sorted, self.fkey)
        pos = cell_keys.lookup(fi_old * nb + self.tbin * self.np_ + self.pbin, uc)
        ex = pos >= 0
        if bool(ex.any()):
            rows = pos[ex]
            W0 = self.weight[rows]
            W1 = W0 + sw[ex]
            self.feat[rows] = ((self.feat[rows].to(torch.float32) * W0[:, None] + sf[ex]) / W1[:, None]).to(self.dtype)
            self.weight[rows] = W1
            self.dsum[rows] = self.dsum[rows] + sd[ex]
        nw = ~ex
        if bool(nw.any()):
            c = uc[nw]
            fidx = torch.div(c, nb, rounding_mode="floor")
            rem = c - fidx * nb
            self.fkey = torch.cat([self.fkey, frontier_keys_sorted[fidx]])
            self.tbin = torch.cat([self.tbin, torch.div(rem, self.np_, rounding_mode="floor")])
            self.pbin = torch.cat([self.pbin, rem % self.np_])
            self.feat = torch.cat([self.feat, (sf[nw] / sw[nw][:, None]).to(self.dtype)])
            self.weight = torch.cat([self.weight, sw[nw]])
            self.dsum = torch.cat([self.dsum, sd[nw]])
            fi_all = cell_keys.lookup(frontier_keys_sorted, self.fkey)
            self._take(torch.argsort(fi_all * nb + self.tbin * self.np_ + self.pbin))

    def origins(self):
        return voxel_center(cell_keys.unpack(self.fkey), self.beta)

    def directions(self):
        n = self.dsum.norm(dim=1, keepdim=True)
        bc = bin_centre_dirs(self.tbin, self.pbin, self.psi)
        return torch.where(n > 1e-12, self.dsum / n.clamp_min(1e-12), bc)

    def set_frontier_directions(self, fkeys, dirs):
        pos = cell_keys.lookup(fkeys, self.fkey) if fkeys.numel() else torch.full_like(self.fkey, -1)
        hit = pos >= 0
        self.dsum[hit] = dirs[pos[hit]].to(torch.float32) * self.weight[hit, None]

    def memory_bytes(self):
        return sum(getattr(self, f).numel() * getattr(self, f).element_size() for f in self._fields())

    def state(self):
        return {f: getattr(self, f).clone() for f in self._fields()}

    def load_state(self, st):
        for f in self._fields():
            t = st[f]
            setattr(self, f, t.to(self.dtype) if f == "feat" else t.clone())
