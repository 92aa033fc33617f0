"""The query's copy of the map (:class:`QuerySnapshot`), kept query-ready incrementally, and
its half-precision scoring (:class:`HalfFeatures`); split out of :mod:`mapper.query_answer`
(which re-exports the names).

Why half precision: at 5 M voxels × 100 dims a float32 copy is 2 GB and one text query is a
memory-bound matrix-vector product over all of it (~150–250 ms on the 2-core EPYC, at
~8–13 GB/s). The copy is therefore kept in **float16**, each row scaled by a power of two
(``2^-e``, ``e`` from the row's largest magnitude, so the scaled row lies in [-1, 1] and
neither overflows nor loses range; the scaling is exact, so the copy is a deterministic
function of the map's row whatever the batch it was copied in). A query reads half the bytes.

Accuracy (stated tolerance, tested in ``tests/test_query_half.py`` against a float64
brute-force cosine): a score differs from the float64 cosine of the map's float32 feature
by at most ``SCORE_ATOL`` = 2e-3 (the float16 rounding of a row is ≤ 2^-11 of its largest
entry; the product accumulates in float32); the top-k set equals the float64 one except
for voxels whose reference score lies within ``2·SCORE_ATOL`` of the k-th best (near-ties).
Cosine terms that do not depend on the query (the inverse norms) are float32, from the
stored row.
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

import numpy as np
import torch

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace, PreparedFeatures
    from semantic_map.map import RayFrontsMap
    from semantic_map.semantic_voxels import SemanticVoxels

#: max |score − float64 cosine| of the half-precision copy (see the module docstring)
SCORE_ATOL = 2e-3
#: below this many feature elements a query's product runs on one thread (the parallel
#: region's hand-off costs more than it saves; on a loaded machine a descheduled OpenMP
#: worker stalls it), and the elementwise terms after it always do (one pass over N each)
PARALLEL_MIN_ELEMENTS = 1 << 25
#: rows converted to float32 per block when several queries are scored at once on CPU
#: (float16 matrix products with Q > 1 have no fast CPU kernel; the block stays in cache)
HALF_BLOCK_ROWS = 16384


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
                 b: torch.Tensor) -> None:
        self.space, self.device, self.n = space, torch.device(device), int(half.shape[0])
        self._h, self._a, self._b = half, a, b

    def __len__(self) -> int:
        return self.n

    @torch.inference_mode()
    def similarity(self, queries: np.ndarray | torch.Tensor) -> torch.Tensor:
        """``(Q, N)`` float32 cosine (within :data:`SCORE_ATOL` of the exact one)."""
        qn, qm = self.space.project_queries(queries, self.device)
        nq = qn.shape[0]
        if self.n == 0:
            return torch.zeros((nq, 0), dtype=torch.float32, device=self.device)
        h = self._h
        small = self.n * h.shape[1] <= PARALLEL_MIN_ELEMENTS
        if nq == 1:
            with (_one_thread() if small else contextlib.nullcontext()):
                out = torch.mv(h, qn[0].to(torch.float16))
            with _one_thread():
                out = out.to(torch.float32)[None]                                    # (1, N)
                out *= self._a
                if qm is not None:
                    out.addcmul_(qm[:, None].expand(nq, self.n), self._b.expand(nq, self.n))
            return out
        elif self.device.type != "cpu":
            out = (h @ qn.to(torch.float16).T).to(torch.float32).T.contiguous()
        else:
            out = torch.empty((self.n, nq), dtype=torch.float32)
            buf = torch.empty((min(self.n, HALF_BLOCK_ROWS), h.shape[1]), dtype=torch.float32)
            qt = qn.T.contiguous()
            for s in range(0, self.n, HALF_BLOCK_ROWS):
                e = min(self.n, s + HALF_BLOCK_ROWS)
                b = buf[: e - s]
                b.copy_(h[s:e])
                torch.mm(b, qt, out=out[s:e])
            out = out.T.contiguous()
        out *= self._a
        if qm is not None:
            out.addcmul_(qm[:, None].expand(nq, self.n), self._b.expand(nq, self.n))
        return out


@dataclass
class _PreparedSpace:
    """What :meth:`QuerySnapshot.prepared` keeps per (feature space, device)."""

    kind: str                                       # "half" (no head), "raw" or "head" (language head)
    v: HalfFeatures | PreparedFeatures              # prepared voxel features
    aux: torch.Tensor | None = None                 # per-row terms, capacity rows ("half": a, "head": rows)
    aux2: torch.Tensor | None = None                # "half": b
    rows: list[torch.Tensor] = field(default_factory=list)   # rows the syncs changed since the last query
    rays: PreparedFeatures | None = None            # prepared ray features (None: rebuild)


class QuerySnapshot:
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

    def reserve(self, m: RayFrontsMap) -> QuerySnapshot:
        """Grow the buffers for map ``m``'s current size ahead of :meth:`sync` (no lock
        needed: a size hint; the copy's content is kept)."""
        sem = m.sem
        if sem is self._sem:
            self._fit(sem, len(sem), self.n_voxels)
        return self

    def sync(self, m: RayFrontsMap, gen: int, frames_mapped: int = 0) -> QuerySnapshot:
        """Bring the copy up to map ``m`` (the caller holds the map lock): changed rows only."""
        with _one_thread():
            return self._sync(m, gen, frames_mapped)

    def _sync(self, m: RayFrontsMap, gen: int, frames_mapped: int) -> QuerySnapshot:
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
        self._copy_rest(m, gen, frames_mapped)
        self.take_ms = (time.perf_counter() - t) * 1e3
        return self

    def take(self, m: RayFrontsMap, gen: int, frames_mapped: int = 0) -> QuerySnapshot:
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
        self._copy_rest(m, gen, frames_mapped)
        self.take_ms = (time.perf_counter() - t) * 1e3
        return self

    def _copy_rest(self, m: RayFrontsMap, gen: int, frames_mapped: int) -> None:
        self.vox = float(m.cfg.vox_size)
        rs = m.ray_store
        self.ray_feats = rs.feat.clone()
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
            return _PreparedSpace("half", HalfFeatures(fs, dev, self._vhalf[:n].to(dev), aux[:n], aux2[:n]), aux, aux2)
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
            st.v = HalfFeatures(fs, dev, self._vhalf[:n].to(dev), st.aux[:n], st.aux2[:n])
            return
        if rows.numel():
            sub = fs.prepare(self.feats_of(rows), device=device)
            # the language-space rows a space with a head caches (a batch too large to cache
            # leaves them None, which index_copy_ rejects, as before)
            st.aux.index_copy_(0, rows.to(dev), cast(torch.Tensor, sub._y))
        st.v = PreparedFeatures(fs, dev, n, st.aux[:n], None, None)
