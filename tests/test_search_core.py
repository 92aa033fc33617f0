"""Search-for-planners computation (planning.instances / look_next / beyond /
occupancy_queries) against the synthetic world's ground truth and brute force.

The map is built from rendered frames of ``World.generate(3)`` whose features are the
one-hot ground-truth labels, so a voxel's confidence for a class is its label share.
"""
import math

import numpy as np
import pytest
import torch

from common.conventions import voxel_center
from planning.beyond import best_rays, closest_approach, triangulate
from planning.instances import InstanceTracker, connected_26
from planning.look_next import MIN_RAYS_FOR_Z, look_next, points_in_polygon, ray_outlier_z, unknown_volume
from planning.occupancy_queries import FREE, OCCUPIED, UNKNOWN, costmap_slice, point_states, state_grid
from semantic_map.config import map_config
from semantic_map.map import RayFrontsMap
from synthetic_world import World
from tests.support.data import bfs_components

HW = (48, 64)
VOX = 0.3
STAGES = tuple(range(22, 42, 2))     # ten map updates


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _confidence(feat: torch.Tensor, cls: int) -> np.ndarray:
    f = feat.float()
    return (f[:, cls] / f.sum(1).clamp_min(1e-9)).numpy()


@pytest.fixture(scope="module")
def built():
    """Map after each stage of frames, with the car tracker's instances at each stage."""
    w = World.generate(3)
    poses = w.trajectory("ground", 240, seed=3)
    K = w.camera(HW, 90.0)
    cfg = map_config("default", dict(vox_size=VOX, depth_limit=15.0, vox_accum_period=2, ray_accum_period=3,
                                     ray_accum_phase=1))
    n_cls = len(w.classes)
    m = RayFrontsMap(cfg, n_cls, "labels", occupancy_backend="torch")
    car = w.class_id("car")
    tr = InstanceTracker(VOX, min_voxels=3)
    stages = []
    done = 0
    for stop in STAGES:
        for p in poses[done:stop]:
            r = w.render(p, K, HW)
            oh = torch.nn.functional.one_hot(torch.as_tensor(r.labels.astype(np.int64)), n_cls)
            m.integrate(p, K, r.depth.astype(np.float32), r.rgb, oh.permute(2, 0, 1).float())
        done = stop
        m.flush()
        conf = _confidence(m.voxels().features, car)
        sel = conf > 0.5
        frames = m.schedule_counters()["frames"]
        events = tr.update("car", m.voxel_ijk()[torch.as_tensor(sel)].numpy(), conf[sel], frames)
        stages.append(dict(instances=tr.current("car"), events=events, frames=frames))
    return dict(world=w, map=m, tracker=tr, stages=stages, car=car, poses=poses)


def _box_distance(p, lo, hi) -> float:
    return float(np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0)))


# ----------------------------------------------------------------------------- instances
def test_found_instances_are_true_cars(built):
    w, m, car = built["world"], built["map"], built["car"]
    inst = built["stages"][-1]["instances"]
    assert len(inst) >= 2
    true = w.instances_of(car)
    xyz = m.voxel_xyz().numpy().astype(np.float64)
    truth = w.voxel_labels(m.voxel_ijk().numpy(), VOX)
    for i in inst:
        # the centroid lies within 2 voxels of a true car's box ...
        d = [_box_distance(i.centroid, t.aabb_min, t.aabb_max) for t in true]
        t = true[int(np.argmin(d))]
        assert min(d) <= 2 * VOX, (i, min(d))
        # ... and within 2 voxels of the centroid of the mapped voxels truly of that car
        pad = VOX
        inside = (truth == car) & np.all((xyz >= t.aabb_min - pad) & (xyz <= t.aabb_max + pad), axis=1)
        assert inside.sum() > 0
        assert np.linalg.norm(xyz[inside].mean(0) - i.centroid) <= 2 * VOX, i
        assert np.all(i.box_min <= i.centroid) and np.all(i.centroid <= i.box_max)
        assert 0.5 < i.confidence <= 1.0 and i.voxels >= 3
        assert i.first_seen <= i.last_seen == built["stages"][-1]["frames"]


def _true_car(built, inst) -> str:
    true = built["world"].instances_of(built["car"])
    d = [_box_distance(inst.centroid, t.aabb_min, t.aabb_max) for t in true]
    return true[int(np.argmin(d))].name


