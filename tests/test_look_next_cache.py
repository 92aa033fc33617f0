"""Look-next's kept work (issue 46): :class:`planning.look_next.LookNextCache` reuses the
frontier–ray pairs, viewpoints and gains between calls; every answer is held equal to a call
without a cache, over random map-update sequences (hypothesis) and on the synthetic world,
and standing searches of several robots on one map version equal their one-by-one answers."""
from __future__ import annotations

import numpy as np
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planning.look_next import LookNextCache, look_next
from semantic_map.occupancy import make_occupancy

VOX = 0.5


def _goals(*args, **kw) -> list[dict]:
    return [g.as_dict() for g in look_next(*args, **kw)]


def _random_state(rng, n_front: int, n_rays: int):
    f = (rng.integers(-12, 12, (n_front, 3)) + 0.5) * VOX * 2
    o = rng.uniform(-12, 12, (n_rays, 3))
    d = rng.normal(size=(n_rays, 3))
    return f, o, d / np.linalg.norm(d, axis=1, keepdims=True)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 31 - 1), steps=st.lists(st.sampled_from(["grid", "front", "rays", "same", "prune"]),
                                                         min_size=2, max_size=5))
def test_cached_look_next_equals_a_full_recompute(seed, steps):
    rng = np.random.default_rng(seed)
    g = make_occupancy(VOX, -5, 30, backend="vdb")
    g.update(rng.integers(-24, 24, (6000, 3)), rng.choice([-3, 2], 6000))
    f, o, d = _random_state(rng, 400, 150)
    cache = LookNextCache()
    compared = 0
    for step in ["same", *steps]:
        if step == "grid":
            g.update(rng.integers(-24, 24, (300, 3)), rng.choice([-20, 20], 300))
        elif step == "prune":
            g.prune(0)
        elif step == "front":                         # some frontiers go, some come, order kept
            keep = rng.random(len(f)) > 0.1
            f = np.concatenate([f[keep], (rng.integers(-12, 12, (30, 3)) + 0.5) * VOX * 2])
        elif step == "rays":
            keep = rng.random(len(o)) > 0.2
            _, o2, d2 = _random_state(rng, 0, 25)
            o, d = np.concatenate([o[keep], o2]), np.concatenate([d[keep], d2])
        for n, robot in enumerate(([0.0, 0.0, 1.0], [5.0, -3.0, 0.0], None)):   # several requests per version
            if n != 1:                                # the second robot asks with the first's scores
                T = int(rng.integers(1, 3))
                s = rng.random((len(o), T)) ** 4
                z = rng.normal(size=(len(o), T)) * 2
            kw = dict(ray_z=z, ray_radius_m=1.5, standoff_m=1.0, sensing_radius_m=2.0, max_goals=6,
                      max_candidates=20)
            names = [f"t{i}" for i in range(T)]
            want = _goals(g, VOX, f, o, d, s, names, robot, **kw)
            got = _goals(g, VOX, f, o, d, s, names, robot, cache=cache, **kw)
            assert got == want
            compared += len(want)
    assert compared > 0 and cache.hits > 0          # goals were compared, and the fast path ran


def test_cache_follows_a_changed_grid_at_the_same_frontiers():
    """The same frontiers and rays, the occupancy around a viewpoint changed: the viewpoint
    and gain must be recomputed (a stale cache would keep the old ones)."""
    g = make_occupancy(VOX, -5, 30, backend="torch")
    ax = np.arange(-6, 7)
    box = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    g.update(box, -3)                                          # all free around the origin
    f = np.array([[0.25, 0.25, 0.25]])
    o, d = np.array([[0.3, 0.3, 0.3]]), np.array([[1.0, 0.0, 0.0]])
    cache = LookNextCache()
    a = _goals(g, VOX, f, o, d, np.ones((1, 1)), ["x"], cache=cache, sensing_radius_m=2.0)
    g.update(np.array([[0, 0, 0], [1, 1, 1]]), 20)              # occupied at the old viewpoint
    g.update(np.array([[4, 4, 4]]), 10)                         # unknown inside the gain sphere -> none
    b = _goals(g, VOX, f, o, d, np.ones((1, 1)), ["x"], cache=cache, sensing_radius_m=2.0)
    assert a and b and a[0]["position"] != b[0]["position"]
    assert b == _goals(g, VOX, f, o, d, np.ones((1, 1)), ["x"], sensing_radius_m=2.0)


def test_on_the_synthetic_world_across_frames():
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    from synthetic_world import World

    w = World.generate(3)
    poses = w.trajectory("ground", 60, seed=3)
    hw = (40, 52)
    K = w.camera(hw, 90.0)
    cfg = map_config("default", dict(vox_size=0.3, depth_limit=12.0, vox_accum_period=2, ray_accum_period=2))
    n_cls = len(w.classes)
    m = RayFrontsMap(cfg, n_cls, "labels", occupancy_backend="vdb")
    cache = LookNextCache()
    car = w.class_id("car")
    checked = 0
    for k, p in enumerate(poses[10:17]):
        r = w.render(p, K, hw)
        oh = torch.nn.functional.one_hot(torch.as_tensor(r.labels.astype(np.int64)), n_cls)
        m.integrate(p, K, r.depth.astype(np.float32), r.rgb, oh.permute(2, 0, 1).float())
        if k % 2 != 0:
            continue
        m.flush()
        f = m.frontiers().centres.numpy().astype(np.float64)
        rl = m.rays()
        o, dd = rl.origins.numpy(), rl.directions.numpy()
        feat = rl.features.float()
        s = (feat[:, car] / feat.sum(1).clamp_min(1e-9)).numpy().reshape(-1, 1)
        for start in ([0.0, 0.0, 1.0], list(p[:3, 3])):
            want = _goals(m.occupancy_view(), 0.3, f, o, dd, s, ["car"], start, max_goals=8)
            assert _goals(m.occupancy_view(), 0.3, f, o, dd, s, ["car"], start, max_goals=8, cache=cache) == want
            checked += len(want)
    assert checked > 0 and len(f) > 0 and len(o) > 0 and cache.hits > 0


