"""The pybullet world (synthetic_world/pybullet_world.py), a world this project did not
write: its rendered depth, back-projected with its intrinsics and pose, lands on the assets'
surfaces as pybullet's own ray test finds them; its labels and instances are the
segmentation mask's bodies; its free space holds the assets' surfaces; the edge's
``source.kind=pybullet`` renders it at the poses a simulator sends."""
from __future__ import annotations

import numpy as np
import pytest

from apps.closed_loop.robot import camera_pose
from synthetic_world.pybullet_assets import ASSETS, CLASS_NAMES

HW = (96, 96)


@pytest.fixture(scope="module")
def world():
    from synthetic_world.pybullet_world import PybulletWorld

    w = PybulletWorld.generate(0)
    yield w
    w.close()


def _views(world) -> list[np.ndarray]:
    """Camera poses 5 m from one object of four classes, looking at it, where a ground robot's
    body is free (a camera inside a one-sided mesh sees nothing of it: the renderer culls
    back faces, the ray test does not)."""
    from apps.closed_loop.robot import Platform

    body = Platform.make("ground")
    out = []
    for name in ("teddy bear", "shelf", "r2d2", "husky"):
        c = world.instances_of(world.class_id(name))[0].center
        for yaw in np.arange(8) * np.pi / 4:
            at = np.array([c[0] - 5.0 * np.cos(yaw), c[1] - 5.0 * np.sin(yaw), 1.5])
            if not (world.labels_at(body.body_points(at, 0.5)) != 0).any():
                out.append(camera_pose(at, yaw, 0.25))
                break
    assert len(out) == 4
    return out


