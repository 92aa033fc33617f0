"""The mapper's fast query path: prepared similarity (per map snapshot), exact stable top-k,
sampled cone-union volume, snapshot consistency and the bounded wait for the map lock.
Every result is checked against an independent brute-force computation."""
from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import torch

from common.cones import cone_union_volume
from common.feature_space import FeatureSpace
from common.language_head import MLP2, MLP2Config
from common.messages import QueryRequest
from mapper.query_answer import answer_snapshot, top_stable
from semantic_map.query_copy import SCORE_ATOL, QueryCopy
from tests.support.data import bfs_components, low_rank_pca, query_map


def _slow_cos(fs, y, q):
    """float64: decompress (+ head), normalise, dot."""
    x = torch.as_tensor(fs.decompress(y.double().numpy()))
    if fs.head_config is not None:
        x = fs.language_head()(x.float()).double()
    n = x.norm(dim=1, keepdim=True)
    x = torch.where(n > 1e-10, x / n.clamp_min(1e-300), torch.zeros_like(x))
    q = q.double() / q.double().norm(dim=1, keepdim=True)
    return q @ x.T


# ------------------------------------------------------------------ prepared similarity
def test_prepared_similarity_equals_exact_cosine():
    p, X = low_rank_pca(n=3000)
    torch.manual_seed(0)
    head = MLP2(MLP2Config(32, 20, 12, num_inner=1))
    hs = {k: v.detach().numpy().copy() for k, v in head.state_dict().items()}
    spaces = [FeatureSpace("label", "1", 32, pca=p), FeatureSpace("label", "1", 32),
              FeatureSpace("naradio", "1", 32, "siglip", p, head.cfg, hs)]
    for fs in spaces:
        y = torch.from_numpy(fs.compress(X[:700].astype(np.float32))).half()   # stored as float16
        y[5] = torch.from_numpy(fs.compress(np.zeros((1, 32), np.float32)))[0].half()  # |x| ~ 0 row
        for q in (torch.randn(1, fs.lang_dim), torch.randn(4, fs.lang_dim)):
            ref = _slow_cos(fs, y.float(), q).float()
            for cache in ((1 << 28), 0):
                got = fs.prepare(y, max_cache_bytes=cache).similarity(q)
                assert got.shape == ref.shape and torch.isfinite(got).all()
                torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-4)
                torch.testing.assert_close(got, fs.similarity(y, q), rtol=1e-5, atol=1e-5)
    # a workspace from an earlier prepare is reused and gives the same answer
    fs = spaces[0]
    y = torch.from_numpy(fs.compress(X[:500].astype(np.float32)))
    a = fs.prepare(y)
    b = fs.prepare(y[:300], workspace=a.storage())
    assert b.storage() is a.storage()
    q = torch.randn(2, 32)
    torch.testing.assert_close(b.similarity(q), fs.similarity(y[:300], q), rtol=1e-5, atol=1e-5)
    assert fs.prepare(y[:0]).similarity(q).shape == (2, 0)


# ------------------------------------------------------------------ exact stable top-k
@pytest.mark.parametrize("n, k", [(10, 3), (5000, 7), (20000, 2000), (20000, 25000), (9000, 1)])
def test_top_stable_equals_stable_argsort(n, k):
    rng = np.random.default_rng(n + k)
    s = rng.integers(0, 50, n).astype(np.float32)          # many ties
    assert np.array_equal(top_stable(s, k), np.argsort(-s, kind="stable")[:k])
    s = rng.standard_normal(n).astype(np.float32)
    s[rng.integers(0, n, 5)] = np.nan
    ref = np.argsort(-np.where(np.isnan(s), -np.inf, s), kind="stable")[:k]
    assert np.array_equal(top_stable(s, k), ref)


