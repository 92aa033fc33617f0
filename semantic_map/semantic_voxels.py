"""Semantic voxels: RGB + feature + hit count per voxel, hit-count weighted running mean.

Storage is row-based (rows never move except when pruning fills holes); a full table grows
by ~1/32 (:mod:`semantic_map.row_storage`). A persistent key index maps packed voxel keys
(:mod:`semantic_map.cell_keys`) to int32 rows: a large sorted ``main`` array plus a small
sorted ``delta`` array that absorbs inserts and is merged into ``main`` only when it grows
past a fraction of it, so an update costs O(new points · log) amortised, never a re-sort of
the whole map per update.

Fusion of points ``(x, rgb, f)`` into voxel ``v`` with count ``n``:
``mean' = (n * mean + sum_new) / (n + k)``, ``n' = n + k`` (k new points), accumulated in
float32 and stored in ``feature_dtype`` (float32 or float16; colours too, so a float16 map's
colours are within 2^-11 of the float32 mean: at most ±1 of the uint8 output). Equal to the
hit-count weighted mean over every point ever inserted.

Change journal (for an incrementally maintained copy, the query's
:class:`mapper.query_answer.QueryCopy`): every row a fuse writes or a prune moves is
recorded; :meth:`SemanticVoxels.take_changes` hands the rows changed since the last call to
*one* consumer (``owner``), so the copy is brought up to date by copying those rows only.
The journal holds at most ``n / 4`` rows (then it says "everything", and the consumer takes a
full copy), so it stays bounded when nobody consumes it.
"""
from __future__ import annotations

import torch

from common.conventions import voxel_center, voxel_index
from semantic_map import cell_keys
from semantic_map.row_storage import grown_capacity


class KeyIndex:
    """int64 key → row, with insert / lookup / delete (two-level sorted arrays; rows are
    stored as int32 and returned as int64)."""

    def __init__(self, device: str | torch.device = "cpu") -> None:
        self.device = torch.device(device)
        k = torch.empty(0, dtype=torch.int64, device=self.device)
        r = torch.empty(0, dtype=torch.int32, device=self.device)
        self.main_k, self.main_r, self.delta_k, self.delta_r = k, r, k.clone(), r.clone()

    def __len__(self) -> int:
        return self.main_k.numel() + self.delta_k.numel()

    def lookup(self, q: torch.Tensor) -> torch.Tensor:
        out = torch.full(q.shape, -1, dtype=torch.int64, device=q.device)
        for k, r in ((self.main_k, self.main_r), (self.delta_k, self.delta_r)):
            p = cell_keys.lookup(k, q)
            hit = p >= 0
            out[hit] = r[p[hit]].to(torch.int64)
        return out

    def insert(self, k: torch.Tensor, r: torch.Tensor) -> None:
        """Insert keys that are not present yet (caller guarantees)."""
        dk = torch.cat([self.delta_k, k])
        dr = torch.cat([self.delta_r, r.to(torch.int32)])
        o = torch.argsort(dk)
        self.delta_k, self.delta_r = dk[o], dr[o]
        if self.delta_k.numel() > max(4096, self.main_k.numel() // 8):
            self._merge()

    def _merge(self) -> None:
        k = torch.cat([self.main_k, self.delta_k])
        r = torch.cat([self.main_r, self.delta_r])
        o = torch.argsort(k)
        self.main_k, self.main_r = k[o], r[o]
        self.delta_k = self.delta_k[:0]
        self.delta_r = self.delta_r[:0]

    def delete(self, k: torch.Tensor) -> None:
        if k.numel() == 0:
            return
        for name in ("main", "delta"):
            kk = getattr(self, name + "_k")
            keep = ~torch.isin(kk, k)
            setattr(self, name + "_k", kk[keep])
            setattr(self, name + "_r", getattr(self, name + "_r")[keep])

    def set_rows(self, k: torch.Tensor, r: torch.Tensor) -> None:
        for kk, rr in ((self.main_k, self.main_r), (self.delta_k, self.delta_r)):
            p = cell_keys.lookup(kk, k)
            hit = p >= 0
            rr[p[hit]] = r[hit].to(torch.int32)

    def items(self) -> tuple[torch.Tensor, torch.Tensor]:
        """All (keys, int64 rows), keys ascending."""
        self._merge()
        return self.main_k, self.main_r.to(torch.int64)

    def memory_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.main_k, self.main_r, self.delta_k, self.delta_r))