def test_ids_stable_while_objects_grow(built):
    stages = built["stages"]
    grew = 0
    for a, b in zip(stages[:-1], stages[1:], strict=True):
        for ib in b["instances"]:
            # previous instances sharing voxels with it: it carries the oldest of their ids,
            # and they were all parts of the same true car (merges join fragments of one object)
            prev = [ia for ia in a["instances"] if np.intersect1d(ia.keys, ib.keys).size]
            if prev:
                oldest = min(prev, key=lambda x: (x.first_seen, x.id))
                assert ib.id == oldest.id and ib.first_seen == oldest.first_seen
                assert ib.observations == oldest.observations + 1
                assert {_true_car(built, x) for x in prev} == {_true_car(built, ib)}
                grew += ib.voxels > oldest.voxels
        for e in b["events"]:
            assert e.kind in ("new", "merge", "grow"), e
        # a grow event for every kept id (one heir) with more voxels, and only for those
        before = {i.id: i.voxels for i in a["instances"]}
        grown = {i.id: i.voxels for i in b["instances"] if i.id in before and i.voxels > before[i.id]}
        merged = {e.id for e in b["events"] if e.kind == "merge"}
        assert {e.id: e.voxels for e in b["events"] if e.kind == "grow"} == {
            k: v for k, v in grown.items() if k not in merged}
    assert grew >= 1
    # per true car found from the first stage on: its oldest id is its id at the end
    first = {}
    for i in stages[0]["instances"]:
        first.setdefault(_true_car(built, i), i.id)
    last = {_true_car(built, i): i.id for i in stages[-1]["instances"]}
    assert first and all(last.get(name) == i for name, i in first.items())
    all_ids = [i.id for s in stages for i in s["instances"]]
    assert len(set(all_ids)) == len({(i.id, i.first_seen) for s in stages for i in s["instances"]})


def test_split_and_merge_events():
    tr = InstanceTracker(0.5)
    bar = np.array([[x, 0, 0] for x in range(10)])
    ev = tr.update("x", bar, np.full(10, 0.9), 1)
    assert [e.kind for e in ev] == ["new"] and tr.current()[0].voxels == 10
    bar_id = tr.current()[0].id
    # cut the bar: 6 + 3 voxels -> the id stays on the 6-voxel part, the other is a split
    cut = np.delete(bar, 6, axis=0)
    ev = tr.update("x", cut, np.full(9, 0.8), 2)
    now = {i.id: i for i in tr.current()}
    assert len(now) == 2 and now[bar_id].voxels == 6
    (split,) = [e for e in ev if e.kind == "split"]
    assert split.parent == bar_id and split.id in now and now[split.id].voxels == 3
    assert split.id > bar_id
    # a new blob far away, then join everything: the oldest id (bar_id) survives
    blob = np.array([[20, 0, 0], [21, 0, 0]])
    tr.update("x", np.concatenate([cut, blob]), np.full(11, 0.8), 3)
    blob_id = max(i.id for i in tr.current())
    joined = np.concatenate([bar, [[x, 0, 0] for x in range(10, 22)]])
    ev = tr.update("x", joined, np.full(len(joined), 0.7), 4)
    (only,) = tr.current()
    assert only.id == bar_id and only.voxels == 22 and only.observations == 4
    (merge,) = [e for e in ev if e.kind == "merge"]
    assert merge.id == bar_id and sorted(merge.merged) == sorted([split.id, blob_id])
    # ids never reused: a fresh object after everything vanished gets a new id
    assert [e.kind for e in tr.update("x", np.zeros((0, 3)), np.zeros(0), 5)] == ["lost"]
    tr.update("x", bar, np.full(10, 0.9), 6)
    assert tr.current()[0].id > blob_id