# ------------------------------------------------------------------ search volume
def test_cone_union_samples_vs_fine_grid():
    rng = np.random.default_rng(3)
    exact1 = math.pi * 50 ** 3 * math.tan(math.radians(25)) ** 2 / 3
    d = np.array([[0.0, 0.0, 1.0]])
    # disjoint and identical cones: exact by construction
    far = np.array([[0.0, 0, 0], [500.0, 0, 0], [0, 500.0, 0]])
    assert cone_union_volume(far, np.repeat(d, 3, 0), 25, 50, 1.0) == pytest.approx(3 * exact1, rel=1e-9)
    assert cone_union_volume(np.zeros((4, 3)), np.repeat(d, 4, 0), 25, 50, 1.0) == pytest.approx(exact1, rel=1e-9)
    # overlapping cones: within 0.5 % of a fine grid (documented accuracy)
    for _ in range(2):
        o = rng.normal(size=(6, 3)) * 10
        dd = rng.normal(size=(6, 3))
        dd /= np.linalg.norm(dd, axis=1, keepdims=True)
        fine = cone_union_volume(o, dd, 30, 50, 0.25, max_cells=3_000_000, method="grid")
        got = cone_union_volume(o, dd, 30, 50, 2.0)
        assert got == pytest.approx(fine, rel=5e-3)
        assert 0 < fine < 6 * math.pi * 50 ** 3 * math.tan(math.radians(30)) ** 2 / 3
    with pytest.raises(ValueError, match="method"):
        cone_union_volume(o, dd, 30, 50, 2.0, method="nope")


