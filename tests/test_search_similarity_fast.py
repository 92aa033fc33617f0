"""The search's similarity fast path against brute force: the targets' softmax share over a
background summarised by its per-voxel log-sum-exp (semantic_map.query.softmax_share), the
snapshot's cached, incrementally updated log-sum-exp (QueryCopy.phrase_logsumexp) and
the search's voxel probabilities (mapper.search_answer) against a float64 softmax of the
same scores."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from apps.bench.query import _change, _space, build_map
from mapper.search_answer import _probabilities, _voxel_probabilities
from semantic_map.query import softmax_share
from semantic_map.query_copy import SCORE_ATOL, QueryCopy
from tests.support.snapshots import ChangingMap

#: |fast − float64 softmax of the same float32 scores| at temperature 100 (float32 rounding of
#: arguments up to 100: ulp 7.6e-6)
PROB_ATOL = 3e-5


def _softmax64(scores: np.ndarray, temperature: float) -> np.ndarray:
    x = np.asarray(scores, np.float64) * temperature
    x = x - x.max(0, keepdims=True)
    e = np.exp(x)
    return e / e.sum(0, keepdims=True)


def _lse64(scores: np.ndarray, temperature: float) -> np.ndarray:
    x = np.asarray(scores, np.float64) * temperature
    mx = x.max(0)
    return mx + np.log(np.exp(x - mx).sum(0))


@pytest.mark.parametrize("n_targets,n_rest", [(1, 5), (2, 4), (3, 1), (1, 0), (2, 0)])
def test_softmax_share_equals_full_softmax(n_targets: int, n_rest: int):
    rng = np.random.default_rng(n_targets * 10 + n_rest)
    s = rng.uniform(-1, 1, (n_targets + n_rest, 4000)).astype(np.float32)
    s[:, :100] = s[0, :100]                                   # ties: every phrase scores the same
    s[:, 100:200] = np.round(s[:, 100:200], 1)                # ties between some phrases
    s[0, 200:300], s[-1, 300:400] = 1.0, 1.0                  # saturated: a target or the last phrase at 1
    s[:, 400] = -1.0
    for temperature in (1.0, 100.0, 1000.0):
        rest = torch.as_tensor(_lse64(s[n_targets:], temperature).astype(np.float32)) if n_rest else None
        got = softmax_share(torch.as_tensor(s[:n_targets]), rest, temperature).numpy()
        want = _softmax64(s, temperature)[:n_targets]
        assert got.shape == want.shape and got.dtype == np.float32
        assert np.abs(got - want).max() <= PROB_ATOL * max(1.0, temperature / 100), np.abs(got - want).max()
    if n_targets == 1 and n_rest == 0:
        assert np.array_equal(got, np.ones_like(got))         # a softmax of one is 1
    assert softmax_share(torch.zeros((n_targets, 0)), torch.zeros(0)).shape == (n_targets, 0)


def _snap_scores(snap: QueryCopy, fs, q: torch.Tensor) -> np.ndarray:
    """(Q, N) scores of a fresh snapshot's float16 copy, one query at a time."""
    v, _ = snap.prepared(fs)
    return np.stack([v.similarity(q[i:i + 1])[0].numpy() for i in range(len(q))])


def test_multi_query_scores_are_the_single_query_ones():
    fs = _space(24)
    _, mp = build_map(8_000, 24, 50, fs, seed=2)
    v, _ = QueryCopy().take(mp, 0).prepared(fs)
    q = torch.randn((4, fs.lang_dim), generator=torch.Generator().manual_seed(4))
    many = v.similarity(q).numpy()
    assert np.array_equal(many, _snap_scores(QueryCopy().take(mp, 0), fs, q))
    rows = torch.tensor([5, 0, 7999, 3, 3], dtype=torch.int64)
    np.testing.assert_allclose(v.subset(rows).similarity(q).numpy(), many[:, rows.numpy()], rtol=1e-6, atol=1e-7)