def test_standing_searches_of_three_robots_equal_their_one_by_one_answers():
    """As the standing loop runs them after a map update: three robots' searches for one target
    on one map version, sharing the copy's score caches and the map's look-next cache, equal
    each robot's search answered alone from a fresh copy and an empty look-next cache."""
    from apps.bench.search import ROBOTS
    from common.search_messages import SearchRequest
    from mapper import search_answer as sa
    from semantic_map.query_copy import QueryCopy
    from tests.support.search_world import search_world

    fs, cfg, m, frames = search_world(24, 3000, 60)
    cfg.search.background = []                  # embeddings only: no text model to load
    frames(0, 2)
    emb = np.random.default_rng(1).standard_normal((2, fs.lang_dim)).astype(np.float32)
    snap = QueryCopy()
    snap.sync(m, 1, 1)
    trackers = sa.TrackerStore(cfg.search.max_trackers)

    def ask(s, xyz, version):
        req = SearchRequest(targets=["a", "b"], embeddings=emb, background=[], from_xyz=xyz).validate()
        rep = sa.answer_search(s, fs, req, cfg, trackers, lambda fn: fn(m), map_version=version)
        return dict(found=rep.found, look_next=rep.look_next, beyond=rep.beyond, events=rep.events)

    ask(snap, ROBOTS[0], 1)                                     # warm: the caches hold version 1
    frames(2, 3)                                                # a map update
    snap.sync(m, 2, 2)
    hits = sa.look_next_cache(m).hits
    standing = [ask(snap, xyz, 2) for xyz in ROBOTS]
    assert sa.look_next_cache(m).hits == hits + 2              # robots 2 and 3 reused robot 1's work
    assert all(len(a["look_next"]) >= 3 for a in standing) and standing[0]["look_next"] != standing[1]["look_next"]
    for xyz, got in zip(ROBOTS, standing, strict=True):
        sa._LOOK_NEXT.pop(m, None)
        alone = QueryCopy()
        alone.sync(m, 2, 2)
        assert ask(alone, xyz, 2) == got


def _viewpoint_by_hand(g, centre: np.ndarray, standoff: float) -> np.ndarray | None:
    """The look-next viewpoint of one frontier centre, cell by cell: the centre of the free
    voxel nearest ``centre`` within ``standoff`` whose 26 neighbours are not occupied (ties:
    the lowest (i, j, k))."""
    c = np.floor(centre / VOX).astype(np.int64)
    r = int(np.ceil(standoff / VOX))
    best, best_d = None, np.inf
    for i in range(-r, r + 1):
        for j in range(-r, r + 1):
            for k in range(-r, r + 1):
                cell = c + (i, j, k)
                box = (cell + np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3))
                vals = np.asarray(g.query(torch.as_tensor(box)))
                if vals[13] >= 0 or (vals > 0).any():
                    continue
                p = (cell + 0.5) * VOX
                dist = float(np.linalg.norm(p - centre))
                if dist <= standoff + 1e-9 and dist < best_d:
                    best, best_d = p, dist
    return best


def test_viewpoints_equal_a_cell_by_cell_search():
    """The vectorised viewpoint search (one grid read, one distance array for all frontiers)
    against a per-cell search of each frontier's neighbourhood."""
    from planning.look_next import _viewpoints

    rng = np.random.default_rng(3)
    g = make_occupancy(VOX, -5, 30, backend="vdb")
    g.update(rng.integers(-10, 10, (2500, 3)), rng.choice([-3, 2], 2500, p=[0.8, 0.2]))
    centres = rng.uniform(-4, 4, (60, 3))
    got = _viewpoints(g, VOX, centres, 1.0)
    found = 0
    for c, v in zip(centres, got, strict=True):
        want = _viewpoint_by_hand(g, c, 1.0)
        assert (v is None) == (want is None)
        if want is not None:
            assert np.array_equal(v, want)
            found += 1
    assert 10 < found < len(centres)          # both cases met


def test_nearest_frontiers_equal_the_general_ranking():
    """The nearest-frontier list (one partition of the distances) against the general
    score-then-distance ranking with every score 0, ties in distance included."""
    from planning.look_next import _best_first, _nearest

    rng = np.random.default_rng(5)
    for n, k in [(0, 3), (5, 9), (400, 1), (400, 64), (3000, 200)]:
        dist = rng.integers(0, 40, n).astype(np.float64) * 0.5       # many equal distances
        assert np.array_equal(_nearest(dist, k), _best_first(np.zeros(n), dist, k))
