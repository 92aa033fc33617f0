"""Synthetic world geometry against closed-form and brute-force references."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from common.geometry import intrinsics_from_fov, pixel_grid
from synthetic_world import Box, Cone, Cylinder, Part, Sphere, World

CLASSES = ["sky", "ground", "thing", "other"]


def _pose(R_cols, eye):
    """Camera-to-world pose from explicit right/down/forward world vectors."""
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = R_cols
    T[:3, 3] = eye
    return T


def _forward_x_pose(eye=(0.0, 0.0, 0.0), pitch=0.0):
    """Camera looking along +x, pitched down by ``pitch`` rad (independent of look_at)."""
    s, c = np.sin(pitch), np.cos(pitch)
    return _pose(((0.0, -1.0, 0.0), (-s, 0.0, -c), (c, 0.0, -s)), eye)


def _norm_coords(K, h, w):
    u, v = pixel_grid(h, w)
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def test_ground_plane_planar_depth_closed_form():
    h_cam, pitch = 1.7, np.deg2rad(12.0)
    world = World.from_primitives([Part(Box((0.0, 0.0, -1.0), (1000.0, 1000.0, 1.0)), "ground", "g")], CLASSES)
    H, W = 60, 80
    K = intrinsics_from_fov(90.0, H, W)
    r = world.render(_forward_x_pose((0.0, 0.0, h_cam), pitch), K, (H, W))
    _, yn = _norm_coords(K, H, W)
    denom = np.sin(pitch) + yn * np.cos(pitch)
    with np.errstate(divide="ignore"):
        expected = np.where(denom > 0, h_cam / denom, np.inf)
    near = expected < 300.0  # well inside the 1000 m ground square
    assert near.sum() > 0.4 * H * W
    np.testing.assert_allclose(r.depth[near], expected[near], rtol=1e-6)
    assert np.all(np.isinf(r.depth[denom <= 0]))
    assert np.all(r.labels[near] == 1) and np.all(r.labels[denom <= 0] == 0)
    assert np.all(r.instance[denom <= 0] == -1) and np.all(r.instance[near] == 0)


def test_box_face_depth_is_planar_constant():
    world = World.from_primitives([Part(Box((12.0, 0.0, 0.0), (2.0, 3.0, 2.0)), "thing", "b")], CLASSES)
    H, W = 50, 70
    K = intrinsics_from_fov(80.0, H, W)
    r = world.render(_forward_x_pose(), K, (H, W))
    xn, yn = _norm_coords(K, H, W)
    wy, wz = -xn * 10.0, -yn * 10.0  # world y, z where the ray meets the plane x = 10
    inside = (np.abs(wy) < 2.95) & (np.abs(wz) < 1.95)
    outside = (np.abs(wy) > 3.05 * 1.2) | (np.abs(wz) > 2.05 * 1.2)  # misses even the back face
    assert inside.sum() > 100 and outside.sum() > 100
    np.testing.assert_allclose(r.depth[inside], 10.0, rtol=1e-12)
    assert np.all(np.isinf(r.depth[outside])) and np.all(r.labels[inside] == 2)


def test_yawed_box_hits_lie_on_its_surface():
    yaw = np.deg2rad(35.0)
    center, half = np.array([9.0, 1.0, 0.5]), np.array([2.0, 1.0, 1.5])
    world = World.from_primitives([Part(Box(tuple(center), tuple(half), yaw), "thing", "b")], CLASSES)
    H, W = 60, 80
    K = intrinsics_from_fov(90.0, H, W)
    r = world.render(_forward_x_pose(), K, (H, W))
    m = np.isfinite(r.depth)
    assert m.sum() > 200
    xn, yn = _norm_coords(K, H, W)
    z = r.depth[m].astype(np.float64)
    pts = np.stack([z, -xn[m] * z, -yn[m] * z], -1) - center  # world = (fwd, -right, -down)
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.stack([c * pts[:, 0] + s * pts[:, 1], -s * pts[:, 0] + c * pts[:, 1], pts[:, 2]], -1)
    ratio = np.max(np.abs(local) / half, axis=1)
    np.testing.assert_allclose(ratio, 1.0, atol=2e-6)  # float32 depth rounding


def test_sphere_depth_closed_form():
    D, rad = 15.0, 3.0
    world = World.from_primitives([Part(Sphere((D, 0.0, 0.0), rad), "thing", "s")], CLASSES)
    H, W = 61, 61
    K = intrinsics_from_fov(40.0, H, W)
    r = world.render(_forward_x_pose(), K, (H, W))
    xn, yn = _norm_coords(K, H, W)
    cos_a = 1.0 / np.sqrt(1 + xn ** 2 + yn ** 2)
    sin2 = 1 - cos_a ** 2
    disc = rad ** 2 - D ** 2 * sin2
    hit = disc > 0.05
    expected = (D * cos_a - np.sqrt(np.maximum(disc, 0))) * cos_a
    assert hit.sum() > 50 and (disc < -0.05).sum() > 50
    np.testing.assert_allclose(r.depth[hit], expected[hit], rtol=1e-6)
    assert np.all(np.isinf(r.depth[disc < -0.05]))
    assert abs(r.depth[30, 30] - (D - rad)) < 1e-3  # centre pixel


def test_cylinder_depth_closed_form():
    D, rad = 10.0, 1.5
    world = World.from_primitives([Part(Cylinder(D, 0.0, -5.0, 5.0, rad), "thing", "c")], CLASSES)
    H, W = 60, 90
    K = intrinsics_from_fov(60.0, H, W)
    r = world.render(_forward_x_pose(), K, (H, W))
    xn, yn = _norm_coords(K, H, W)
    beta = np.arctan(xn)
    disc = rad ** 2 - D ** 2 * np.sin(beta) ** 2
    planar = (D * np.cos(beta) - np.sqrt(np.maximum(disc, 0))) * np.cos(beta)
    zhit = -yn * planar
    ok = (disc > 0.02) & (np.abs(zhit) < 4.9)
    assert ok.sum() > 100
    np.testing.assert_allclose(r.depth[ok], planar[ok], rtol=1e-6)
    assert np.all(np.isinf(r.depth[disc < -0.02]))


def test_cone_hits_lie_on_its_lateral_surface_or_base():
    r0, hgt = 2.0, 6.0
    world = World.from_primitives([Part(Cone(8.0, 0.0, 0.0, hgt, r0), "thing", "c")], CLASSES)
    H, W = 60, 80
    K = intrinsics_from_fov(90.0, H, W)
    r = world.render(_forward_x_pose((0.0, 0.0, 2.0), np.deg2rad(5)), K, (H, W))
    m = np.isfinite(r.depth)
    assert m.sum() > 100
    xn, yn = _norm_coords(K, H, W)
    pitch = np.deg2rad(5)
    s, c = np.sin(pitch), np.cos(pitch)
    z = r.depth[m].astype(np.float64)
    # world = eye + z * (fwd + xn * right + yn * down)
    px = z * (c - yn[m] * s)
    py = -xn[m] * z
    pz = 2.0 + z * (-s - yn[m] * c)
    rho = np.hypot(px - 8.0, py)
    on_side = np.abs(rho - r0 * (1 - pz / hgt)) < 1e-4
    assert np.all(on_side | (np.abs(pz) < 1e-5))
    assert on_side.mean() > 0.95  # seen from above the base: mostly the lateral surface


# ------------------------------------------------------------------ dense surface samples


def _box_surface(center, half, yaw, step):
    pts = []
    for ax in range(3):
        o1, o2 = [a for a in range(3) if a != ax]
        g1 = np.arange(-half[o1], half[o1] + 1e-9, step)
        g2 = np.arange(-half[o2], half[o2] + 1e-9, step)
        a, b = np.meshgrid(g1, g2, indexing="ij")
        for sgn in (-1, 1):
            p = np.zeros((a.size, 3))
            p[:, ax] = sgn * half[ax]
            p[:, o1], p[:, o2] = a.ravel(), b.ravel()
            pts.append(p)
    p = np.concatenate(pts)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]], -1) + center


def _frustum_surface(cx, cy, z0, z1, r0, r1, step):
    pts = []
    for z in np.arange(z0, z1 + 1e-9, step):
        rr_ = r0 + (r1 - r0) * (z - z0) / (z1 - z0)
        n = max(int(2 * np.pi * rr_ / step), 1)
        th = np.arange(n) * 2 * np.pi / n
        pts.append(np.stack([cx + rr_ * np.cos(th), cy + rr_ * np.sin(th), np.full(n, z)], -1))
    for z, rc in ((z0, r0), (z1, r1)):
        g = np.arange(-rc, rc + 1e-9, step)
        a, b = np.meshgrid(g, g)
        m = a ** 2 + b ** 2 <= rc ** 2
        pts.append(np.stack([cx + a[m], cy + b[m], np.full(m.sum(), z)], -1))
    return np.concatenate(pts)


def _sphere_surface(center, rad, step):
    n = int(4 * np.pi * rad ** 2 / step ** 2) + 1
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5 ** 0.5) * i
    return np.asarray(center) + rad * np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], -1)


STEP = 0.02


@pytest.fixture(scope="module")
def mixed():
    parts = [
        Part(Box((1.0, 2.0, 0.5), (0.8, 0.4, 0.5), np.deg2rad(25)), "thing", "box"),
        Part(Cylinder(-1.5, 0.0, 0.0, 1.5, 0.4), "thing", "cyl"),
        Part(Cone(0.5, -2.0, 0.2, 1.8, 0.7, 0.2), "thing", "frustum"),
        Part(Sphere((-1.0, 2.5, 1.0), 0.6), "other", "ball"),
    ]
    surf_thing = np.concatenate([
        _box_surface(np.array([1.0, 2.0, 0.5]), (0.8, 0.4, 0.5), np.deg2rad(25), STEP),
        _frustum_surface(-1.5, 0.0, 0.0, 1.5, 0.4, 0.4, STEP),
        _frustum_surface(0.5, -2.0, 0.2, 1.8, 0.7, 0.2, STEP),
    ])
    surf_other = _sphere_surface((-1.0, 2.5, 1.0), 0.6, STEP)
    return World.from_primitives(parts, CLASSES), {2: cKDTree(surf_thing), 3: cKDTree(surf_other)}


def test_distance_to_class_matches_dense_surface_sampling(mixed):
    world, trees = mixed
    rng = np.random.default_rng(3)
    near = [t.data[rng.choice(t.n, 1500)] + rng.normal(scale=0.15, size=(1500, 3)) for t in trees.values()]
    pts = np.concatenate([rng.uniform([-4, -4, -1.5], [4, 5, 3.5], size=(3000, 3))] + near)
    inside = world.labels_at(pts)
    for cid in (2, 3):
        exact = world.distance_to_class(pts, cid)
        assert np.all(exact[inside == cid] == 0.0)
        out = inside != cid
        brute = trees[cid].query(pts[out])[0]
        # exact distance never exceeds the distance to a surface sample, and the sampling gap is small
        assert np.all(exact[out] <= brute + 1e-9)
        assert np.all(brute - exact[out] < STEP), np.max(brute - exact[out])
        # points inside report 0; brute (distance to the surface) is positive there
        assert (inside == cid).sum() > 100


def test_ray_distance_to_class_matches_brute_force(mixed):
    world, trees = mixed
    rng = np.random.default_rng(5)
    dt = 0.004
    for _ in range(12):
        o = rng.uniform([-6, -6, -1], [6, 6, 3])
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        t = np.arange(0, 20, dt)
        pts = o + t[:, None] * d
        for cid in (2, 3):
            brute_surface = trees[cid].query(pts)[0].min()
            inside_any = np.any(world.labels_at(pts) == cid)
            got = world.ray_distance_to_class(o, d, cid)
            if inside_any:
                assert got < 1e-5
            else:
                assert got <= brute_surface + 1e-9
                assert brute_surface - got < STEP + dt
            # consistency with the point distance along the ray (independent of the search)
            assert got <= world.distance_to_class(pts, cid).min() + 1e-9


def test_batched_ray_distances_match_single_rays(mixed):
    world, _ = mixed
    rng = np.random.default_rng(9)
    o = rng.uniform(-6, 6, size=(40, 3))
    d = rng.normal(size=(40, 3))
    got = world.rays_distance_to_class(o, d, 2)
    one = [world.ray_distance_to_class(a, b, 2) for a, b in zip(o, d, strict=True)]
    np.testing.assert_allclose(got, one, atol=1e-9)
    lim = world.rays_distance_to_class(o, d, 2, max_range=0.5)  # shorter segments: never closer
    assert np.all(lim >= got - 1e-9)
    np.testing.assert_allclose(lim, world.distance_to_class(o, 2), atol=0.5 + 1e-6, rtol=0)


def test_ray_distance_exact_for_sphere_and_behind_origin():
    world = World.from_primitives([Part(Sphere((10.0, 3.0, 0.0), 1.0), "thing", "s")], CLASSES)
    assert world.ray_distance_to_class([0, 0, 0], [1, 0, 0], 2) == pytest.approx(2.0, abs=1e-6)
    # sphere behind the origin: nearest point of the half-line is the origin itself
    assert world.ray_distance_to_class([0, 0, 0], [-1, 0, 0], 2) == pytest.approx(np.hypot(10, 3) - 1, abs=1e-6)
    assert world.ray_distance_to_class([0, 0, 0], [10, 3, 0], 2) == pytest.approx(0.0, abs=1e-6)
    assert world.ray_distance_to_class([0, 0, 0], [1, 0, 0], 3) == np.inf  # class without instances


def test_voxel_labels_majority_and_empty():
    parts = [Part(Box((0.275, 0.5, 0.5), (0.275, 0.5, 0.5)), "thing", "a"),   # x in [0, 0.55]
             Part(Box((0.775, 0.5, 0.5), (0.225, 0.5, 0.5)), "other", "b")]   # x in [0.55, 1.0]
    world = World.from_primitives(parts, CLASSES)
    vox = 0.25
    ijk = np.array([[0, 1, 1], [1, 1, 1], [2, 1, 1], [3, 1, 1], [4, 1, 1], [-1, 1, 1], [2, 4, 1]])
    got = world.voxel_labels(ijk, vox, samples=3)
    # voxel 2 spans x in [0.5, 0.75]: sub-sample x = 0.5417 (a), 0.625, 0.708 (b) -> b wins 2:1
    np.testing.assert_array_equal(got, [2, 2, 3, 3, 0, 0, 0])
    only_a = World.from_primitives(parts[:1], CLASSES)
    assert only_a.voxel_labels(np.array([[2, 1, 1]]), vox, samples=3)[0] == 2  # 1/3 inside is enough


def test_bad_inputs_raise_clear_errors(mixed):
    world, _ = mixed
    with pytest.raises(ValueError, match="valid classes"):
        world.class_id("spaceship")
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        world.labels_at(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="direction"):
        world.ray_distance_to_class([0, 0, 0], [0, 0, 0], 2)
    with pytest.raises(ValueError, match="4x4"):
        world.render(np.eye(3), np.eye(3), (10, 10))
    with pytest.raises(ValueError, match="half extents"):
        Box((0, 0, 0), (1, -1, 1))
    with pytest.raises(ValueError, match="z1 > z0"):
        Cylinder(0, 0, 2, 1, 1)
    with pytest.raises(ValueError, match="sky"):
        World.from_primitives([Part(Sphere((0, 0, 0), 1), "sky", "x")], CLASSES)