def test_phrase_logsumexp_follows_incremental_changes():
    """After fuses, new voxels and a prune the cached log-sum-exp equals the brute-force one of
    a fresh copy (the rows a sync changed are recomputed, the others kept)."""
    cm = ChangingMap()
    fs, mp, snap = cm.fs, cm.map, cm.snap
    bg = torch.randn((3, fs.lang_dim), generator=torch.Generator().manual_seed(2))
    other = torch.randn((2, fs.lang_dim), generator=torch.Generator().manual_seed(3))
    for step in cm.steps(4):
        got = snap.phrase_logsumexp(fs, bg, 100.0)
        assert got is not None and len(got) == mp.n_voxels()
        want = _lse64(_snap_scores(QueryCopy().take(mp, step), fs, bg), 100.0)
        assert np.abs(got.numpy() - want).max() <= 1e-4 * 100
        np.testing.assert_allclose(got.numpy(), want, rtol=2e-6, atol=1e-5)
        if step == 1:                                          # a second phrase set kept alongside
            o = snap.phrase_logsumexp(fs, other, 50.0)
            assert o is not None
            np.testing.assert_allclose(o.numpy(), _lse64(_snap_scores(snap, fs, other), 50.0), rtol=2e-6,
                                       atol=1e-5)
    assert snap.phrase_logsumexp(fs, bg[:0], 100.0) is None


def test_search_voxel_probabilities_match_full_softmax():
    """The cached-background probabilities equal a float64 softmax over targets + background
    of the copy's scores, and those scores the float64 cosine within SCORE_ATOL."""
    fs = _space(32)
    _, mp = build_map(30_000, 32, 100, fs, seed=7)
    snap = QueryCopy()
    snap.reserve(mp)
    snap.sync(mp, 1)
    v, _ = snap.prepared(fs)
    q = torch.randn((6, fs.lang_dim), generator=torch.Generator().manual_seed(8))
    for n_targets in (1, 2, 6):
        got = _voxel_probabilities(snap, fs, v, q, n_targets, 100.0, "cpu")
        s = _snap_scores(snap, fs, q)
        want = _softmax64(s, 100.0)[:n_targets]
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= PROB_ATOL
        plain = _probabilities(v, q, n_targets, 100.0)       # the full softmax path
        assert np.abs(plain - want).max() <= PROB_ATOL
        if n_targets == len(q):
            assert np.array_equal(got, plain)                  # no background: the same path
    # the copy's scores are the cosine of the map's features within the stated tolerance
    m, vb = fs.pca.torch_basis("cpu", torch.float32)
    x = mp.voxels().features.double() @ vb.double().T + m.double()
    ref = (torch.nn.functional.normalize(q.double(), dim=1) @ torch.nn.functional.normalize(x, dim=1).T).numpy()
    assert np.abs(s - ref).max() <= SCORE_ATOL


def test_voxel_ijk_equals_the_centres_round_trip():
    """Snapshot rows' voxel indices from their keys equal floor(centre / vox), the search's
    earlier route, including indices at the ends of the packable range."""
    from common.conventions import voxel_index
    from semantic_map import cell_keys

    fs = _space(8)
    _, mp = build_map(2_000, 8, 10, fs)
    lim = (1 << 20) - 1
    ijk = torch.tensor([[lim, -lim - 1, 0], [-lim - 1, lim, lim], [123456, -654321, 7], [-1, -1, -1]])
    mp.fuse_sums(cell_keys.pack(ijk), torch.rand((4, 3)), torch.randn((4, 8)), torch.ones(4))
    for vox in (0.05, 0.2, 1.0):
        mp.cfg.vox_size = vox
        snap = QueryCopy().take(mp, 0)
        rows = np.r_[np.arange(0, mp.n_voxels(), 7), mp.n_voxels() - 4 + np.arange(4)]
        got = snap.voxel_ijk(rows)
        assert got.dtype == np.int64
        assert np.array_equal(got, voxel_index(snap.voxel_xyz(rows).astype(np.float64), vox))
    assert {tuple(r) for r in got[-4:].tolist()} == {tuple(r) for r in ijk.tolist()}
    assert snap.voxel_ijk(np.zeros(0, np.int64)).shape == (0, 3)