def test_connected_26_matches_brute_force():
    rng = np.random.default_rng(1)
    ijk = np.unique(rng.integers(-6, 6, (250, 3)), axis=0)
    lab = connected_26(ijk)
    ref = bfs_components(ijk)  # brute force: flood fill over the 26-neighbourhood
    c = ref.max() + 1
    assert lab.max() + 1 == c
    assert np.array_equal(lab[:, None] == lab[None], ref[:, None] == ref[None])
    # a sparse set spread over a large box takes the union-find path: the same labels
    far = np.unique(np.concatenate([ijk, ijk + [5000, 0, 0], rng.integers(-9000, 9000, (300, 3))]), axis=0)
    ref_far = bfs_components(far)
    lab_far = connected_26(far)
    assert np.array_equal(lab_far[:, None] == lab_far[None], ref_far[:, None] == ref_far[None])
    # both paths number components by their lowest voxel key
    from planning.instances import pack_ijk

    keys = pack_ijk(far)
    firsts = [keys[lab_far == k].min() for k in range(lab_far.max() + 1)]
    assert firsts == sorted(firsts)
    dense_first = [pack_ijk(ijk)[lab == k].min() for k in range(lab.max() + 1)]
    assert dense_first == sorted(dense_first)


# ----------------------------------------------------------------------------- look next
def test_look_next_goals_free_in_map_and_world(built):
    w, m, car = built["world"], built["map"], built["car"]
    rl = m.rays()
    rscore = _confidence(rl.features, car)[:, None]
    start = built["poses"][STAGES[-1] - 1][:3, 3]
    goals = look_next(m.occupancy_view(), VOX, m.frontiers().centres.numpy(), rl.origins.numpy(), rl.directions.numpy(),
                      rscore, ["car"], from_xyz=start, max_goals=8, sensing_radius_m=2.0)
    assert len(goals) >= 3
    pos = np.stack([g.position for g in goals])
    st, _ = point_states(m.occupancy_view(), VOX, pos, 0.0)
    assert np.all(st == FREE)
    assert np.all(w.labels_at(pos) == 0)                     # free in the true world as well
    scores = [round(g.score, 3) for g in goals]          # ranked by score to 3 decimals
    assert scores == sorted(scores, reverse=True)
    for g in goals:
        assert np.linalg.norm(g.position - g.frontier) <= 1.0 + 1e-6
        assert -math.pi <= g.heading_rad <= math.pi
        assert g.distance_m == pytest.approx(float(np.linalg.norm(g.position - start)))
        # score = best car score of the rays attached within 1 m (brute force)
        near = np.linalg.norm(rl.origins.numpy() - g.frontier, axis=1) <= 1.0
        assert g.score == pytest.approx(float(rscore[near, 0].max()) if near.any() else 0.0)
        assert (g.target == "car") == (g.score > 0)
    gains = unknown_volume(m.occupancy_view(), VOX, pos[:2], 2.0)
    assert [g.gain_m3 for g in goals[:2]] == pytest.approx(list(gains))
    assert any(g.gain_m3 > 0 for g in goals)


def test_ray_outlier_z_against_scipy():
    """The modified z-score of each ray's cosine per target, against scipy's MAD."""
    from scipy.stats import median_abs_deviation

    rng = np.random.default_rng(2)
    c = rng.normal(0.45, 0.02, (2, 60))
    c[0, 7] = 0.60                                     # one ray reads much more like target 0
    z = ray_outlier_z(c)
    for t in range(2):
        want = 0.6745 * (c[t] - np.median(c[t])) / median_abs_deviation(c[t], scale=1.0)
        assert z[t] == pytest.approx(want, rel=1e-5, abs=1e-5)
    assert int(np.argmax(z[0])) == 7 and z[0, 7] > 3.5 and z[1].max() < 3.5
    assert not ray_outlier_z(c[:, :MIN_RAYS_FOR_Z - 1]).any()         # too few rays: no z
    assert not ray_outlier_z(np.full((1, 40), 0.5)).any()              # no spread: no z
    assert ray_outlier_z(np.zeros((1, 0))).shape == (1, 0)


def test_ray_outlier_z_ignores_deviations_within_the_resolution():
    """A tiny spread (float16 rounding: cosines within ~1e-6 of each other) makes a 1e-4 blip an
    outlier of z ~ 100; with a resolution of 2^-11 only values further than that from the
    median keep their z (unchanged: the MAD is that of all rays), the blip reads 0."""
    rng = np.random.default_rng(5)
    c = rng.normal(0.0, 1e-6, (1, 200))
    c[0, 3], c[0, 9], c[0, 11] = 1e-4, 2e-3, -3e-3          # a rounding blip, a real ray, a real opposite
    plain, floored = ray_outlier_z(c), ray_outlier_z(c, 2.0 ** -11)
    assert plain[0, 3] > 3.5 and (np.abs(plain) > 0).sum() > 150
    assert floored[0, 3] == 0 and np.count_nonzero(floored) == 2
    assert floored[0, [9, 11]] == pytest.approx(plain[0, [9, 11]])
    assert floored[0, 9] > 3.5 > floored[0, 11]