@pytest.mark.parametrize("threads", [1, 2])
def test_cone_union_kernel_equals_numpy(threads: int):
    """The mapper's C++ per-cone step (``semantic_map.kernels.cone_weighted_union``) against
    the numpy one: the same volume up to float64 rounding on overlapping, nested, parallel
    and disjoint cones, and exact for identical and disjoint ones."""
    from semantic_map import kernels

    assert kernels.available(), f"the C++ kernels are not built: {kernels.IMPORT_ERROR}"
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        union = kernels.cone_weighted_union()
        assert union is not None
        rng = np.random.default_rng(8)
        for n in (2, 5, 12):
            o = rng.normal(size=(n, 3)) * 8
            dd = rng.normal(size=(n, 3))
            dd[: max(2, n // 2)] = dd[0]                   # some parallel axes
            o[1] = o[0] + dd[0] * 5 / np.linalg.norm(dd[0])  # one nested in another
            dd /= np.linalg.norm(dd, axis=1, keepdims=True)
            want = cone_union_volume(o, dd, 20, 40, 1.0, max_cells=120_000)
            got = cone_union_volume(o, dd, 20, 40, 1.0, max_cells=120_000, weighted_union=union)
            assert got == pytest.approx(want, rel=1e-12, abs=0) and got < n * 0.999 * cone_union_volume(
                o[:1], dd[:1], 20, 40, 1.0)
        d = np.repeat(np.array([[0.0, 0.0, 1.0]]), 3, 0)
        exact1 = math.pi * 40 ** 3 * math.tan(math.radians(20)) ** 2 / 3
        far = np.array([[0.0, 0, 0], [500.0, 0, 0], [0, 500.0, 0]])
        assert cone_union_volume(far, d, 20, 40, 1.0, weighted_union=union) == pytest.approx(3 * exact1, rel=1e-9)
        assert cone_union_volume(np.zeros((3, 3)), d, 20, 40, 1.0, weighted_union=union) == pytest.approx(exact1,
                                                                                                          rel=1e-9)
    finally:
        torch.set_num_threads(old)


# ------------------------------------------------------------------ answer vs brute force
def test_answer_snapshot_matches_bruteforce():
    m, fs, cfg, X = query_map()
    qcfg = cfg.query
    qcfg.cluster_candidates = 300
    q = np.asarray(X[7], np.float32)
    snap = QueryCopy().take(m, 1)
    res = answer_snapshot(snap, fs, QueryRequest(embedding=q, top_k=5), qcfg)
    # the brute force scores the rows as the query copy holds them (float16, per-row scaled:
    # their distance to the float32 / float64 cosine is tests/test_query_half.py's subject)
    feats, xyz, vijk = snap.voxel_feats, m.voxel_xyz().numpy(), m.voxel_ijk().numpy()
    vs = _slow_cos(fs, feats, torch.from_numpy(q)[None])[0].numpy()
    order = np.argsort(-vs, kind="stable")
    np.testing.assert_array_equal(res.voxel_xyz, xyz[order[:5]])
    np.testing.assert_allclose(res.voxel_score, vs[order[:5]], atol=SCORE_ATOL)   # float16 product
    # clusters: candidates above the relative score, 26-connected, best first
    cand = order[:300]
    keep = cand[vs[cand] >= vs.min() + qcfg.cluster_rel_score * (vs[cand[0]] - vs.min())]
    ijk = vijk[keep]
    lab = bfs_components(ijk)  # the brute-force 26-neighbour oracle
    best = np.array([vs[keep][lab == c].max() for c in range(lab.max() + 1)])
    cl = np.argsort(-best, kind="stable")[:5]
    np.testing.assert_allclose(res.cluster_score, best[cl], atol=SCORE_ATOL)
    np.testing.assert_array_equal(res.cluster_size, [(lab == c).sum() for c in cl])
    for i, c in enumerate(cl):
        ctr = (ijk[lab == c] + 0.5) * 0.5
        np.testing.assert_allclose(res.cluster_xyz[i], ctr.mean(0), atol=1e-5)
        np.testing.assert_allclose(res.cluster_extent[i], ctr.max(0) - ctr.min(0) + 0.5, atol=1e-6)
    assert res.cluster_size.sum() > len(res.cluster_size)     # some clusters have several voxels
    # rays and their search volume
    rs = _slow_cos(fs, m.rays().features.float(), torch.from_numpy(q)[None])[0].numpy()
    ro = np.argsort(-rs, kind="stable")[:5]
    np.testing.assert_array_equal(res.ray_origin, m.ray_geometry()[0].numpy()[ro])
    np.testing.assert_allclose(res.ray_score, rs[ro], atol=1e-5)
    ns = min(qcfg.search_rays, 5)
    ref = cone_union_volume(res.ray_origin[:ns], res.ray_direction[:ns], m.cone_half_angle(),
                            qcfg.search_range_m, 1.0, max_cells=4_000_000, method="grid")
    assert res.search_volume_m3 == pytest.approx(ref, rel=0.02)


def test_snapshot_is_isolated_from_later_map_changes():
    m, fs, cfg, X = query_map(n_side=8)
    q = QueryRequest(embedding=np.asarray(X[3], np.float32), top_k=4)
    snap = QueryCopy().take(m, 1)
    before = answer_snapshot(snap, fs, q, cfg.query)
    # the map changes: every voxel gets the query's own feature, and new voxels appear
    best = torch.from_numpy(fs.compress(X[3:4].astype(np.float32)))
    m.fuse_samples(torch.full((50, 3), 100.25), torch.rand(50, 3), best.repeat(50, 1))
    m.fuse_samples(m.voxel_xyz()[:64], torch.rand(64, 3), best.repeat(64, 1) * 9)
    after_old = answer_snapshot(snap, fs, q, cfg.query)
    for f in ("voxel_xyz", "voxel_score", "cluster_xyz", "cluster_size", "ray_score"):
        np.testing.assert_array_equal(getattr(after_old, f), getattr(before, f))
    fresh = answer_snapshot(snap.take(m, 2), fs, q, cfg.query)
    assert fresh.voxel_score[0] > before.voxel_score[0]
    assert fresh.voxel_score[0] == pytest.approx(1.0, abs=1e-3)


def test_query_does_not_wait_past_lock_timeout_while_map_is_busy():
    from mapper.service import MapperService
    from mapper.service_config import load_mapper_config

    m, fs, _, X = query_map(n_side=6)
    cfg = load_mapper_config(None, ["preset=throughput", "query.lock_timeout_s=0.05"])
    svc = MapperService(cfg)
    svc.map, svc.space, svc.map_gen, svc.mapped = m, fs, 1, 3
    req = QueryRequest(embedding=np.asarray(X[1], np.float32), top_k=3)
    first = svc.run_query(req)
    assert "stale" not in first.timings and first.frames_mapped == 3
    # the mapping thread holds the lock (a long integration) and the map changed
    held, release = threading.Event(), threading.Event()

    def busy():
        with svc.lock:
            # the map grows (so the next snapshot needs bigger buffers) while the lock is held
            m.fuse_samples(torch.rand(3000, 3) * 40 + 50, torch.rand(3000, 3), torch.randn(3000, fs.dim))
            svc.map_gen += 1
            svc.mapped = 4
            held.set()
            release.wait(60)

    t = threading.Thread(target=busy)
    t.start()
    try:
        assert held.wait(30)
        res = svc.run_query(req)
        assert not release.is_set() and t.is_alive()            # answered while the lock was held
        assert res.timings["stale"] == 1.0 and res.frames_mapped == 3
        np.testing.assert_array_equal(res.voxel_xyz, first.voxel_xyz)
    finally:
        release.set()
        t.join(30)
    res = svc.run_query(req)
    assert "stale" not in res.timings and res.frames_mapped == 4
    assert svc._qsnap.n_voxels == m.n_voxels() > 6 ** 3
    ref = answer_snapshot(QueryCopy().take(m, 0), fs, req, cfg.query)
    np.testing.assert_array_equal(res.voxel_xyz, ref.voxel_xyz)
    np.testing.assert_array_equal(res.cluster_xyz, ref.cluster_xyz)