def test_tracker_repeat_of_the_same_input_matches_reference():
    """An update with the same voxels, confidences and frame as the last one (answered at
    once) and its neighbours (another frame, other confidences: the full update) equal the
    brute-force reference tracker."""
    import planning.instances as inst
    from tests.test_search_fast_paths import _random_voxels, _ReferenceTracker

    rng = np.random.default_rng(3)
    fast, ref = inst.InstanceTracker(0.2, 2), _ReferenceTracker(0.2, 2)
    base = _random_voxels(rng, 400, 10, spread=200)
    conf = rng.random(len(base))
    keep = rng.random(len(base)) < 0.7
    for frame, change in ((0, None), (0, None), (1, None), (1, None), (1, "conf"), (1, None), (2, "voxels"),
                          (2, None)):
        if change == "conf":
            conf = rng.random(len(base))
        elif change == "voxels":
            keep = rng.random(len(base)) < 0.7
        ev = [e.as_dict() for e in fast.update("t", base[keep], conf[keep], frame)]
        assert ev == ref.update("t", base[keep], conf[keep], frame)
        got, want = fast.current("t"), ref.instances["t"]
        assert [(g.id, g.confidence, g.voxels, g.observations, g.first_seen, g.last_seen) for g in got] == [
            (w["id"], w["confidence"], w["voxels"], w["observations"], w["first_seen"], w["last_seen"]) for w in want]
    assert fast.current("t") and fast.updates == 8


def test_score_cache_follows_incremental_changes(monkeypatch):
    """Queries scored on earlier versions of the copy (cached, updated for the changed rows)
    score exactly like a fresh copy, also when the cache evicts (few entries allowed)."""
    import semantic_map.query_copy as qs

    monkeypatch.setattr(qs, "SCORE_CACHE_ENTRIES", 3)
    cm = ChangingMap(seed=4, change_seed=9)
    fs, mp, snap = cm.fs, cm.map, cm.snap
    q = torch.randn((5, fs.lang_dim), generator=torch.Generator().manual_seed(6))
    for step in cm.steps(4):
        v, _ = snap.prepared(fs)
        fresh, _ = QueryCopy().take(mp, step).prepared(fs)
        want = fresh.similarity(q, use_cache=False).numpy()
        for i in ([0, 1], [0], [2, 3, 4], [1, 0]):             # hits, misses and evictions
            assert np.array_equal(v.similarity(q[i]).numpy(), want[i])
        assert len(v._cache.entries) == 3
        got = v.similarity(q[:1])
        with torch.inference_mode():
            got += 1.0                                          # a caller's in-place change stays its own
        assert np.array_equal(v.similarity(q[:1]).numpy(), want[:1])


def test_answer_search_equals_the_plain_path_across_map_changes(monkeypatch):
    """answer_search with the snapshot's caches (background log-sum-exp, target scores, keys
    for voxel indices) gives the same instances (confidences to float32 rounding), events and
    rays as the plain path (full softmax over every phrase's scores, centres for voxel
    indices) over map changes."""
    from apps.bench.search import TARGETS
    from common.search_messages import SearchRequest
    from mapper.search_answer import TrackerStore, answer_search
    from semantic_map.query_copy import HalfFeatures

    class Plain:
        """The snapshot without its caches."""

        def __init__(self, s):
            self._s = s

        def __getattr__(self, k):
            if k in ("phrase_logsumexp", "voxel_ijk"):
                raise AttributeError(k)
            return getattr(self._s, k)

        def prepared(self, fs, device="cpu"):
            v, r = self._s.prepared(fs, device)
            return HalfFeatures(fs, device, v._h, v._a, v._b), r

    import mapper.search_answer as sa

    fs = _space(16)
    table: dict = {}

    def embed(fs_, req, background, *a):                     # fixed random vectors per phrase (no text model)
        rows = [torch.as_tensor(req.embeddings, dtype=torch.float32)] if req.embeddings is not None else [
            table.setdefault(t, torch.randn((1, fs.lang_dim))) for t in req.targets]
        return torch.cat(rows + [table.setdefault(b, torch.randn((1, fs.lang_dim))) for b in background])

    monkeypatch.setattr(sa, "embed_phrases", embed)
    torch.manual_seed(14)
    cfg, mp = build_map(30_000, 16, 300, fs, seed=11)
    snap = QueryCopy()
    fast, plain = TrackerStore(8), TrackerStore(8)
    g = torch.Generator().manual_seed(12)
    bg = torch.randn((4, fs.lang_dim), generator=torch.Generator().manual_seed(13)).numpy()
    n_found = 0
    for step in range(3):
        snap.reserve(mp)
        snap.sync(mp, step, step)
        for i, tg in enumerate(TARGETS[:3]):
            emb = bg[i:i + 1] if i == 2 else None              # a request's own embedding too
            req = SearchRequest(targets=[tg], embeddings=emb, threshold=0.3).validate()
            a = answer_search(snap, fs, req, cfg, fast, None, map_version=step)
            b = answer_search(Plain(snap), fs, req, cfg, plain, None, map_version=step)
            assert a.events == b.events and a.beyond == b.beyond
            assert [{**f, "confidence": 0} for f in a.found] == [{**f, "confidence": 0} for f in b.found]
            assert np.allclose([f["confidence"] for f in a.found], [f["confidence"] for f in b.found], rtol=0,
                               atol=PROB_ATOL)
            n_found += len(a.found)
        _change(mp, 16, g, 31)
        mp.remove_voxels(mp.voxel_ijk()[:200])
    assert n_found > 0


