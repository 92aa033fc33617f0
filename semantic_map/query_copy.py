"""The query's copy of the map (:class:`QueryCopy`), kept query-ready incrementally, and
its half-precision scoring (:class:`HalfFeatures`); split out of :mod:`mapper.query_answer`
(which re-exports the names).

Why half precision: at 5 M voxels × 100 dims a float32 copy is 2 GB and one text query is a
memory-bound matrix-vector product over all of it (~150–250 ms on the 2-core EPYC, at
~8–13 GB/s). The copy is therefore kept in **float16**, each row scaled by a power of two
(``2^-e``, ``e`` from the row's largest magnitude, so the scaled row lies in [-1, 1] and
neither overflows nor loses range; the scaling is exact, so the copy is a deterministic
function of the map's row whatever the batch it was copied in). A query reads half the bytes.
On x86-64 CPUs with F16C the product is the C++ kernel :func:`semantic_map.kernels.half_scores`
(torch's float16 matrix-vector product there runs well below memory speed: 10 M × 100 dims
~200 ms against ~85 ms for the kernel's float32 sums, on 2 cores).

Accuracy (stated tolerance, tested in ``tests/test_query_half.py`` against a float64
brute-force cosine): a score differs from the float64 cosine of the map's float32 feature
by at most ``SCORE_ATOL`` = 2e-3 (the float16 rounding of a row is ≤ 2^-11 of its largest
entry; the product accumulates in float32); the top-k set equals the float64 one except
for voxels whose reference score lies within ``2·SCORE_ATOL`` of the k-th best (near-ties).
Cosine terms that do not depend on the query (the inverse norms) are float32, from the
stored row.

Per-version products, kept up to date for the rows each :meth:`QueryCopy.sync` changed
(as the prepared terms): the scores of the last queries (:class:`_ScoreCache`: a repeated
or standing query costs the changed rows, not a pass over the copy; 4 bytes per voxel per
query, at most :data:`SCORE_CACHE_ENTRIES` queries and a quarter of the copy's bytes) and
the per-voxel log-sum-exp of a search's background phrases
(:meth:`QueryCopy.phrase_logsumexp`). Both hold exactly what a fresh computation gives
(the same per-row product).
"""
from __future__ import annotations

import contextlib
import hashlib
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

import numpy as np
import torch

from semantic_map import kernels

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace, PreparedFeatures
    from semantic_map.map import RayFrontsMap
    from semantic_map.semantic_voxels import SemanticVoxels

#: max |score − float64 cosine| of the half-precision copy (see the module docstring)
SCORE_ATOL = 2e-3
#: phrase sets whose per-row log-sum-exp :meth:`QueryCopy.phrase_logsumexp` keeps per space
LSE_SETS = 4
#: queries whose scores a prepared space keeps (:class:`HalfFeatures`), and the least bytes allowed
SCORE_CACHE_ENTRIES = 16
SCORE_CACHE_MIN_BYTES = 64 << 20
#: below this many feature elements a query's product runs on one thread (the parallel
#: region's hand-off costs more than it saves; on a loaded machine a descheduled OpenMP
#: worker stalls it), and the elementwise terms after it always do (one pass over N each)
PARALLEL_MIN_ELEMENTS = 1 << 25
#: a search's softmax over at least this many scores (targets × voxels, an exp per element)
#: runs on torch's threads (elementwise: the same values on any thread count)
PARALLEL_MIN_SCORES = 1 << 21