def _live_rows(name: str, doc: str) -> property:
    """A property: the first ``n`` rows (the live voxels) of row table ``name``, a view."""
    return property(lambda self: getattr(self, name)[: self.n], doc=doc)


class SemanticVoxels:
    """Sparse semantic voxel map (see module docstring). ``vox`` in metres."""

    # row storage, set by _alloc (capacity rows, the first n live)
    _row_keys: torch.Tensor   # (cap,) int64 packed voxel key
    _rgb: torch.Tensor        # (cap, 3) feature dtype, in [0, 1]
    _feat: torch.Tensor       # (cap, C) feature dtype
    _count: torch.Tensor      # (cap,) float32 hit count

    def __init__(self, vox: float, feature_dim: int, feature_dtype: torch.dtype = torch.float32,
                 device: str | torch.device = "cpu") -> None:
        self.vox = float(vox)
        self.dim = int(feature_dim)
        self.dtype = feature_dtype
        self.device = torch.device(device)
        self.index = KeyIndex(self.device)
        self.n = 0
        self._alloc(1024)
        self._journal: list[torch.Tensor] = []   # rows changed since the consumer's last take
        self._journal_rows = 0
        self._journal_all = True                 # the consumer must take everything
        self._journal_owner: object = None

    def _alloc(self, cap: int) -> None:
        dev = self.device
        new = dict(
            row_keys=torch.zeros(cap, dtype=torch.int64, device=dev),
            rgb=torch.zeros((cap, 3), dtype=self.dtype, device=dev),
            feat=torch.zeros((cap, self.dim), dtype=self.dtype, device=dev),
            count=torch.zeros(cap, dtype=torch.float32, device=dev),
        )
        for k, v in new.items():
            old = getattr(self, "_" + k, None)
            if old is not None:
                v[: self.n] = old[: self.n]
            setattr(self, "_" + k, v)

    def __len__(self) -> int:
        return self.n

    # ------------------------------------------------------------------------------------
    def fuse(self, xyz: torch.Tensor, rgb: torch.Tensor, feat: torch.Tensor) -> torch.Tensor:
        """Fuse points ``xyz`` (P, 3) with ``rgb`` (P, 3) in [0, 1] and ``feat`` (P, C);
        returns the packed keys of the touched voxels (sorted, unique)."""
        keys = cell_keys.pack(voxel_index(xyz.to(torch.float64), self.vox))
        ones = torch.ones(keys.shape[0], dtype=torch.float32, device=keys.device)
        return self.fuse_sums(keys, rgb, feat, ones)

    def fuse_sums(self, keys: torch.Tensor, rgb_sum: torch.Tensor, feat_sum: torch.Tensor,
                  counts: torch.Tensor) -> torch.Tensor:
        """Fuse pre-aggregated samples: per row a packed voxel key, the sums of RGB and
        features over ``counts`` points (keys may repeat). Returns touched keys (sorted)."""
        if keys.numel() == 0:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        if feat_sum.shape[1] != self.dim:
            raise ValueError(f"feature dim {feat_sum.shape[1]} != map feature dim {self.dim}")
        uk, inv = torch.unique(keys, return_inverse=True)
        m = uk.numel()
        sf = torch.zeros((m, self.dim), dtype=torch.float32, device=self.device).index_add_(
            0, inv, feat_sum.to(torch.float32))
        sc = torch.zeros((m, 3), dtype=torch.float32, device=self.device).index_add_(0, inv, rgb_sum.to(torch.float32))
        cnt = torch.zeros(m, dtype=torch.float32, device=self.device).index_add_(0, inv, counts.to(torch.float32))
        rows = self.index.lookup(uk)
        new = rows < 0
        nn = int(new.sum())
        if nn:
            if self.n + nn > self._count.numel():
                self._alloc(grown_capacity(self._count.numel(), self.n + nn))
            nr = torch.arange(self.n, self.n + nn, device=self.device)
            rows[new] = nr
            self.index.insert(uk[new], nr)
            self._row_keys[nr] = uk[new]
            self._count[nr] = 0
            self.n += nn
        self._note(rows)
        c0 = self._count[rows]
        c1 = c0 + cnt
        w0 = (c0 / c1)[:, None]
        self._feat[rows] = (self._feat[rows].to(torch.float32) * w0 + sf / c1[:, None]).to(self.dtype)
        self._rgb[rows] = (self._rgb[rows].to(torch.float32) * w0 + sc / c1[:, None]).to(self.dtype)
        self._count[rows] = c1
        return uk

    def remove(self, keys: torch.Tensor) -> int:
        """Remove voxels with these packed keys (absent keys ignored); returns how many."""
        if keys.numel() == 0 or self.n == 0:
            return 0
        keys = torch.unique(keys)
        rows = self.index.lookup(keys)
        hit = rows >= 0
        keys, rows = keys[hit], rows[hit]
        k = rows.numel()
        if k == 0:
            return 0
        self.index.delete(keys)
        new_n = self.n - k
        # fill holes below new_n with live rows from the tail
        dead = torch.zeros(self.n, dtype=torch.bool, device=self.device)
        dead[rows] = True
        holes = torch.nonzero(dead[:new_n]).squeeze(1)
        tail = torch.nonzero(~dead[new_n:]).squeeze(1) + new_n
        if holes.numel():
            for name in ("_row_keys", "_rgb", "_feat", "_count"):
                t = getattr(self, name)
                t[holes] = t[tail]
            self.index.set_rows(self._row_keys[holes], holes)
            self._note(holes)
        self.n = new_n
        return k

    # ------------------------------------------------------------------ change journal
    def _note(self, rows: torch.Tensor) -> None:
        if self._journal_all:
            return
        self._journal.append(rows)
        self._journal_rows += int(rows.numel())
        if self._journal_rows > max(4096, self.n // 4):
            self._journal, self._journal_rows, self._journal_all = [], 0, True

    def take_changes(self, owner: object) -> torch.Tensor | None:
        """Rows (sorted, unique, all ``< len(self)``) written or moved since ``owner``'s last
        call, or ``None``: take everything (first call of this owner, another owner in
        between, a reload, or more changes than the journal keeps). Rows ``>= len(self)`` are
        gone (pruned). Clears the journal."""
        everything = self._journal_all or self._journal_owner is not owner
        rows = None
        if not everything and self._journal:
            r = torch.cat(self._journal)
            r = torch.unique(r[r < self.n])
            rows = r
        elif not everything:
            rows = torch.empty(0, dtype=torch.int64, device=self.device)
        self._journal, self._journal_rows, self._journal_all = [], 0, False
        self._journal_owner = owner
        return rows

    # ------------------------------------------------------------------------------------
    keys = _live_rows("_row_keys", "(n,) int64 packed voxel keys (a view of the live rows).")
    rgb = _live_rows("_rgb", "(n, 3) mean colour in [0, 1] (feature dtype).")
    feat = _live_rows("_feat", "(n, C) mean feature (feature dtype).")
    count = _live_rows("_count", "(n,) float32 hit count.")

    def ijk(self) -> torch.Tensor:
        return cell_keys.unpack(self.keys)

    def xyz(self) -> torch.Tensor:
        return voxel_center(self.ijk(), self.vox)

    def memory_bytes(self) -> int:
        """Bytes held: row storage (capacity) and key index."""
        t = (self._row_keys, self._rgb, self._feat, self._count)
        return sum(x.numel() * x.element_size() for x in t) + self.index.memory_bytes()

    def state(self) -> dict[str, torch.Tensor]:
        return {"keys": self.keys.clone(), "rgb": self.rgb.clone(), "feat": self.feat.clone(),
                "count": self.count.clone()}

    def load_state(self, st: dict[str, torch.Tensor]) -> None:
        n = int(st["keys"].shape[0])
        self.n = 0
        self._alloc(max(1024, n))
        self.n = n
        self._row_keys[:n] = st["keys"].to(self.device)
        self._rgb[:n] = st["rgb"].to(self.device, self.dtype)
        self._feat[:n] = st["feat"].to(self.device, self.dtype)
        self._count[:n] = st["count"].to(self.device)
        self.index = KeyIndex(self.device)
        if n:
            self.index.insert(self._row_keys[:n].clone(), torch.arange(n, device=self.device))
            self.index._merge()
        self._journal, self._journal_rows, self._journal_all = [], 0, True