def test_distinct_cosines_against_the_projection_and_a_similar_class_reads_zero():
    """The rays' evidence for ray_z (mapper.search_answer.distinct_cosines) equals the cosine of
    each ray to the target's embedding minus its least-squares projection on the other
    phrases (computed here on the vectors, not the cosines), and on rays toward a class
    similar to the target (a radio tower for a water tower: cosine 0.86) beside rays that hold
    a small share of the target, the target's rays stand out while by raw cosine the similar
    class's do."""
    from mapper.search_answer import _ray_scores, distinct_cosines
    from planning.look_next import ray_outlier_z

    rng = np.random.default_rng(3)
    D = 32
    basis = np.linalg.qr(rng.normal(size=(D, 6)))[0].T            # orthonormal class directions
    water, radio = basis[0], 0.86 * basis[0] + np.sqrt(1 - 0.86 ** 2) * basis[1]
    others = basis[2:]                                              # building, tree, ground, road
    q = torch.as_tensor(np.vstack([water, radio, others]), dtype=torch.float32)
    rays = [w @ others + 0.02 * rng.normal(size=D) for w in rng.dirichlet(np.ones(4), 60)]
    at_radio = [radio + 0.02 * rng.normal(size=D) for _ in range(4)]
    at_water = [0.3 * water + 0.7 * others[0] + 0.02 * rng.normal(size=D) for _ in range(4)]
    feats = torch.as_tensor(np.vstack(rays + at_radio + at_water), dtype=torch.float32)
    radio_rows, water_rows = np.arange(60, 64), np.arange(64, 68)

    p, ev = _ray_scores(feats, q, 2, 100.0)
    f = feats.numpy().astype(np.float64)
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    qv = q.numpy().astype(np.float64)
    for t in range(2):
        rest = np.delete(qv, t, 0)
        u = qv[t] - rest.T @ np.linalg.lstsq(rest.T, qv[t], rcond=None)[0]
        assert np.allclose(ev[t], f @ (u / np.linalg.norm(u)), atol=1e-5)
    assert np.abs(ev[0, radio_rows]).max() < 0.1 and ev[0, water_rows].min() > 0.15
    z, z_cos = ray_outlier_z(ev[:1])[0], ray_outlier_z((f @ qv[0])[None])[0]
    assert z[water_rows].min() > z[radio_rows].max() and int(np.argmax(z)) in water_rows
    assert int(np.argmax(z_cos)) in radio_rows                       # what raw cosines chase
    sim = (f @ qv.T).T
    assert np.allclose(distinct_cosines(sim[:1], q[:1], 1), sim[:1], atol=1e-6)    # no other phrase
    twin = torch.cat([q[:1], q[:1]])                                 # the others explain it wholly
    assert not distinct_cosines(np.vstack([sim[:1], sim[:1]]), twin, 1).any()