def _np(x: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


class _one_thread:
    """torch runs single-threaded inside (the incremental copy is many small ops: on a loaded
    machine every parallel region would wait on a descheduled OpenMP worker)."""

    def __enter__(self) -> None:
        self.n = torch.get_num_threads()
        if self.n != 1:
            torch.set_num_threads(1)

    def __exit__(self, *exc: object) -> None:
        if self.n != 1:
            torch.set_num_threads(self.n)


#: public name of the single-thread context (elementwise passes over the rows after a product)
one_thread = _one_thread


def to_half_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(float16 rows scaled by 2^-e, float32 2^e)`` of float rows ``x`` (N, dim):
    ``x ≈ h.float() * s[:, None]``; zero rows get ``s = 0``."""
    x = x.to(torch.float32)
    amax = x.abs().amax(dim=1) if x.shape[1] else torch.zeros(x.shape[0], device=x.device)
    _, e = torch.frexp(amax)                               # amax = f·2^e, f in [0.5, 1)
    scale = torch.ldexp(torch.ones_like(amax), e)          # 2^e >= amax (exact power of two)
    scale = torch.where(amax > 0, scale, torch.zeros_like(scale))
    inv = torch.where(scale > 0, 1.0 / scale.clamp_min(torch.finfo(torch.float32).tiny), scale)
    return (x * inv[:, None]).to(torch.float16), scale


class HalfFeatures:
    """Prepared features of a space without a language head, over the float16 copy: the
    cosine of a query is ``(H·(Vᵀq̂))·a + (q̂ᵀm)·b`` with ``H`` the scaled float16 rows,
    ``a = 2^e/|x|`` and ``b = 1/|x|`` per row (float32; ``x = V·y + m`` the decompressed
    feature; without PCA ``V = I``, ``m = 0``). Same interface as
    :class:`common.feature_space.PreparedFeatures` (``len``, :meth:`similarity`)."""

    def __init__(self, space: FeatureSpace, device: str | torch.device, half: torch.Tensor, a: torch.Tensor,
                 b: torch.Tensor, cache: _ScoreCache | None = None) -> None:
        self.space, self.device, self.n = space, torch.device(device), int(half.shape[0])
        self._h, self._a, self._b = half, a, b
        self._cache = cache

    def __len__(self) -> int:
        return self.n

    def subset(self, rows: torch.Tensor) -> HalfFeatures:
        """The prepared features of rows ``rows`` (int64 indices) only: a row scores the same
        as in the whole (the product of a row does not depend on the others)."""
        r = rows.to(self.device)
        return HalfFeatures(self.space, self.device, self._h.index_select(0, r), self._a.index_select(0, r),
                            self._b.index_select(0, r))

    def _one(self, qn: torch.Tensor, qm: torch.Tensor | None) -> torch.Tensor:
        """(N,) float32 cosine of one projected query ``qn`` (dim,) (``qm`` its mean term)."""
        small = self.n * self._h.shape[1] <= PARALLEL_MIN_ELEMENTS
        if kernels.half_scores_enabled(self._h):       # float32 sums at memory speed (C++)
            return kernels.half_scores(self._h, qn, self._a, None if qm is None else self._b,
                                       0.0 if qm is None else float(qm), 1 if small else torch.get_num_threads())
        with (_one_thread() if small else contextlib.nullcontext()):
            out = torch.mv(self._h, qn.to(torch.float16))
        with _one_thread():
            out = torch.mul(out, self._a)               # float16 · float32 -> float32, one pass
            if qm is not None:
                out.add_(self._b, alpha=float(qm))
        return out

    @torch.inference_mode()
    def similarity(self, queries: np.ndarray | torch.Tensor, use_cache: bool = True) -> torch.Tensor:
        """``(Q, N)`` float32 cosine (within :data:`SCORE_ATOL` of the exact one). On CPU each
        query is one pass over the float16 copy (the C++ :func:`~semantic_map.kernels.half_scores`,
        else torch's float16 matrix-vector product: a float16 matrix product with Q > 1 has no
        fast path, and converting the rows to float32 costs more than Q passes), so a row's
        score does not depend on the other queries.
        With the snapshot's score cache (``use_cache``) a query scored on an earlier version
        of the copy costs the rows changed since: the result is the same."""
        with _one_thread():                     # a (Q, lang_dim) · (lang_dim, dim) product
            qn, qm = self.space.project_queries(queries, self.device)
        nq = qn.shape[0]
        if self.n == 0:
            return torch.zeros((nq, 0), dtype=torch.float32, device=self.device)
        if self.device.type != "cpu" and nq > 1:
            out = (self._h @ qn.to(torch.float16).T).to(torch.float32).T.contiguous()
            out *= self._a
            if qm is not None:
                out.addcmul_(qm[:, None].expand(nq, self.n), self._b.expand(nq, self.n))
            return out
        if nq == 1:
            return self._cached(qn[0], None if qm is None else qm[0], use_cache)[None]
        out = torch.empty((nq, self.n), dtype=torch.float32, device=self.device)
        for i in range(nq):
            out[i] = self._cached(qn[i], None if qm is None else qm[i], use_cache)
        return out

    def _cached(self, qn: torch.Tensor, qm: torch.Tensor | None, use_cache: bool) -> torch.Tensor:
        """:meth:`_one` through the score cache: a query scored before is updated for the rows
        changed since (the same per-row product), else scored in full and kept."""
        c = self._cache
        if c is None or not use_cache:
            return self._one(qn, qm)
        key = qn.detach().cpu().numpy().tobytes() + (b"" if qm is None else qm.detach().cpu().numpy().tobytes())
        e = c.entries.get(key)
        if e is None:
            out = self._one(qn, qm)
            c.put(key, out, self.n)
            return out
        c.entries.move_to_end(key)
        if e.rows or e.n != self.n:
            rows = torch.unique(torch.cat(e.rows)) if e.rows else torch.empty(0, dtype=torch.int64)
            rows = rows[rows < self.n].to(self.device)
            e.rows = []
            if e.values.shape[0] < self.n:
                grown = torch.zeros(self.n + self.n // 4, dtype=torch.float32, device=self.device)
                grown[: e.values.shape[0]] = e.values
                e.values = grown
            if rows.numel():
                e.values.index_copy_(0, rows, self.subset(rows)._one(qn, qm))
            e.n = self.n
        return e.values[: self.n].clone()


@dataclass
class _PreparedSpace:
    """What :meth:`QueryCopy.prepared` keeps per (feature space, device)."""

    kind: str                                       # "half" (no head), "raw" or "head" (language head)
    v: HalfFeatures | PreparedFeatures              # prepared voxel features
    aux: torch.Tensor | None = None                 # per-row terms, capacity rows ("half": a, "head": rows)
    aux2: torch.Tensor | None = None                # "half": b
    rows: list[torch.Tensor] = field(default_factory=list)   # rows the syncs changed since the last query
    rays: PreparedFeatures | None = None            # prepared ray features (None: rebuild)
    lse: OrderedDict = field(default_factory=OrderedDict)   # phrase set -> _RowValues (kind "half")
    scores: _ScoreCache | None = None               # recent queries' scores (kind "half")


@dataclass
class _RowValues:
    """One float32 value per voxel row (a cached query's scores, a phrase set's log-sum-exp),
    kept up to date for the rows the syncs change."""

    values: torch.Tensor                            # (capacity,) float32, rows < n valid
    n: int                                          # rows it covers
    rows: list[torch.Tensor] = field(default_factory=list)   # rows changed since it was brought up to date


class _ScoreCache:
    """The scores of the last queries of one prepared space (:class:`HalfFeatures`), by
    projected query: at most :data:`SCORE_CACHE_ENTRIES`, and at most a quarter of the
    float16 copy's bytes (at least :data:`SCORE_CACHE_MIN_BYTES`); least recently used first out."""

    def __init__(self, copy_bytes: int) -> None:
        self.entries: OrderedDict[bytes, _RowValues] = OrderedDict()
        self.max_bytes = max(SCORE_CACHE_MIN_BYTES, copy_bytes // 4)

    def changed(self, rows: torch.Tensor) -> None:
        for c in self.entries.values():
            c.rows.append(rows)

    def put(self, key: bytes, scores: torch.Tensor, n: int) -> None:
        """Keep a copy of ``scores`` (n,) for ``key``, evicting the least recently used first
        (the copy goes into an evicted entry's buffer when one is big enough: no new pages)."""
        need = scores.numel() * 4
        if need > self.max_bytes:
            return
        buf = None
        while self.entries and (len(self.entries) >= SCORE_CACHE_ENTRIES
                                or sum(c.values.numel() * 4 for c in self.entries.values()) + need > self.max_bytes):
            _, old = self.entries.popitem(last=False)
            if buf is None and old.values.numel() >= scores.numel() and old.values.device == scores.device:
                buf = old.values
        if buf is None:
            buf = torch.empty_like(scores)
        buf[: scores.numel()].copy_(scores)
        self.entries[key] = _RowValues(buf, n)


class QueryCopy:
    """A consistent copy of what a query reads from the map, maintained *incrementally*.

    :meth:`sync` (the caller holds the map lock) copies only the voxel rows the map wrote or
    moved since the previous sync (``SemanticVoxels.take_changes``; everything on the first
    sync, after a reload or when the journal overflowed) into float16 feature rows (scaled
    by a power of two per row, :func:`to_half_rows`) and int64 key buffers reused across map
    versions, plus the rays (small). The query-independent terms (:meth:`prepared`: per-row
    inverse norms, or the cached language-space rows of a space with a language head, see
    ``FeatureSpace.prepare``) are likewise updated for the changed rows only, outside the
    lock. So the first query after a map change costs about what a later one does, and the
    lock is held for O(changed rows), not O(N·dim).

    A query that cannot get the map lock within ``query.lock_timeout_s`` reads this copy as
    it is: the last consistent state (``gen`` / ``frames_mapped`` say which).

    Memory: ``2·dim·N`` bytes (+25 % headroom for a growing map) for the features, ``4·N``
    for the row scales, ``8·N`` for the keys, ``8·N`` for the prepared terms of a space
    without a head. :meth:`reserve` grows the buffers (copying their content) before the lock
    is taken, so the lock is held for the changed rows only.

    Not thread-safe: the caller serialises queries (``query_lock``). :meth:`take` is the
    one-off full copy (no journal), for a map used once.
    """

    def __init__(self) -> None:
        self.gen = -1
        self.frames_mapped = 0
        self.vox = 1.0
        self.half_angle = 45.0
        self.n_voxels = 0
        self._vhalf = torch.empty((0, 0), dtype=torch.float16)   # scaled float16 rows (capacity >= n)
        self._vscale = torch.empty(0)                               # their 2^e
        self._vkeys = torch.empty(0, dtype=torch.int64)
        self.ray_feats = torch.empty(0)
        self.ray_origins = np.zeros((0, 3), np.float32)
        self.ray_dirs = np.zeros((0, 3), np.float32)
        self._prep: dict[tuple[str, str], _PreparedSpace] = {}   # (space id, device) -> prepared state
        self._sem: SemanticVoxels | None = None   # the SemanticVoxels the copy follows
        self.take_ms = 0.0
        self.changed_rows = 0                 # rows copied by the last sync (-1: everything)
        self.revision = 0                     # +1 per sync / take: what was computed at one revision holds

    @staticmethod
    def _grow(buf: torch.Tensor, n: int, tail: tuple[int, ...], dtype: torch.dtype, device: torch.device,
              keep: int) -> torch.Tensor:
        """``buf`` if it holds ``n`` rows of that kind, else a bigger one with its first ``keep`` rows."""
        if (buf.dtype == dtype and buf.device == device and tuple(buf.shape[1:]) == tail
                and buf.shape[0] >= n):
            return buf
        new = torch.zeros((max(n + n // 4, 1024), *tail), dtype=dtype, device=device)
        if keep and tuple(buf.shape[1:]) == tail and buf.dtype == dtype:
            k = min(keep, buf.shape[0])
            new[:k].copy_(buf[:k])
        return new

    def _fit(self, sem: SemanticVoxels, n: int, keep: int) -> None:
        dev = sem.keys.device
        self._vhalf = self._grow(self._vhalf, n, (int(sem.dim),), torch.float16, dev, keep)
        self._vscale = self._grow(self._vscale, n, (), torch.float32, dev, keep)
        self._vkeys = self._grow(self._vkeys, n, (), torch.int64, dev, keep)

    def _copy_all(self, sem: SemanticVoxels, n: int, block: int = 65536) -> None:
        feat = sem.feat
        for s in range(0, n, block):
            e = min(n, s + block)
            h, sc = to_half_rows(feat[s:e])
            self._vhalf[s:e].copy_(h)
            self._vscale[s:e].copy_(sc)
        self._vkeys[:n].copy_(sem.keys)

    def reserve(self, m: RayFrontsMap) -> QueryCopy:
        """Grow the buffers for map ``m``'s current size ahead of :meth:`sync` (no lock
        needed: a size hint; the copy's content is kept)."""
        sem = m.sem
        if sem is self._sem:
            self._fit(sem, len(sem), self.n_voxels)
        return self

    def sync(self, m: RayFrontsMap, gen: int, frames_mapped: int = 0) -> QueryCopy:
        """Bring the copy up to map ``m`` (the caller holds the map lock): changed rows only."""
        with _one_thread():
            return self._sync(m, gen, frames_mapped)

    def _sync(self, m: RayFrontsMap, gen: int, frames_mapped: int) -> QueryCopy:
        t = time.perf_counter()
        sem = m.sem
        n = len(sem)
        rows = sem.take_changes(self) if sem is self._sem else None
        if rows is None:
            sem.take_changes(self)           # this copy now owns the journal
            self._fit(sem, n, 0)
            self._copy_all(sem, n)
            self._prep = {}
            self.changed_rows = -1
        else:
            self._fit(sem, n, min(self.n_voxels, n))
            if rows.numel():
                h, sc = to_half_rows(sem.feat.index_select(0, rows))
                self._vhalf.index_copy_(0, rows, h)
                self._vscale.index_copy_(0, rows, sc)
                self._vkeys.index_copy_(0, rows, sem.keys.index_select(0, rows))
            for st in self._prep.values():
                st.rows.append(rows)
            self.changed_rows = int(rows.numel())
        self._sem = sem
        self.n_voxels = n
        self.revision += 1
        self._copy_rest(m, gen, frames_mapped)
        self.take_ms = (time.perf_counter() - t) * 1e3
        return self

    def take(self, m: RayFrontsMap, gen: int, frames_mapped: int = 0) -> QueryCopy:
        """A full copy of the map's query arrays (the caller holds the map lock), without
        touching the map's change journal (for a map queried once)."""
        t = time.perf_counter()
        sem = m.sem
        n = self.n_voxels = len(sem)
        self._fit(sem, n, 0)
        self._copy_all(sem, n)
        self._prep = {}
        self._sem = None
        self.changed_rows = -1
        self.revision += 1
        self._copy_rest(m, gen, frames_mapped)
        self.take_ms = (time.perf_counter() - t) * 1e3
        return self

    def _copy_rest(self, m: RayFrontsMap, gen: int, frames_mapped: int) -> None:
        self.vox = float(m.cfg.vox_size)
        rs = m.ray_store
        self.ray_feats = rs.feat   # a fresh copy
        self.ray_origins = _np(rs.origins()).astype(np.float32).reshape(-1, 3)
        self.ray_dirs = _np(rs.directions()).astype(np.float32).reshape(-1, 3)
        self.half_angle = float(m.cone_half_angle())
        self.gen, self.frames_mapped = gen, frames_mapped
        for st in self._prep.values():
            st.rays = None

    def feats_of(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """float32 voxel features (of ``rows``, else all) as the copy holds them."""
        if rows is None:
            h, s = self._vhalf[: self.n_voxels], self._vscale[: self.n_voxels]
        else:
            h, s = self._vhalf.index_select(0, rows), self._vscale.index_select(0, rows)
        return h.to(torch.float32) * s[:, None]

    @property
    def voxel_feats(self) -> torch.Tensor:
        """(N, dim) float32 features of the copy (materialised: ``4·dim·N`` bytes)."""
        return self.feats_of()

    def voxel_xyz(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), 3) float32 voxel centres of snapshot rows."""
        from common.conventions import voxel_center
        from semantic_map import cell_keys

        k = self._vkeys[: self.n_voxels][torch.as_tensor(np.asarray(rows, np.int64))]
        return _np(voxel_center(cell_keys.unpack(k), self.vox)).astype(np.float32, copy=False).reshape(-1, 3)

    def voxel_keys(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),) int64 packed voxel keys of snapshot rows (:mod:`semantic_map.cell_keys`)."""
        r = torch.as_tensor(np.asarray(rows, np.int64))
        return _np(self._vkeys[: self.n_voxels].index_select(0, r.to(self._vkeys.device))).astype(np.int64, copy=False)

    def voxel_ijk(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), 3) int64 voxel indices of snapshot rows (unpacked from their keys:
        ``voxel_index(voxel_xyz(rows))`` without the round trip through the centres)."""
        from semantic_map import cell_keys

        k = self.voxel_keys(rows)
        out = np.empty((len(k), 3), np.int64)
        b = cell_keys.BITS
        np.right_shift(k, 2 * b, out=out[:, 0])
        np.right_shift(k, b, out=out[:, 1])
        out[:, 2] = k
        out &= cell_keys.MASK
        out -= cell_keys.OFFSET
        return out

    # ------------------------------------------------------------ prepared terms
    def _half_terms(self, fs: FeatureSpace, rows: torch.Tensor | None,
                    device: str | torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """``(a, b)`` of :class:`HalfFeatures` for ``rows`` (else all), in blocks."""
        idx = torch.arange(self.n_voxels) if rows is None else rows
        a = torch.empty(len(idx), dtype=torch.float32)
        b = torch.empty(len(idx), dtype=torch.float32)
        for s in range(0, len(idx), 65536):
            r = idx[s:s + 65536]
            prep = fs.prepare(self.feats_of(r), device=device)
            assert prep._inv is not None  # the inverse norms of a space without a language head
            inv = prep._inv.to(torch.float32).cpu()
            b[s:s + len(r)] = inv
            a[s:s + len(r)] = inv * self._vscale.index_select(0, r).cpu()
        return a, b

    def prepared(self, fs: FeatureSpace, device: str | torch.device = "cpu"
                 ) -> tuple[HalfFeatures | PreparedFeatures, PreparedFeatures]:
        """``(voxels, rays)`` prepared features for space ``fs``: built in full once per copy,
        then updated for the rows each :meth:`sync` changed. A space without a language head
        scores the float16 copy (:class:`HalfFeatures`); one with a head caches its
        language-space rows (``FeatureSpace.prepare``)."""
        key = (fs.id, str(device))
        dev = torch.device(device)
        n = self.n_voxels
        st = self._prep.get(key)
        if st is None:
            with _one_thread():
                st = self._prep[key] = self._build_prepared(fs, n, dev, device)
        elif st.rows or st.v.n != n:
            with _one_thread():
                self._update_prepared(fs, st, n, dev, device)
        if st.rays is None:
            st.rays = fs.prepare(self.ray_feats, device=device)
        return st.v, st.rays

    def _capacity(self) -> int:
        return max(self._vhalf.shape[0], 1)

    def _build_prepared(self, fs: FeatureSpace, n: int, dev: torch.device,
                        device: str | torch.device) -> _PreparedSpace:
        from common.feature_space import PreparedFeatures

        if fs.head_config is None:
            a, b = self._half_terms(fs, None, device)
            aux = torch.zeros(self._capacity(), dtype=torch.float32, device=dev)
            aux2 = torch.zeros(self._capacity(), dtype=torch.float32, device=dev)
            aux[:n], aux2[:n] = a.to(dev), b.to(dev)
            cache = _ScoreCache(self._vhalf.numel() * 2)
            return _PreparedSpace("half", HalfFeatures(fs, dev, self._vhalf[:n].to(dev), aux[:n], aux2[:n], cache),
                                  aux, aux2, scores=cache)
        v = fs.prepare(self.voxel_feats, device=device)
        if v._y is None:
            return _PreparedSpace("raw", v)
        aux = torch.zeros((self._capacity(), v._y.shape[1]), dtype=torch.float32, device=dev)
        aux[:n] = v._y
        return _PreparedSpace("head", PreparedFeatures(fs, dev, n, aux[:n], None, None), aux)

    @staticmethod
    def _grown(aux: torch.Tensor, cap: int, dev: torch.device) -> torch.Tensor:
        new = torch.zeros((cap, *aux.shape[1:]), dtype=aux.dtype, device=dev)
        new[: aux.shape[0]] = aux
        return new

    def _update_prepared(self, fs: FeatureSpace, st: _PreparedSpace, n: int, dev: torch.device,
                         device: str | torch.device) -> None:
        """The prepared terms of the rows the syncs since the last query changed."""
        from common.feature_space import PreparedFeatures

        rows = torch.unique(torch.cat(st.rows)) if st.rows else torch.empty(0, dtype=torch.int64)
        rows = rows[rows < n]
        st.rows = []
        kind = st.kind
        if kind == "raw":
            st.v = PreparedFeatures(fs, dev, n, None, None, None, raw=self.voxel_feats)
            return
        assert st.aux is not None  # "half" and "head" keep per-row terms
        if st.aux.shape[0] < n:
            st.aux = self._grown(st.aux, self._capacity(), dev)
            if st.aux2 is not None:
                st.aux2 = self._grown(st.aux2, self._capacity(), dev)
        if kind == "half":
            assert st.aux2 is not None
            if rows.numel():
                a, b = self._half_terms(fs, rows, device)
                r = rows.to(dev)
                st.aux.index_copy_(0, r, a.to(dev))
                st.aux2.index_copy_(0, r, b.to(dev))
                for c in st.lse.values():
                    c.rows.append(rows)
                if st.scores is not None:
                    st.scores.changed(rows)
            st.v = HalfFeatures(fs, dev, self._vhalf[:n].to(dev), st.aux[:n], st.aux2[:n], st.scores)
            return
        if rows.numel():
            sub = fs.prepare(self.feats_of(rows), device=device)
            # the language-space rows a space with a head caches (a batch too large to cache
            # leaves them None, which index_copy_ rejects, as before)
            st.aux.index_copy_(0, rows.to(dev), cast(torch.Tensor, sub._y))
        st.v = PreparedFeatures(fs, dev, n, st.aux[:n], None, None)

    # ------------------------------------------------------------ per-row log-sum-exp
    @torch.inference_mode()
    def phrase_logsumexp(self, fs: FeatureSpace, phrases: torch.Tensor, temperature: float,
                         device: str | torch.device = "cpu") -> torch.Tensor | None:
        """``(N,)`` float32 ``log Σ_j exp(temperature · score_j)`` per voxel row over the phrase
        embeddings ``phrases`` (B, lang_dim), ``score_j`` the copy's cosine
        (:meth:`HalfFeatures.similarity`, one product per phrase); None for a space with a
        language head (no float16 copy) or an empty set.

        Kept per phrase set (the :data:`LSE_SETS` last used per space) and, like the
        prepared terms, brought up to date for the rows each :meth:`sync` changed: a search
        against a standing background costs the products of its targets only. A row's value
        comes from the same per-row computation in the full pass and in an update."""
        if phrases.shape[0] == 0:
            return None
        v, _ = self.prepared(fs, device)
        st = self._prep[(fs.id, str(device))]
        if st.kind != "half" or not isinstance(v, HalfFeatures):
            return None
        q = phrases.detach().to(torch.float32).cpu().contiguous()
        key = (hashlib.sha1(q.numpy().tobytes()).hexdigest(), tuple(q.shape), float(temperature))
        n = v.n
        c = st.lse.get(key)
        if c is None:
            vals = torch.zeros(self._capacity(), dtype=torch.float32, device=v.device)
            vals[:n] = self._lse(v, q, temperature)
            c = st.lse[key] = _RowValues(vals, n)
            while len(st.lse) > LSE_SETS:
                st.lse.popitem(last=False)
        else:
            st.lse.move_to_end(key)
            if c.rows or c.n != n:
                rows = torch.unique(torch.cat(c.rows)) if c.rows else torch.empty(0, dtype=torch.int64)
                rows = rows[rows < n]
                c.rows = []
                if c.values.shape[0] < n:
                    c.values = self._grown(c.values, self._capacity(), v.device)
                if rows.numel():
                    c.values.index_copy_(0, rows.to(v.device), self._lse(v.subset(rows), q, temperature))
                c.n = n
        return c.values[:n]

    @staticmethod
    def _lse(v: HalfFeatures, q: torch.Tensor, temperature: float) -> torch.Tensor:
        s = v.similarity(q, use_cache=False)
        with _one_thread():
            s *= float(temperature)
            return torch.logsumexp(s, dim=0)
