"""The query copy's float16 scoring against a float64 brute-force cosine, and the sampled
top-k against a full stable sort (semantic_map.query_copy, mapper.query_answer.top_stable)."""
import numpy as np
import pytest
import torch

from apps.bench.query import _space, build_map
from mapper.query_answer import top_stable
from semantic_map.query_copy import SCORE_ATOL, QueryCopy


def _reference(fs, feats: torch.Tensor, q: torch.Tensor) -> np.ndarray:
    """(Q, N) float64 cosine of the decompressed features x = V·y + m with queries q."""
    m, v = fs.pca.torch_basis("cpu", torch.float32)
    x = feats.double() @ v.double().T + m.double()
    xn = x / x.norm(dim=1, keepdim=True)
    qn = q.double() / q.double().norm(dim=1, keepdim=True)
    return (qn @ xn.T).numpy()


@pytest.mark.parametrize("n_queries", [1, 3])
def test_half_copy_scores_and_top_k_match_float64(n_queries):
    fs = _space(32)
    cfg, mp = build_map(60_000, 32, 200, fs, seed=5)
    with torch.no_grad():                                   # rows of very different magnitude
        mp.sem._feat[: len(mp.sem) // 3] *= 1e3
        mp.sem._feat[len(mp.sem) // 3: len(mp.sem) // 2] *= 1e-3
    snap = QueryCopy().take(mp, 0)
    vprep, _ = snap.prepared(fs)
    assert type(vprep).__name__ == "HalfFeatures" and snap._vhalf.dtype == torch.float16
    q = torch.randn((n_queries, fs.lang_dim), generator=torch.Generator().manual_seed(1))
    got = vprep.similarity(q).numpy()
    ref = _reference(fs, mp.sem.feat, q)
    err = np.abs(got - ref).max()
    assert err <= SCORE_ATOL, err
    assert err > 0                                           # it is float16: not bit-equal
    k = 50
    for i in range(n_queries):
        top = top_stable(got[i].astype(np.float32), k)
        order = np.argsort(-ref[i])
        kth = ref[i][order[k - 1]]
        sure = set(np.flatnonzero(ref[i] > kth + 2 * SCORE_ATOL))   # must be in the top k
        maybe = set(np.flatnonzero(ref[i] >= kth - 2 * SCORE_ATOL))  # may be (near-ties)
        assert sure <= set(top.tolist()) <= maybe
        assert len(sure) > k // 2


def test_half_copy_follows_incremental_changes():
    """After fuses and a prune the synced float16 copy scores like a fresh one (same rows,
    deterministic per-row scaling) and within tolerance of the map's float32 rows."""
    from tests.support.snapshots import ChangingMap

    cm = ChangingMap()
    fs, mp, inc = cm.fs, cm.map, cm.snap
    q = torch.randn((1, fs.lang_dim), generator=torch.Generator().manual_seed(2))
    for step in cm.steps(3):
        a = inc.prepared(fs)[0].similarity(q).numpy()
        b = QueryCopy().take(mp, step).prepared(fs)[0].similarity(q).numpy()
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
        assert np.abs(a - _reference(fs, mp.sem.feat, q)).max() <= SCORE_ATOL


def test_top_stable_equals_a_stable_sort():
    rng = np.random.default_rng(0)
    cases = [rng.standard_normal(300_000).astype(np.float32),
             np.sort(rng.standard_normal(300_000)).astype(np.float32),          # sample misleads: fallback
             rng.integers(0, 5, 300_000).astype(np.float32),                   # massive ties
             np.where(rng.random(300_000) < 0.1, np.nan, rng.random(300_000)).astype(np.float32)]
    for s in cases:
        for k in (1, 10, 2000):
            np.testing.assert_array_equal(top_stable(s, k), np.argsort(-np.nan_to_num(s, nan=-np.inf),
                                                                        kind="stable")[:k])