def test_distinct_cosines_against_the_nearest_phrases_of_a_vocabulary():
    """A background of more phrases than the features have dimensions (a vocabulary) explains
    every target wholly: no ray keeps any evidence. Against the target's few nearest phrases
    (``search.distinct_phrases``) the evidence is that of those phrases alone (the projection
    computed here on the vectors), and among rays toward what resembles the target, those
    holding a share of it stand out."""
    from mapper.search_answer import distinct_cosines

    rng = np.random.default_rng(4)
    D = 16
    water = rng.normal(size=D)
    water /= np.linalg.norm(water)
    vocab = rng.normal(size=(40, D))                                 # spans the space
    vocab /= np.linalg.norm(vocab, axis=1, keepdims=True)
    q = torch.as_tensor(np.vstack([water, vocab]), dtype=torch.float64)
    near = np.argsort(-(vocab @ water), kind="stable")[:5]
    mix = rng.dirichlet(np.ones(5), 50) @ vocab[near]                   # rays toward what resembles it
    rays = mix + 0.02 * rng.normal(size=(50, D)) + np.outer(np.r_[np.zeros(45), np.full(5, 0.3)], water)
    f = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    sim = (f @ q.numpy().T).T
    assert np.abs(distinct_cosines(sim, q, 1)).max() < 1e-6          # the whole vocabulary: nothing left
    got = distinct_cosines(sim, q, 1, nearest=5)
    rest = vocab[np.sort(near)]
    u = water - rest.T @ np.linalg.lstsq(rest.T, water, rcond=None)[0]
    assert np.allclose(got[0], f @ (u / np.linalg.norm(u)), atol=1e-5)
    assert got[0, 45:].min() > got[0, :45].max()                     # the target's rays stand out
    assert np.array_equal(distinct_cosines(sim, q, 1, nearest=40), distinct_cosines(sim, q, 1))


def test_margin_evidence_sets_the_target_apart_from_a_similar_class():
    """``search.ray_evidence=margin``: a ray's cosine to the target less its best cosine to the
    target's nearest other phrases (held to that computation on the cosines), on rays toward a
    class similar to the target (a radio tower for a water tower: it shares a "tower" phrase's
    direction) beside rays of sky and rays holding a small share of the target: against the
    target's nearest phrase the target's rays read above the sky's, the similar class's below."""
    from mapper.search_answer import margin_cosines
    from planning.look_next import ray_outlier_z

    rng = np.random.default_rng(6)
    D = 24
    basis = np.linalg.qr(rng.normal(size=(D, 5)))[0].T
    tower, water_part, radio_part, sky, ground = basis
    water_t, radio_t = tower + 0.5 * water_part, tower + 0.5 * radio_part         # the two classes
    q = torch.as_tensor(np.vstack([water_t, tower, sky, ground]), dtype=torch.float64)   # target, "tower", ...
    rays = [sky + 0.3 * ground + 0.02 * rng.normal(size=D) for _ in range(60)]
    rays += [sky + 0.3 * ground + 0.4 * radio_t + 0.02 * rng.normal(size=D) for _ in range(4)]
    rays += [sky + 0.3 * ground + 0.4 * water_t + 0.02 * rng.normal(size=D) for _ in range(4)]
    f = np.vstack(rays)
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    qv = q.numpy() / np.linalg.norm(q.numpy(), axis=1, keepdims=True)
    sim = qv @ f.T
    got = margin_cosines(sim, q, 1, nearest=1)                      # "tower", the target's nearest phrase
    assert np.allclose(got[0], sim[0] - sim[1], atol=1e-6)
    both = margin_cosines(sim, q, 1, nearest=3)
    assert np.allclose(both[0], sim[0] - sim[1:].max(0), atol=1e-6)
    sky_rows, radio_rows, water_rows = np.arange(60), np.arange(60, 64), np.arange(64, 68)
    assert got[0, water_rows].min() > got[0, sky_rows].max() > got[0, radio_rows].max()
    z = ray_outlier_z(got[:1])[0]
    assert z[water_rows].min() > 3.0 and z[radio_rows].max() < 0
    assert np.allclose(margin_cosines(sim[:1], q[:1], 1), sim[:1])   # no other phrase: the raw cosine
