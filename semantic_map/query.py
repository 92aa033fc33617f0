"""Open-vocabulary queries against the map's voxel and ray features.

* Similarity: cosine by default (both sides L2-normalised), or a caller-provided
  ``similarity(feats (N, C) float32, queries (Q, D)) -> (Q, N)`` (e.g. one that decompresses
  PCA features and applies a language head). Large maps are processed in chunks.
* ``softmax=True``: softmax across the queries of ``temperature * sim`` (CLIP's 100) per
  voxel/ray. With a single query this is identically 1; callers should add negatives.
* ``denoise=t`` (MaskCLIP+ prompt denoising): a query whose maximum value over the **whole**
  layer (all voxels, resp. all rays — not per chunk) is below ``t`` is disabled: its row is
  set to 0 and it predicts nothing.
* Labels: per voxel/ray the arg-max query, ``-1`` where the best value is below
  ``threshold`` (or every query is disabled).
* Top-k voxels and rays per query with positions and scores.

:func:`score_rows` (similarity, then the softmax across queries) is the one scoring step of
every query answer: the mapper's service (``mapper.query_answer``) and the evaluation (through
:meth:`RayFrontsMap.query`) both score through it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import torch

Similarity = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class PreparedRows(Protocol):
    """Feature rows prepared for scoring (``FeatureSpace.prepare``, the query copy's
    ``HalfFeatures``): they score queries themselves; ``len()`` is the row count."""

    def __len__(self) -> int: ...

    def similarity(self, queries: torch.Tensor) -> torch.Tensor:
        """(Q, N) float32 similarity of the (Q, D) ``queries`` to the rows."""
        ...


DEFAULT_CHUNK = 262144


def cosine(feats: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """(Q, N) cosine similarity of float feature rows and query rows."""
    q = torch.nn.functional.normalize(queries.to(torch.float32), dim=1)
    f = feats.to(torch.float32)
    n = torch.linalg.vector_norm(f, dim=1).clamp_min(1e-12)
    return (q @ f.T) / n


def similarity_matrix(feats: torch.Tensor, queries: torch.Tensor, similarity: Similarity | None = None,
                      chunk: int = DEFAULT_CHUNK) -> torch.Tensor:
    """(Q, N) similarities computed in chunks of ``chunk`` rows."""
    sim = similarity or cosine
    qn = queries.shape[0]
    n = feats.shape[0]
    out = torch.empty((qn, n), dtype=torch.float32, device=feats.device)
    for s in range(0, n, chunk):
        out[:, s:s + chunk] = sim(feats[s:s + chunk].to(torch.float32), queries).to(torch.float32)
    return out


def score_rows(feats: torch.Tensor | PreparedRows, queries: torch.Tensor, similarity: Similarity | None = None,
               softmax: bool = False, temperature: float = 100.0, chunk: int = DEFAULT_CHUNK) -> torch.Tensor:
    """``(Q, N)`` float32 scores of ``queries`` against feature rows ``feats``: the similarity
    (``similarity``, else :func:`cosine`; chunked by ``chunk`` rows when ``feats`` is a tensor;
    prepared features — anything with ``.similarity(queries)`` — score themselves), then with
    ``softmax`` the softmax across the queries of ``temperature · sim`` per row."""
    if isinstance(feats, torch.Tensor):
        sim = similarity_matrix(feats, queries, similarity, chunk)
    else:
        sim = feats.similarity(queries)
    if softmax and sim.numel():
        sim = torch.softmax(temperature * sim, dim=0)
    return sim


def softmax_share(scores: torch.Tensor, rest_lse: torch.Tensor | None, temperature: float = 100.0) -> torch.Tensor:
    """``(T, N)`` float32 softmax probabilities of the ``T`` rows of ``scores`` (T, N) over
    themselves and further rows summarised by their per-column log-sum-exp ``rest_lse``
    (N,) = ``log Σ_j exp(temperature · s_j)`` (None: no further rows): the first ``T`` rows
    of ``softmax(temperature · [scores; S_rest], dim=0)`` without the other rows' scores.
    Equal to that softmax up to float32 rounding (relative ~1e-5 at temperature 100)."""
    x = scores.to(torch.float32) * float(temperature)
    if x.numel() == 0:
        return x
    if rest_lse is None:
        return torch.softmax(x, dim=0)
    if x.shape[0] == 1:     # exp(x - logaddexp(x, lse)) = sigmoid(x - lse): two passes, not five
        x -= rest_lse.to(torch.float32)
        return x.sigmoid_()
    total = torch.logaddexp(torch.logsumexp(x, dim=0), rest_lse.to(torch.float32))
    x -= total
    return x.exp_()


@dataclass
class TopK:
    index: torch.Tensor   # (k,) rows into the layer
    score: torch.Tensor   # (k,)
    xyz: torch.Tensor     # (k, 3) voxel centres or ray origins
    direction: torch.Tensor | None = None  # (k, 3) rays only


@dataclass
class LayerScores:
    """Every voxel's and ray's score for each query, their labels and the top k (one call of
    :func:`run_query`)."""

    voxel_sim: torch.Tensor            # (Q, N)
    ray_sim: torch.Tensor              # (Q, R)
    voxel_labels: torch.Tensor         # (N,) int64, -1 = none
    ray_labels: torch.Tensor           # (R,) int64, -1 = none
    top_voxels: list[TopK] = field(default_factory=list)
    top_rays: list[TopK] = field(default_factory=list)
    voxel_disabled: torch.Tensor | None = None  # (Q,) bool (prompt denoising)
    ray_disabled: torch.Tensor | None = None


def _labels(sim: torch.Tensor, denoise, threshold):
    disabled = torch.zeros(sim.shape[0], dtype=torch.bool, device=sim.device)
    if denoise is not None and sim.shape[1]:
        disabled = sim.max(dim=1).values < denoise
        sim = sim.masked_fill(disabled[:, None], 0.0)
    if sim.shape[1] == 0 or sim.shape[0] == 0:
        return sim, torch.full((sim.shape[1],), -1, dtype=torch.int64, device=sim.device), disabled
    best, lab = sim.max(dim=0)
    bad = disabled[lab]
    if threshold is not None:
        bad |= best < threshold
    lab = torch.where(bad, torch.full_like(lab, -1), lab)
    return sim, lab, disabled


def _topk(sim: torch.Tensor, k: int, xyz: torch.Tensor, dirs: torch.Tensor | None) -> list[TopK]:
    out = []
    kk = min(k, sim.shape[1])
    if kk <= 0:
        e = torch.empty(0, dtype=torch.int64)
        return [TopK(e, torch.empty(0), torch.empty((0, 3)), None if dirs is None else torch.empty((0, 3)))
                for _ in range(sim.shape[0])]
    sc, ix = torch.topk(sim, kk, dim=1)
    for q in range(sim.shape[0]):
        out.append(TopK(ix[q], sc[q], xyz[ix[q]], None if dirs is None else dirs[ix[q]]))
    return out


def run_query(queries: torch.Tensor, voxel_feats: torch.Tensor, voxel_xyz: torch.Tensor,
              ray_feats: torch.Tensor, ray_origins: torch.Tensor, ray_dirs: torch.Tensor, *,
              similarity: Similarity | None = None, softmax: bool = False, temperature: float = 100.0,
              top_k: int = 10, denoise: float | None = None, threshold: float | None = None,
              chunk: int = DEFAULT_CHUNK) -> LayerScores:
    """Query both layers (see module docstring). ``queries`` (Q, D) float."""
    q = torch.as_tensor(queries)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2 or q.shape[0] == 0:
        raise ValueError(f"queries must be a non-empty (Q, D) array, got shape {tuple(q.shape)}")
    q = q.to(torch.float32).to(voxel_feats.device)
    if similarity is None and q.shape[1] != voxel_feats.shape[1]:
        raise ValueError(f"query dim {q.shape[1]} != map feature dim {voxel_feats.shape[1]}; "
                         "pass a similarity callable that maps between the spaces")
    vs = score_rows(voxel_feats, q, similarity, softmax, temperature, chunk)
    rs = score_rows(ray_feats, q, similarity, softmax, temperature, chunk)
    vs, vl, vd = _labels(vs, denoise, threshold)
    rs, rl, rd = _labels(rs, denoise, threshold)
    return LayerScores(vs, rs, vl, rl, _topk(vs, top_k, voxel_xyz, None), _topk(rs, top_k, ray_origins, ray_dirs),
                       vd, rd)
