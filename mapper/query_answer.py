"""Query answering, kept free of Zenoh and of the map's locking: embed the request in the
map's language space, score voxels and rays, take the top k, cluster the best voxels
(26-connected), measure the search volume of the best rays' cones (module map:
:mod:`mapper.state`; ARCHITECTURE.md).

Where to change a query's scoring: :func:`scores_for` (cosine / softmax at
:data:`SOFTMAX_TEMPERATURE` against the softmax set of :func:`softmax_set`),
:func:`answer_snapshot` (top k, clusters, search volume, timings), :class:`QueryCopy`
(what a query copies from the map). World frame, metres, z up.

Query defaults are the paper's (``query.*`` config keys):

* text: the mean of the 80 ImageNet/NACLIP prompt templates for language encoders
  (feature spaces with a language head or the SigLIP text model); raw text for the label
  encoder, whose features are raw name embeddings (``query.templates``);
* softmax set (``softmax=true`` requests): the query and the mapper's other standing queries,
  as the reference softmaxes over its whole query list (``query.softmax_set=queries``). With
  no other query the softmax of one is identically 1 — the reference's pitfall, kept on
  purpose; ``query.softmax_set=negatives`` compares against the phrases in
  ``query.softmax_negatives`` instead (our earlier behaviour, not the paper's).
"""
from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Iterable, Protocol, Sequence

import numpy as np
import numpy.typing as npt
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from common.cones import cone_union_volume
from common.conventions import voxel_center, voxel_index
from common.messages import MessageError, QueryRequest, QueryResult
from semantic_map.query import PreparedRows, score_rows
from semantic_map.query_copy import QueryCopy

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from encoders.text.base import CachedTextEncoder
    from semantic_map.map import RayFrontsMap


class QuerySettings(Protocol):
    """What answering reads of :class:`mapper.service_config.QuerySection` (a protocol, not an
    import: that module's imports lead back here); ``templates``, ``softmax_set``,
    ``softmax_negatives`` and ``image_model_dir`` are read with defaults when absent."""

    cluster_candidates: int
    cluster_rel_score: float
    search_rays: int
    search_range_m: float
    search_cell_m: float
    search_samples: int


#: generic phrases of ``query.softmax_set=negatives`` (relevancy-style; not the paper's default)
SOFTMAX_NEGATIVES = ("object", "things", "stuff", "texture")
SOFTMAX_TEMPERATURE = 100.0


