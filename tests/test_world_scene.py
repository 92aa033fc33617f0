"""The generated town: determinism, classes, trajectories, landmark placement, visibility,
and rendered labels against the solid-membership ground truth."""
from __future__ import annotations

import numpy as np
import pytest

from common.conventions import is_rigid, sanitize_depth
from common.geometry import camera_rays, scale_intrinsics
from synthetic_world import FAR_CLASSES, IN_RANGE_CLASSES, World


@pytest.fixture(scope="module")
def world():
    return World.generate(seed=0)


@pytest.fixture(scope="module")
def ground_views(world):
    hw = (96, 128)
    K = world.camera(hw, 90.0)
    poses = world.trajectory("ground", 60)
    return hw, K, poses, [world.render(p, K, hw) for p in poses]


def test_classes_and_instances(world):
    assert world.classes[0] == "sky" and len(world.classes) >= 10
    for name in ("ground", "road", "building", "tree", "car", "fence", "chimney", "street lamp",
                 "water tower", "radio tower"):
        assert world.classes[world.class_id(name)] == name
    with pytest.raises(ValueError, match="radio tower"):
        world.class_id("antenna mast")
    ids = [i.id for i in world.instances]
    assert ids == list(range(len(ids)))
    for c in IN_RANGE_CLASSES:
        assert len(world.instances_of(world.class_id(c))) >= 3, c
    assert 100 <= world.n_primitives <= 400
    lo, hi = world.bounds
    for inst in world.instances:
        assert np.all(inst.aabb_min >= lo - 1e-9) and np.all(inst.aabb_max <= hi + 1e-9)
        assert np.all(inst.aabb_min <= inst.center) and np.all(inst.center <= inst.aabb_max)
    assert hi[0] - lo[0] <= 1000 and hi[2] >= 50  # finite ground square, a tall tower


def test_generation_and_rendering_are_deterministic_by_seed():
    a, b, c = World.generate(5), World.generate(5), World.generate(6)
    assert [p for p in a.parts] == [p for p in b.parts]
    assert [p for p in a.parts] != [p for p in c.parts]
    pa, pb, pc = a.trajectory("ground", 10), b.trajectory("ground", 10), c.trajectory("ground", 10)
    np.testing.assert_array_equal(pa, pb)
    assert not np.allclose(pa, pc)
    K = a.camera((40, 60))
    ra, rb = a.render(pa[3], K, (40, 60)), b.render(pb[3], K, (40, 60))
    for f in ("rgb", "depth", "labels", "instance"):
        np.testing.assert_array_equal(getattr(ra, f), getattr(rb, f))
    assert not np.array_equal(ra.rgb, c.render(pa[3], K, (40, 60)).rgb)
    with pytest.raises(ValueError, match="presets"):
        World.generate(0, preset="jungle")


def test_render_outputs_follow_conventions(world, ground_views):
    hw, K, poses, views = ground_views
    r = views[0]
    assert r.rgb.shape == (*hw, 3) and r.rgb.dtype == np.uint8
    assert r.depth.shape == hw and r.depth.dtype == np.float32
    assert r.labels.dtype == np.int32 and r.instance.dtype == np.int32
    for v in views:
        sky = v.labels == 0
        assert np.all(np.isinf(v.depth[sky])) and np.all(v.instance[sky] == -1)
        assert np.all(np.isfinite(v.depth[~sky])) and np.all(v.depth[~sky] > 0)
        cls_of_inst = np.array([i.class_id for i in world.instances])
        assert np.all(cls_of_inst[v.instance[~sky]] == v.labels[~sky])
    # any resolution: at 3x, pixel (3r+1, 3c+1) looks through the same ray as pixel (r, c)
    hi_hw = (3 * hw[0], 3 * hw[1])
    big = world.render(poses[5], scale_intrinsics(K, hw, hi_hw), hi_hw)
    small = views[5]
    np.testing.assert_allclose(big.depth[1::3, 1::3], small.depth, rtol=1e-6)
    assert (big.labels[1::3, 1::3] == small.labels).mean() > 0.999