def test_look_next_brings_a_far_outlier_ray_forward(built):
    """With every probability ~0 (a far target), the frontier whose ray stands out (ray_z)
    is examined even when it is the farthest and ranks first; without ray_z it is not even a
    candidate when candidates are few."""
    m = built["map"]
    rl = m.rays()
    o, d = rl.origins.numpy(), rl.directions.numpy()
    f = m.frontiers().centres.numpy()
    start = built["poses"][STAGES[-1] - 1][:3, 3]
    far = int(np.argmax(np.linalg.norm(o - start, axis=1)))         # the ray attached farthest away
    score = np.full((len(o), 1), 1e-12)
    z = np.zeros((len(o), 1))
    z[far] = 6.0
    plain = look_next(m.occupancy_view(), VOX, f, o, d, score, ["water tower"], from_xyz=start, max_goals=3,
                      max_candidates=3, ray_radius_m=1.0)
    goals = look_next(m.occupancy_view(), VOX, f, o, d, score, ["water tower"], from_xyz=start, max_goals=3,
                      max_candidates=3, ray_radius_m=1.0, ray_z=z)
    near_far = np.linalg.norm(f - o[far], axis=1) <= 1.0
    assert near_far.any()
    assert all(g.ray_z == 0 for g in plain)
    assert not any(np.linalg.norm(g.frontier - o[far]) <= 1.0 for g in plain)
    assert goals[0].ray_z == pytest.approx(6.0)                      # brute force: the best z within 1 m
    assert np.linalg.norm(goals[0].frontier - o[far]) <= 1.0 + 1e-6
    assert all(g.ray_z == 0 for g in goals[1:])
    with pytest.raises(ValueError, match="ray_z has shape"):
        look_next(m.occupancy_view(), VOX, f, o, d, score, ["water tower"], ray_z=z[:-1])


def test_look_next_keeps_places_for_the_way_on(built):
    """When more frontiers hold evidence than ``max_goals`` has places, a quarter of the places
    go to the best gain per distance among the goals the ranking leaves out (brute force: the
    whole ranked list, cut by hand); without ``from_xyz`` or with ``explore_share=0`` the list
    is the ranking's head."""
    m = built["map"]
    rl = m.rays()
    o, d = rl.origins.numpy(), rl.directions.numpy()
    f = m.frontiers().centres.numpy()
    start = built["poses"][STAGES[-1] - 1][:3, 3]
    r = np.linalg.norm(o - start, axis=1)
    score = (r > np.median(r)).astype(np.float64)[:, None]          # the far half of the rays see it
    kw = dict(from_xyz=start, max_candidates=100000, ray_radius_m=1.0, sensing_radius_m=2.0)
    every = look_next(m.occupancy_view(), VOX, f, o, d, score, ["car"], max_goals=100000, **kw)
    n = 8
    assert sum(g.score > 0.5 for g in every) > n                    # more evidence than places
    goals = look_next(m.occupancy_view(), VOX, f, o, d, score, ["car"], max_goals=n, **kw)
    rest = sorted(every[n - 2:], key=lambda g: -g.gain_m3 / (1.0 + g.distance_m))[:2]
    key = lambda g: tuple(np.round(g.position, 6))                  # noqa: E731
    assert {key(g) for g in goals} == {key(g) for g in every[:n - 2] + rest}
    assert any(g.score < 0.5 for g in goals)                        # the way on: no evidence, near
    head = look_next(m.occupancy_view(), VOX, f, o, d, score, ["car"], max_goals=n, explore_share=0.0, **kw)
    assert [key(g) for g in head] == [key(g) for g in every[:n]]
    scores = [round(g.score, 3) for g in goals]
    assert scores == sorted(scores, reverse=True)                   # still in rank order