def _back_project(depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) world m, mask (H, W)) of the finite-depth pixels, pixel centres at +½."""
    v, u = np.mgrid[0:depth.shape[0], 0:depth.shape[1]]
    ok = np.isfinite(depth)
    z = depth[ok].astype(np.float64)
    cam = np.stack([(u[ok] + 0.5 - K[0, 2]) / K[0, 0] * z, (v[ok] + 0.5 - K[1, 2]) / K[1, 1] * z, z])
    return (pose[:3, :3] @ cam).T + pose[:3, 3], ok


def test_depth_lands_on_the_surfaces_pybullet_ray_test_finds(world):
    """For four views (objects, ground, monastery, landmarks in view): every pixel with a
    surface, back-projected with the world's K and the pose, lies where pybullet's
    ``rayTestBatch`` along the same ray (collision shapes: an independent path) first hits
    something — within 2 cm + 0.2 % of the range for 97 % of the pixels (the rest: the
    silhouettes of assets whose visual mesh differs from their collision shape) and with
    the same class for 95 %."""
    K = world.camera(HW, 90.0)
    seen = set()
    for pose in _views(world):
        r = world.render(pose, K, HW)
        P, ok = _back_project(r.depth, K, pose)
        assert ok.sum() > 0.5 * ok.size                 # the view has surfaces to check
        o = pose[:3, 3]
        d = P - o
        rng = np.linalg.norm(d, axis=1)
        hit, cls = world.ray_test(np.repeat(o[None], len(P), 0), o + d / rng[:, None] * (rng[:, None] + 2.0))
        err = np.linalg.norm(hit - P, axis=1)
        good = np.nan_to_num(err, nan=np.inf) <= 0.02 + 0.002 * rng
        assert good.mean() >= 0.97, (good.mean(), np.nanmedian(err))
        assert (cls == r.labels[ok]).mean() >= 0.95
        seen |= set(np.unique(r.labels[ok]).tolist())
    assert {world.class_id(n) for n in ("ground", "monastery", "teddy bear", "shelf", "r2d2", "husky")} <= seen


def test_labels_and_instances_equal_the_segmentation_mask(world):
    """``labels`` and ``instance`` are the segmentation mask's body ids mapped through the
    world's bodies (read here from pybullet: body i is instance i, its class the asset's;
    the last body, the monastery's visual-only back faces, is the monastery), pixel for
    pixel; −1 (no body) is class 0 (sky) and instance −1."""
    import pybullet as p

    K = world.camera(HW, 90.0)
    assert world.classes == list(CLASS_NAMES) and world.classes[0] == "sky"
    n_bodies = p.getNumBodies(physicsClientId=world.cid)
    assert n_bodies - 1 == len(world.instances) == sum(a.count if a.role == "object" else 1 for a in ASSETS)
    monastery = next(i for i in world.instances if world.classes[i.class_id] == "monastery")
    twin = n_bodies - 1
    for pose in _views(world)[:2] + [camera_pose(np.array([0.0, -60.0, 1.5]), np.pi / 2, -0.2)]:
        r = world.render(pose, K, HW)
        view, proj = world.gl_matrices(pose, K, HW)
        seg = np.asarray(p.getCameraImage(HW[1], HW[0], view, proj, renderer=p.ER_TINY_RENDERER,
                                          physicsClientId=world.cid)[4]).reshape(HW)
        assert (seg >= 0).sum() > 100 and (seg == -1).sum() > 0 or (seg >= 0).all()
        for uid in np.unique(seg):
            m = seg == uid
            if uid < 0:
                assert (r.labels[m] == 0).all() and (r.instance[m] == -1).all()
                continue
            inst = monastery if uid == twin else world.instances[int(uid)]
            assert (r.instance[m] == inst.id).all() and (r.labels[m] == inst.class_id).all()
            assert p.getBodyUniqueId(int(uid), physicsClientId=world.cid) == uid


def test_free_space_holds_the_assets_surfaces(world):
    """``labels_at`` (the voxelised collision shapes): points on each object's surface (where
    downward ray tests hit it) are solid with the object's class; points 1.5 m above the
    site's open ground and below z = 0 are what they are (free, ground)."""
    for inst in world.instances:
        name = world.classes[inst.class_id]
        if name in ("ground", "monastery") or "statue" in name:
            continue
        xy = np.random.default_rng(inst.id).uniform(inst.aabb_min[:2], inst.aabb_max[:2], (40, 2))
        top = np.c_[xy, np.full(len(xy), inst.aabb_max[2] + 1.0)]
        hit, cls = world.ray_test(top, np.c_[xy, np.full(len(xy), -0.5)])
        on = cls == inst.class_id
        assert on.sum() >= 5, name                        # something of the object to check
        assert (world.labels_at(hit[on]) == inst.class_id).all(), name
    ground = world.class_id("ground")
    assert (world.labels_at(np.array([[0.0, 0.0, -0.3], [50.0, 50.0, -2.0]])) == ground).all()
    sky = np.array([[0.0, 0.0, 45.0], [120.0, -120.0, 1.5]])
    assert (world.labels_at(sky) == 0).all()


def test_edge_source_pybullet_renders_the_poses_it_is_sent(world):
    """``source.kind=pybullet`` is the sim_camera source with the pybullet world: a step of
    poses put on the robot's sim-views key (through the source's own callback) comes out as
    frames at those poses whose depth and labels equal the world's render."""
    from common.messages import encode_sim_views
    from edge.sources import SourceConfig, open_source

    src = open_source(SourceConfig(kind="pybullet", seed=0, resolution="96x96"))
    assert src.class_names == list(CLASS_NAMES) and src.name.startswith("pybullet:seed0")
    poses = _views(world)[:2]

    class Sample:
        payload = type("P", (), {"to_bytes": staticmethod(lambda: encode_sim_views(3, poses))})()

    src._on_sample(Sample())
    step, pz = src._steps.popleft()
    frames = [src._finish(src._render(step, k, pose), k) for k, pose in enumerate(pz)]
    assert len(frames) == 2
    K = world.camera(HW, 90.0)
    for f, pose in zip(frames, poses, strict=True):
        r = world.render(pose, K, HW)
        assert np.allclose(f.pose, pose)
        assert np.array_equal(f.labels, r.labels)
        assert np.array_equal(np.isinf(f.depth), np.isinf(r.depth))
        assert np.allclose(f.depth[np.isfinite(f.depth)], r.depth[np.isfinite(r.depth)])