def to_numpy(x: torch.Tensor | npt.ArrayLike) -> np.ndarray:
    """``x`` (a tensor on any device, or array-like) as a numpy array."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


_TEXT_ENCODERS: dict = {}
_TEXT_ENCODERS_LOCK = threading.Lock()   # one load per model, whoever asks first (query or warm-up)
TEXT_MODEL_LOADS: dict[str, dict] = {}   # model name -> {"thread": who loaded it, "load_s": seconds}


def text_encoder(name: str, device: str | torch.device = "cpu", model_dir: str = "") -> CachedTextEncoder:
    """The text model the feature space names (loaded once per process, thread-safe). A model
    missing on disk raises a one-line :class:`MessageError` naming ``text_model_dir``."""
    key = (name, str(device), model_dir)
    with _TEXT_ENCODERS_LOCK:
        if key not in _TEXT_ENCODERS:
            from common.model_files import ModelFileError
            from encoders.text import make_text_encoder

            t0 = time.perf_counter()
            try:
                _TEXT_ENCODERS[key] = make_text_encoder(name, model_dir=model_dir or None, device=device)
            except ModelFileError as e:     # bad setup, not a bug: one line naming what to set
                why = " ".join(str(e).split())
                raise MessageError(f"cannot embed text: the map's feature space needs the {name} text model on the "
                                   f"mapper ({why}); set text_model_dir=DIR (a directory 'rayfronts models' "
                                   f"prepared) and restart the mapper, or send embeddings (with background []) "
                                   "instead of text") from None
            TEXT_MODEL_LOADS[name] = {"thread": threading.current_thread().name,
                                      "load_s": round(time.perf_counter() - t0, 4)}
        return _TEXT_ENCODERS[key]


def warm_up_text(fs: FeatureSpace, phrases: list[str], device: str | torch.device = "cpu", model_dir: str = "",
                 templates: str = "auto") -> float:
    """Load the text model of ``fs`` and embed ``phrases`` (e.g. the search background) so the
    first query after start-up does not wait for them. Returns the seconds it took."""
    t0 = time.perf_counter()
    for p in phrases:
        embed_text(fs, p, device, model_dir, templates)
    if not phrases:
        text_encoder(fs.text_model, device, model_dir)
    return time.perf_counter() - t0


def query_templates(fs: FeatureSpace, setting: str = "auto") -> str:
    """Prompt templates of text queries in space ``fs``: ``setting``, or for "auto" the 80
    ImageNet/NACLIP templates ("imagenet80") for language encoders, raw text ("none") else."""
    if setting != "auto":
        return setting
    return "imagenet80" if (fs.head_config is not None or fs.text_model == "siglip") else "none"


_TEXT_CACHE: dict = {}
_TEXT_CACHE_MAX = 256


def embed_text(fs: FeatureSpace, text: str, device: str | torch.device = "cpu", model_dir: str = "",
               templates: str = "auto") -> torch.Tensor:
    """(1, lang_dim) embedding of one query text (cached: 80 templates cost 80 text passes)."""
    tl = query_templates(fs, templates)
    key = (fs.id, fs.text_model, text, tl, str(device), model_dir)
    if key not in _TEXT_CACHE:
        if len(_TEXT_CACHE) >= _TEXT_CACHE_MAX:
            _TEXT_CACHE.pop(next(iter(_TEXT_CACHE)))
        _TEXT_CACHE[key] = fs.embed_queries([text], text_encoder(fs.text_model, device, model_dir),
                                            templates=tl).reshape(1, -1)
    return _TEXT_CACHE[key]


def embed_request(fs: FeatureSpace, req: QueryRequest, device: str | torch.device = "cpu", model_dir: str = "",
                  templates: str = "auto", image_model_dir: str = "") -> torch.Tensor:
    """(1, lang_dim) query vector in the feature space's language space (text: see
    :func:`query_templates`; image: :mod:`mapper.image_query`)."""
    if req.embedding is not None:
        e = torch.as_tensor(np.asarray(req.embedding, np.float32))
        if e.shape[-1] != fs.lang_dim:
            raise MessageError(f"embedding has {e.shape[-1]} dims, the map's language space has {fs.lang_dim}")
        return e.reshape(1, -1)
    if req.image is not None:
        from mapper.image_query import embed_image

        return embed_image(fs, req.image, device, model_dir, image_model_dir, text_encoder)
    assert req.text is not None         # a validated request has exactly one of the three
    return embed_text(fs, req.text, device, model_dir, templates)


def scores_for(fs: FeatureSpace, feats: torch.Tensor | PreparedRows, q: torch.Tensor, softmax: bool,
               negatives: torch.Tensor | None, device: str | torch.device = "cpu") -> np.ndarray:
    """(N,) float32 score of query ``q`` per feature row: cosine, or with ``softmax`` its
    softmax(100·cos) share against ``negatives``. ``feats`` raw ``(N, dim)``, a
    :class:`common.feature_space.PreparedFeatures` or a :class:`HalfFeatures` (the query
    copy's float16 rows: within :data:`SCORE_ATOL` of the float32 cosine)."""
    if len(feats) == 0:
        return np.zeros((0,), np.float32)
    qs = torch.cat([q, negatives]) if softmax and negatives is not None else q
    sim = score_rows(feats, qs, lambda f, qq: fs.similarity(f, qq, device=device), softmax, SOFTMAX_TEMPERATURE,
                     chunk=len(feats))
    return to_numpy(sim[0]).astype(np.float32, copy=False)


def top_stable(s: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` largest values of ``s``, best first, ties by lower index —
    exactly ``np.argsort(-s, kind="stable")[:k]`` (NaN ranks last), in O(N + m log m).

    A strided sample of ``s`` gives a threshold that about ``2k`` values reach; one pass
    collects those (``s >= thr``), a partition of the few finds the k-th largest among them
    — exact, as every value above the k-th largest is in the set once the set holds ``k``
    values (else a full partition of ``s``). Then a stable sort of the m >= k values not
    below the k-th largest."""
    n = len(s)
    k = min(int(k), n)
    if k <= 0:
        return np.zeros((0,), np.int64)
    if np.isnan(s).any():
        s = np.where(np.isnan(s), -np.inf, s)
    if k >= n or n <= 4096:
        return np.argsort(-s, kind="stable")[:k]
    c = None
    stride = 32
    if n >= 64 * k:
        sample = s[::stride]
        ks = min(len(sample), 2 * (k // stride + 1) + 16)
        thr = np.partition(sample, len(sample) - ks)[len(sample) - ks]
        c = np.flatnonzero(s >= thr)
        if len(c) < k:
            c = None
    if c is None:
        kth = np.partition(s, n - k)[n - k]
    else:
        vals = s[c]
        kth = np.partition(vals, len(vals) - k)[len(vals) - k]
    cand = np.flatnonzero(s >= kth) if c is None else c[s[c] >= kth]   # ascending: ties keep index order
    return cand[np.argsort(-s[cand], kind="stable")[:k]]


_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                        if (i, j, k) > (0, 0, 0)], np.int64)  # 13 half-space offsets


def cluster_voxels(ijk: np.ndarray) -> np.ndarray:
    """26-connected components of a set of voxel indices → (M,) component label per voxel."""
    m = len(ijk)
    if m == 0:
        return np.zeros((0,), np.int64)
    base = ijk.min(0) - 1
    span = ijk.max(0) - base + 2
    def pack(a):
        a = a - base
        return (a[:, 0] * span[1] + a[:, 1]) * span[2] + a[:, 2]
    keys = pack(ijk)
    order = np.argsort(keys)
    sk = keys[order]
    rows, cols = [], []
    for off in _NEIGHBOURS:
        nk = pack(ijk + off)
        pos = np.clip(np.searchsorted(sk, nk), 0, m - 1)
        hit = sk[pos] == nk
        rows.append(np.nonzero(hit)[0])
        cols.append(order[pos[hit]])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(m, m))
    _, labels = connected_components(g, directed=False)
    return labels.astype(np.int64)


_NEGATIVES: dict = {}


def softmax_negatives(fs: FeatureSpace, device: str | torch.device = "cpu", model_dir: str = "",
                      phrases: Sequence[str] = SOFTMAX_NEGATIVES, templates: str = "auto") -> torch.Tensor:
    """(len(phrases), lang_dim) embeddings of the negative phrases (cached per space and device)."""
    tl = query_templates(fs, templates)
    key = (fs.id, fs.text_model, str(device), model_dir, tuple(phrases), tl)
    if key not in _NEGATIVES:
        _NEGATIVES[key] = fs.embed_queries(list(phrases), text_encoder(fs.text_model, device, model_dir),
                                           templates=tl)
    return _NEGATIVES[key]


def softmax_set(fs: FeatureSpace, req: QueryRequest, qcfg: QuerySettings, standing: Iterable[QueryRequest] = (),
                device: str | torch.device = "cpu", model_dir: str = "") -> torch.Tensor | None:
    """Embeddings the query is softmaxed against (module docstring), or None (a set of one):
    ``qcfg.softmax_set`` "queries" = the other standing queries, "negatives" = the phrases
    ``qcfg.softmax_negatives``."""
    mode = getattr(qcfg, "softmax_set", "queries")
    tl = getattr(qcfg, "templates", "auto")
    if mode == "negatives":
        phrases = tuple(getattr(qcfg, "softmax_negatives", SOFTMAX_NEGATIVES))
        return softmax_negatives(fs, device, model_dir, phrases, tl) if phrases else None
    if mode != "queries":
        raise MessageError(f"query.softmax_set must be 'queries' or 'negatives', got {mode!r}")
    others = [r for r in standing if r.id != req.id and not r.cancel]
    if not others:
        return None
    return torch.cat([embed_request(fs, r, device, model_dir, tl, getattr(qcfg, "image_model_dir", ""))
                      for r in others])


def answer_query(m: RayFrontsMap, fs: FeatureSpace, req: QueryRequest, qcfg: QuerySettings,
                 device: str | torch.device = "cpu", model_dir: str = "") -> QueryResult:
    """Run ``req`` on map ``m`` (the caller holds its lock throughout): a one-off
    :class:`QueryCopy` + :func:`answer_snapshot`."""
    return answer_snapshot(QueryCopy().take(m, 0), fs, req, qcfg, device, model_dir)


def answer_snapshot(snap: QueryCopy, fs: FeatureSpace, req: QueryRequest, qcfg: QuerySettings,
                    device: str | torch.device = "cpu", model_dir: str = "",
                    standing: Iterable[QueryRequest] = ()) -> QueryResult:
    """Run ``req`` on a map snapshot: voxel clusters, top voxels, top rays, search volume.

    * top voxels/rays: the ``top_k`` best scores, ties by lower row (:func:`top_stable`);
    * clusters: among the ``max(cluster_candidates, top_k)`` best voxels, those scoring at
      least ``lo + cluster_rel_score·(hi − lo)`` (``lo`` the map's minimum, ``hi`` the best;
      only the best one if ``hi == lo``), grouped 26-connected; the ``top_k`` clusters with
      the best maximum score;
    * search volume: union of the cones of the ``search_rays`` best rays
      (:func:`cone_union_volume`, sampled, cost capped by ``search_samples``).
    ``standing``: the mapper's standing queries (the paper's softmax set, :func:`softmax_set`).
    Timings (ms): ``encode``, ``prepare`` (per snapshot; 0 when cached), ``similarity``,
    ``topk``, ``clusters``, ``search_volume``, ``postprocess`` (the last three together)."""
    timings: dict[str, float] = {}
    t = time.perf_counter()
    q = embed_request(fs, req, device, model_dir, getattr(qcfg, "templates", "auto"),
                      getattr(qcfg, "image_model_dir", ""))
    neg = softmax_set(fs, req, qcfg, standing, device, model_dir) if req.softmax else None
    timings["encode"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    vprep, rprep = snap.prepared(fs, device)
    timings["prepare"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    vs = scores_for(fs, vprep, q, req.softmax, neg, device)
    rs = scores_for(fs, rprep, q, req.softmax, neg, device)
    timings["similarity"] = (time.perf_counter() - t) * 1e3
    t0 = t = time.perf_counter()
    res = QueryResult(id=req.id, query=req.label)
    res.half_angle_deg = float(snap.half_angle)
    k = req.top_k
    if len(vs):
        cand = top_stable(vs, max(qcfg.cluster_candidates, k))
        top = cand[:k]
        lo, hi = float(vs.min()), float(vs[cand[0]])
        res.score_min = lo      # not on the wire: the shard info of the reply (client-side merge)
        timings["topk"] = (time.perf_counter() - t) * 1e3
        t = time.perf_counter()
        keep = cand[vs[cand] >= lo + qcfg.cluster_rel_score * (hi - lo)] if hi > lo else cand[:1]
        xyz = snap.voxel_xyz(np.concatenate([top, keep]))
        res.voxel_xyz, res.voxel_score = xyz[:len(top)], vs[top]
        # clusters: the best candidates (relative to the map's score range), 26-connected
        vox = snap.vox
        ijk = voxel_index(xyz[len(top):].astype(np.float64), vox)
        lab = cluster_voxels(ijk)
        n_cl = int(lab.max()) + 1 if len(lab) else 0
        best = np.full(n_cl, -np.inf, np.float32)
        np.maximum.at(best, lab, vs[keep])
        order = np.argsort(-best, kind="stable")[:k]
        # per cluster: centroid, size, bounding box (one pass over the kept voxels)
        centres = voxel_center(ijk, vox)
        size = np.bincount(lab, minlength=n_cl)
        csum = np.zeros((n_cl, 3))
        np.add.at(csum, lab, centres)
        cmin = np.full((n_cl, 3), np.inf)
        cmax = np.full((n_cl, 3), -np.inf)
        np.minimum.at(cmin, lab, centres)
        np.maximum.at(cmax, lab, centres)
        res.cluster_xyz = (csum[order] / size[order, None]).astype(np.float32).reshape(-1, 3)
        res.cluster_size = size[order].astype(np.int32)
        res.cluster_extent = (cmax[order] - cmin[order] + vox).astype(np.float32).reshape(-1, 3)
        res.cluster_score = best[order].astype(np.float32)
        timings["clusters"] = (time.perf_counter() - t) * 1e3
    if len(rs):
        t = time.perf_counter()
        top = top_stable(rs, k)
        o, d = snap.ray_origins, snap.ray_dirs
        res.ray_origin, res.ray_direction, res.ray_score = o[top], d[top], rs[top]
        ns = min(qcfg.search_rays, len(top))
        res.search_volume_m3 = cone_union_volume(o[top[:ns]], d[top[:ns]], snap.half_angle, qcfg.search_range_m,
                                                 qcfg.search_cell_m, max_cells=qcfg.search_samples)
        timings["search_volume"] = (time.perf_counter() - t) * 1e3
    timings["postprocess"] = (time.perf_counter() - t0) * 1e3
    res.timings = timings
    return res