def test_unknown_volume_brute_force(built):
    m = built["map"]
    p = np.array([[1.0, 2.0, 1.2], [5.0, -3.0, 0.5]])
    got = unknown_volume(m.occupancy_view(), VOX, p, 1.0)
    r = 4
    ax = np.arange(-r, r + 1)
    off = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    off = off[np.linalg.norm(off * VOX, axis=1) <= 1.0 + 1e-9]
    for q, g in zip(p, got, strict=True):
        vals = m.occupancy_view().query(torch.as_tensor(np.floor(q / VOX).astype(np.int64) + off)).numpy()
        assert g == pytest.approx((vals == 0).sum() * VOX ** 3)


def test_points_in_polygon():
    sq = [[0, 0], [2, 0], [2, 2], [0, 2]]
    got = points_in_polygon(np.array([[1, 1], [3, 1], [-0.1, 1], [1.9, 1.9]]), sq)
    assert got.tolist() == [True, False, False, True]


# ----------------------------------------------------------------------------- beyond
def test_triangulation_contains_the_crossing_point():
    rng = np.random.default_rng(0)
    target = np.array([30.0, 12.0, 2.0])
    origins = np.array([[0.0, 0.0, 1.0], [5.0, -8.0, 1.0], [-3.0, 9.0, 1.5]])
    err = 3.0
    dirs = []
    for o in origins:
        d = target - o
        d /= np.linalg.norm(d)
        # perturb by up to err degrees
        axis = np.cross(d, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        a = math.radians(err) * 0.9
        dirs.append(d * math.cos(a) + np.cross(axis, d) * math.sin(a))
    dirs = np.array(dirs)
    est = triangulate(origins, dirs, np.array([0.9, 0.8, 0.7]), max_gap_m=10.0, angle_err_deg=err)
    assert est
    assert np.linalg.norm(est[0].position - target) <= est[0].radius_m
    assert est[0].score == pytest.approx(0.8)
    # exact rays: the estimate is the point itself
    exact = (target - origins[:2]) / np.linalg.norm(target - origins[:2], axis=1, keepdims=True)
    (e,) = triangulate(origins[:2], exact, np.ones(2), angle_err_deg=0.0)
    assert np.allclose(e.position, target, atol=1e-9) and e.radius_m < 1e-9
    # rays pointing away from the crossing (behind an origin) or parallel give nothing
    assert triangulate(origins[:2], -exact, np.ones(2)) == []
    assert triangulate(origins[:2], np.array([[1.0, 0, 0], [1.0, 0, 0]]), np.ones(2)) == []
    t1, t2, gap = closest_approach(origins[0], exact[0], origins[1], exact[1])
    assert gap < 1e-9 and t1 == pytest.approx(np.linalg.norm(target - origins[0]))
    assert best_rays(np.array([0.1, 0.5, 0.5, 0.9]), 3).tolist() == [3, 1, 2]


# ----------------------------------------------------------------------------- occupancy
def _cam(built) -> np.ndarray:
    """Camera position (m) at the last mapped frame."""
    return built["poses"][STAGES[-1] - 1][:3, 3].astype(np.float64)


def _brute_states(m, ijk: np.ndarray) -> np.ndarray:
    v = m.occupancy_view().query(torch.as_tensor(ijk)).numpy()
    return np.where(v > 0, OCCUPIED, np.where(v < 0, FREE, UNKNOWN))


def test_state_grid_equals_map_occupancy(built):
    m = built["map"]
    c = _cam(built)
    lo, hi = c + np.array([-4.0, -3.1, -2.0]), c + np.array([3.0, 2.0, 1.1])
    g, origin, cell = state_grid(m.occupancy_view(), VOX, lo, hi)
    assert cell == VOX and np.allclose(origin, np.floor(lo / VOX) * VOX)
    i0 = np.floor(lo / VOX).astype(np.int64)
    idx = np.argwhere(np.ones(g.shape, bool))
    assert np.array_equal(g.reshape(-1), _brute_states(m, idx + i0))
    assert {FREE, OCCUPIED, UNKNOWN} <= set(np.unique(g).tolist())
    assert np.all(origin + np.array(g.shape) * cell >= hi)
    # stride 2: occupied if any, free if all free, else unknown
    g2, o2, c2 = state_grid(m.occupancy_view(), VOX, lo, hi, stride=2)
    assert c2 == 2 * VOX and np.allclose(o2, origin)
    for c in np.argwhere(np.ones(g2.shape, bool))[::7]:
        sub = _brute_states(m, np.argwhere(np.ones((2, 2, 2), bool)) + i0 + 2 * c)
        want = OCCUPIED if (sub == OCCUPIED).any() else FREE if (sub == FREE).all() else UNKNOWN
        assert g2[tuple(c)] == want


def test_costmap_slice_brute_force(built):
    m = built["map"]
    c = _cam(built)[:2]
    cm, origin, cell = costmap_slice(m.occupancy_view(), VOX, c - 4.0, c + 4.0, (0.7, 1.6), stride=2)
    assert {FREE, OCCUPIED, UNKNOWN} <= set(np.unique(cm).tolist())
    k0, k1 = math.floor(0.7 / VOX), math.floor(1.6 / VOX)
    i0 = np.floor((c - 4.0) / VOX).astype(np.int64)
    for c in np.argwhere(np.ones(cm.shape, bool))[::3]:
        cells = np.array([[i0[0] + 2 * c[0] + a, i0[1] + 2 * c[1] + b, k] for a in (0, 1) for b in (0, 1)
                          for k in range(k0, k1 + 1)])
        sub = _brute_states(m, cells)
        want = OCCUPIED if (sub == OCCUPIED).any() else FREE if (sub == FREE).all() else UNKNOWN
        assert cm[tuple(c)] == want
    assert cell == 2 * VOX and np.allclose(origin, i0 * VOX)


def test_point_states_brute_force(built):
    m = built["map"]
    rng = np.random.default_rng(2)
    pts = _cam(built) + rng.uniform([-6, -6, -1.5], [6, 6, 1.5], (40, 3))
    st, dist = point_states(m.occupancy_view(), VOX, pts, 1.0)
    assert np.array_equal(st, _brute_states(m, np.floor(pts / VOX).astype(np.int64)))
    ijk, val = m.occupancy_view().active()
    occ = ijk.numpy()[val.numpy() > 0]
    lo = occ * VOX
    for p, s, d in zip(pts, st, dist, strict=True):
        dd = np.linalg.norm(np.maximum(np.maximum(lo - p, p - (lo + VOX)), 0), axis=1).min()
        assert (d == pytest.approx(dd)) if dd <= 1.0 else d == np.inf
        if s == OCCUPIED:
            assert d == 0.0
    assert np.isfinite(dist).any()


def test_occupancy_requests_over_the_limit_raise(built):
    m = built["map"]
    with pytest.raises(ValueError, match="limit of 4000000 cells"):
        state_grid(m.occupancy_view(), VOX, [-500, -500, 0], [500, 500, 10])
    with pytest.raises(ValueError, match="limit of 1000 cells"):
        costmap_slice(m.occupancy_view(), VOX, [0, 0], [30, 30], (0, 1), max_cells=1000)
    with pytest.raises(ValueError, match="stride"):
        state_grid(m.occupancy_view(), VOX, [0, 0, 0], [1, 1, 1], stride=0)
    with pytest.raises(ValueError, match="limit"):
        point_states(m.occupancy_view(), VOX, np.zeros((10, 3)), 50.0)
    assert voxel_center(np.zeros((1, 3), np.int64), VOX).shape == (1, 3)


def test_car_count_is_the_true_cars_seen(built):
    """"How many cars have we seen" from instances: one instance per true car of which the map
    holds at least ``min_voxels`` voxels truly of that car."""
    w, m, car = built["world"], built["map"], built["car"]
    truth = w.voxel_labels(m.voxel_ijk().numpy(), VOX)
    xyz = m.voxel_xyz().numpy().astype(np.float64)
    seen = set()
    for t in w.instances_of(car):
        inside = (truth == car) & np.all((xyz >= t.aabb_min - VOX) & (xyz <= t.aabb_max + VOX), axis=1)
        if inside.sum() >= 3:
            seen.add(t.name)
    inst = built["stages"][-1]["instances"]
    assert seen and len(inst) == len(seen), (len(inst), sorted(seen))
    assert {_true_car(built, i) for i in inst} == seen


def test_look_next_goals_reachable_through_known_free_space(built):
    """Every goal can be reached from the robot's last position moving through cells the map
    knows to be free (6-connected breadth-first search on the map's occupancy)."""
    from collections import deque

    m, w = built["map"], built["world"]
    rl = m.rays()
    start = built["poses"][STAGES[-1] - 1][:3, 3].astype(np.float64)
    goals = look_next(m.occupancy_view(), VOX, m.frontiers().centres.numpy(), rl.origins.numpy(), rl.directions.numpy(),
                      _confidence(rl.features, built["car"])[:, None], ["car"], from_xyz=start, max_goals=8)
    assert goals
    pts = np.vstack([start] + [g.position for g in goals])
    lo, hi = pts.min(0) - 6.0, pts.max(0) + 6.0
    lo[2], hi[2] = 0.0, max(hi[2], 4.0)
    states, origin, cell = state_grid(m.occupancy_view(), VOX, lo, hi)
    free = states == FREE

    def cell_of(p):
        return tuple(np.floor((np.asarray(p) - origin) / cell).astype(int))

    s = cell_of(start)
    assert free[s], "the robot's own cell is free"
    seen = np.zeros_like(free)
    seen[s] = True
    todo = deque([s])
    while todo:
        c = todo.popleft()
        for a in range(3):
            for d in (-1, 1):
                n = list(c)
                n[a] += d
                n = tuple(n)
                if all(0 <= n[k] < free.shape[k] for k in range(3)) and free[n] and not seen[n]:
                    seen[n] = True
                    todo.append(n)
    for g in goals:
        assert seen[cell_of(g.position)], g
    assert np.all(w.labels_at(np.stack([g.position for g in goals])) == 0)


def test_far_target_seen_only_beyond_range():
    """A constructed scene: a target 40 m away seen from three places only beyond the 10 m
    depth range (every depth +inf, so the map holds no voxel of it). The goals whose rays
    point at it rank first and face it, and the rays from different places triangulate to an
    estimate that contains the true position within its stated radius."""
    H, W = 48, 64
    f = W / 2 / math.tan(math.radians(45))
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    target = np.array([40.0, 0.0, 2.0])
    R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)      # camera looks along +x (RDF)
    cfg = map_config("default", dict(vox_size=0.5, depth_limit=10.0, angle_bin_size=10.0))
    m = RayFrontsMap(cfg, 2, "toy", occupancy_backend="torch")
    cams = [np.array([0.0, -6.0, 1.5]), np.array([0.0, 6.0, 1.5]), np.array([-4.0, 0.0, 1.5])]
    for c in cams:
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = R, c
        pc = R.T @ (target - c)
        u, v = int(K[0, 0] * pc[0] / pc[2] + K[0, 2]), int(K[1, 1] * pc[1] / pc[2] + K[1, 2])
        depth = np.full((H, W), np.inf, np.float32)
        depth[H // 2 + 6:] = np.nan                                  # nothing measured below
        feat = np.zeros((2, H, W), np.float32)
        feat[0] = 1.0                                                # class 0: background
        feat[:, v - 5:v + 6, u - 5:u + 6] = np.array([0.0, 1.0], np.float32)[:, None, None]
        for _ in range(3):
            m.integrate(pose, K, depth, np.zeros((H, W, 3), np.uint8), torch.as_tensor(feat))
    m.flush()
    assert m.n_voxels() == 0                                           # nothing of it in range
    rl = m.rays()
    rf = rl.features.float()
    conf = (rf[:, 1] / rf.sum(1).clamp_min(1e-9)).numpy()
    goals = look_next(m.occupancy_view(), 0.5, m.frontiers().centres.numpy(), rl.origins.numpy(), rl.directions.numpy(),
                      conf[:, None], ["tower"], from_xyz=cams[0], max_goals=5)
    assert goals[0].score > 0.5 and goals[0].score == max(g.score for g in goals)
    for g in goals:
        if g.score > 0.5:                                            # the goals toward it face it
            d = target[:2] - g.position[:2]
            err = abs((g.heading_rad - math.atan2(d[1], d[0]) + math.pi) % (2 * math.pi) - math.pi)
            assert err < math.radians(20), (g, err)
    idx = best_rays(conf, 20)
    est = triangulate(rl.origins.numpy()[idx], rl.directions.numpy()[idx], conf[idx], max_gap_m=2.0,
                      angle_err_deg=cfg.angle_bin_size / 2)
    assert est and np.linalg.norm(est[0].position - target) <= est[0].radius_m < 25.0, est[:1]