def test_trajectories_are_smooth_rigid_and_in_free_space(world):
    g = world.trajectory("ground", 150)
    d = world.trajectory("drone", 150)
    for poses in (g, d):
        assert poses.shape == (150, 4, 4) and poses.dtype == np.float64
        assert all(is_rigid(p) for p in poses)
        assert np.all(world.labels_at(poses[:, :3, 3]) == 0)  # camera never inside a solid
        fwd = poses[:, :3, 2]
        turn = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], 1), -1, 1)))
        assert turn.max() < 20.0
        step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        assert step.max() < 3.0
    np.testing.assert_allclose(g[:, 2, 3], 1.52, atol=1e-9)
    assert np.all(np.abs(np.degrees(np.arcsin(g[:, 2, 2]))) < 5)  # roughly level
    assert np.all((d[:, 2, 3] >= 8) & (d[:, 2, 3] <= 20))
    pitch = -np.degrees(np.arcsin(d[:, 2, 2]))
    assert np.all((pitch >= 15) & (pitch <= 30))
    # the camera's right axis stays horizontal (no roll)
    np.testing.assert_allclose(g[:, 2, 0], 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="presets"):
        world.trajectory("submarine", 3)
    with pytest.raises(ValueError, match="positive"):
        world.trajectory("ground", 0)


def test_far_landmarks_are_beyond_100m_of_every_pose(world):
    for preset in ("ground", "drone"):
        eyes = world.trajectory(preset, 300)[:, :3, 3]
        for name in FAR_CLASSES:
            assert world.distance_to_class(eyes, world.class_id(name)).min() >= 100.0, name
        far = [i for i in world.instances if i.name in world.layout.extra["far_instances"]]
        assert len(far) >= 5
        for inst in far:  # AABB distance is a lower bound of the true distance
            gap = np.maximum(np.maximum(inst.aabb_min - eyes, eyes - inst.aabb_max), 0.0)
            assert np.linalg.norm(gap, axis=1).min() >= 100.0, inst.name


def test_ground_trajectory_sees_near_classes_within_20m_and_far_landmarks(world, ground_views):
    _, _, _, views = ground_views
    near, far = set(), set()
    for v in views:
        d20 = sanitize_depth(v.depth, 20.0)
        near |= set(np.unique(v.labels[np.isfinite(d20)]).tolist())
        far |= set(np.unique(v.labels[np.isfinite(v.depth) & (v.depth >= 100.0)]).tolist())
    for c in IN_RANGE_CLASSES:
        assert world.class_id(c) in near, f"{c} never within 20 m"
    for c in FAR_CLASSES:
        assert world.class_id(c) in far, f"{c} never seen"
        assert world.class_id(c) not in near


def test_rendered_labels_match_solid_membership(world, ground_views):
    hw, K, poses, views = ground_views
    rays = camera_rays(K, *hw)
    agree, empty = [], []
    for p, v in zip(poses[::3], views[::3], strict=True):
        m = np.isfinite(v.depth)
        d = rays[m] @ p[:3, :3].T
        du = d / np.linalg.norm(d, axis=1, keepdims=True)
        pts = p[:3, 3] + d * v.depth[m][:, None].astype(np.float64)
        agree.append(world.labels_at(pts + 1e-4 * du) == v.labels[m])  # just inside the hit surface
        empty.append(world.labels_at(pts - 1e-3 * du) == 0)           # just in front of it
    agree, empty = np.concatenate(agree), np.concatenate(empty)
    assert agree.size > 50_000
    assert agree.mean() > 0.9999, (~agree).sum()  # float32 depth rounding at touching solids
    assert empty.mean() > 0.9999


def test_voxel_labels_of_generated_world_match_point_samples(world):
    vox = 0.5
    rng = np.random.default_rng(0)
    building = next(i for i in world.instances if world.classes[i.class_id] == "building")
    pts = rng.uniform(building.aabb_min - 2, building.aabb_max + 2, size=(400, 3))
    ijk = np.floor(pts / vox).astype(np.int64)
    got = world.voxel_labels(ijk, vox, samples=1)  # 1 sample = the voxel centre
    np.testing.assert_array_equal(got, world.labels_at((ijk + 0.5) * vox))
    assert (got == building.class_id).sum() > 20
