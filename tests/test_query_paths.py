"""The service and the evaluation answer a query through the same scoring function.

The mapper answers with :func:`mapper.query_answer.answer_snapshot` (over its float16 query
copy); the evaluation with :meth:`semantic_map.map.RayFrontsMap.query` (float32 map rows,
a caller's similarity). Both score through :func:`semantic_map.query.score_rows`; on one map,
with the same query and softmax set, they must give the same top voxels and rays with the
same scores (within the query copy's documented :data:`SCORE_ATOL`)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.messages import QueryRequest
from mapper import query_answer
from mapper.query_answer import SOFTMAX_TEMPERATURE, answer_snapshot
from semantic_map.query_copy import SCORE_ATOL, QueryCopy
from tests.support.data import query_map


def _eval_scores(m, fs, queries: torch.Tensor, softmax: bool, k: int):
    """The evaluation's path: RayFrontsMap.query with the feature space's similarity."""
    return m.query(queries, similarity=lambda f, q: fs.similarity(f, q), softmax=softmax,
                   temperature=SOFTMAX_TEMPERATURE, top_k=k)


@pytest.mark.parametrize("softmax", [False, True])
def test_service_and_evaluation_give_equal_answers(softmax):
    m, fs, cfg, X = query_map(seed=3)
    q = torch.from_numpy(np.asarray(X[11:14], np.float32))      # the query and two others
    k = 6
    standing = [QueryRequest(embedding=q[i].numpy(), id=f"s{i}") for i in (1, 2)]
    req = QueryRequest(embedding=q[0].numpy(), top_k=k, softmax=softmax, id="q")
    res = answer_snapshot(QueryCopy().take(m, 1), fs, req, cfg.query, standing=standing)
    ev = _eval_scores(m, fs, q if softmax else q[:1], softmax, k)
    tv, tr = ev.top_voxels[0], ev.top_rays[0]
    # the same scores, rank by rank (float16 copy vs float32 rows)
    np.testing.assert_allclose(res.voxel_score, tv.score.numpy(), atol=SCORE_ATOL)
    np.testing.assert_allclose(res.ray_score, tr.score.numpy(), atol=SCORE_ATOL)
    # the same voxels and rays where the scores are not within the tolerance of a tie
    checked = 0
    for full, got, want in ((ev.voxel_sim[0].numpy(), zip(res.voxel_xyz, res.voxel_score, strict=True), tv.xyz.numpy()),
                            (ev.ray_sim[0].numpy(), zip(res.ray_origin, res.ray_score, strict=True), tr.xyz.numpy())):
        for i, (xyz, s) in enumerate(got):
            if np.sum(np.abs(full - s) <= 2 * SCORE_ATOL) == 1:
                np.testing.assert_allclose(xyz, want[i], atol=1e-5)
                checked += 1
    assert checked >= (0 if softmax else 3)   # softmax at temperature 100 saturates: ties at 1.0
    if softmax:   # a softmax over three queries is not the cosine: the two paths differ from it
        assert not np.allclose(res.voxel_score, _eval_scores(m, fs, q[:1], False, k).top_voxels[0].score.numpy())


def test_service_scores_through_the_map_scoring_function(monkeypatch):
    """answer_snapshot reaches semantic_map.query.score_rows (replacing it changes the answer)."""
    m, fs, cfg, X = query_map(seed=4)
    req = QueryRequest(embedding=np.asarray(X[5], np.float32), top_k=3)
    snap = QueryCopy().take(m, 1)
    before = answer_snapshot(snap, fs, req, cfg.query)
    monkeypatch.setattr(query_answer, "score_rows", lambda *a, **kw: -torch.ones((1, len(a[0]))))
    after = answer_snapshot(snap, fs, req, cfg.query)
    assert np.all(after.voxel_score == -1) and not np.all(before.voxel_score == -1)
