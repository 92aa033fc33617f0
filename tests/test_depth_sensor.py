"""The realistic depth sensor (synthetic_world/depth_sensor.py): its statistics match its
parameters — noise σ = k·z² at several distances, grazing dropouts at the rate the model
gives for each pixel's true incidence angle, edge dropouts at ``edge_drop`` — and beyond
its range a surface returns nothing, exactly like the sky."""
from __future__ import annotations

import math

import numpy as np

from common.geometry import intrinsics_from_fov
from synthetic_world.depth_sensor import DepthSensorModel


def test_noise_sigma_grows_as_k_z_squared():
    """A wall facing the camera at z: the returned depths' mean is z and their standard
    deviation k·z² (within 4 %, 40,000 draws), at three distances; nothing drops out (no
    edge, no grazing angle) and nothing beyond range."""
    K = intrinsics_from_fov(60.0, 200, 200)
    m = DepthSensorModel(max_range_m=40.0, noise_k=0.002)
    rng = np.random.default_rng(0)
    for z in (4.0, 10.0, 20.0):
        out = m.apply(np.full((200, 200), z, np.float32), K, rng)
        assert np.isfinite(out).all()
        sig = 0.002 * z * z
        assert abs(float(out.std()) - sig) < 0.04 * sig, (z, out.std(), sig)
        assert abs(float(out.mean()) - z) < 4 * sig / 200, (z, out.mean())


def test_beyond_range_a_building_returns_nothing_like_the_sky():
    """Half the image a building at 30 m (finite exact depth), half sky (+inf): with a 20 m
    range both halves carry the same no-return value; a 10 m wall returns everywhere."""
    K = intrinsics_from_fov(60.0, 64, 64)
    d = np.full((64, 64), np.inf, np.float32)
    d[:, :32] = 30.0
    for no_return in ("inf", "nan"):
        m = DepthSensorModel(max_range_m=20.0, no_return=no_return)
        out = m.apply(d, K, np.random.default_rng(1))
        expect = np.inf if no_return == "inf" else np.nan
        assert np.array_equal(out, np.full_like(out, expect), equal_nan=True), no_return
    near = DepthSensorModel(max_range_m=20.0, edge_drop=0.0).apply(np.full((64, 64), 10.0, np.float32), K,
                                                                   np.random.default_rng(1))
    assert np.isfinite(near).all()


def test_range_is_euclidean_not_planar():
    """A wall at planar depth 19 m: pixels whose ray is longer than 20 m (off axis) give no
    return, the others do — exactly the pixels with z·|K⁻¹(u, v, 1)| > 20 (brute force)."""
    K = intrinsics_from_fov(90.0, 40, 40)
    out = DepthSensorModel(max_range_m=20.0, noise_k=0.0).apply(np.full((40, 40), 19.0, np.float32), K,
                                                                 np.random.default_rng(2))
    v, u = np.mgrid[0:40, 0:40]
    r = 19.0 * np.sqrt(((u + 0.5 - 20) / K[0, 0]) ** 2 + ((v + 0.5 - 20) / K[1, 1]) ** 2 + 1)
    assert (r > 20).sum() > 100 and (r <= 20).sum() > 100
    assert np.array_equal(np.isinf(out), r > 20)


def _tilted_plane(theta_deg: float, K: np.ndarray, hw: int, z0: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Planar depth of a plane through (0, 0, z0) whose normal is turned ``theta_deg`` about
    the camera's x axis, and each pixel's true incidence angle (degrees)."""
    t = math.radians(theta_deg)
    n = np.array([0.0, math.sin(t), -math.cos(t)])
    v, u = np.mgrid[0:hw, 0:hw].astype(np.float64)
    rays = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones((hw, hw))], 2)
    z = (n @ np.array([0, 0, z0])) / (rays @ n)                   # planar depth along each ray
    cos = np.abs(rays @ n) / np.linalg.norm(rays, axis=2)
    return z.astype(np.float32), np.degrees(np.arccos(cos))


def test_grazing_dropouts_follow_the_incidence_angle():
    """A plane seen at grazing angles (normal turned 76° and 82°, a 10° field of view): the share of pixels that
    drop out equals the mean of the model's probability over the pixels' TRUE incidence
    angles (computed from the plane, not from the depth image), within 3 standard errors;
    and a plane facing the camera loses none."""
    K = intrinsics_from_fov(10.0, 160, 160)
    m = DepthSensorModel(max_range_m=1e6, noise_k=0.0, grazing_deg=70.0, edge_drop=0.0)
    for theta in (76.0, 82.0):
        z, inc = _tilted_plane(theta, K, 160)
        assert (z > 0).all()
        p = m.grazing_drop_p(inc)
        assert 0.2 < p.mean() < 0.9
        dropped = ~np.isfinite(m.apply(z, K, np.random.default_rng(3)))
        inner = (slice(1, -1), slice(1, -1))                   # the image border has one-sided normals
        se = math.sqrt(p[inner].mean() * (1 - p[inner].mean()) / p[inner].size)
        assert abs(dropped[inner].mean() - p[inner].mean()) < 3 * se + 0.01, (theta, dropped.mean(), p.mean())
    z, _ = _tilted_plane(0.0, K, 160)
    assert np.isfinite(m.apply(z, K, np.random.default_rng(3))).all()


def test_edge_dropouts_at_edge_drop_rate():
    """A step from 5 m to 8 m: only pixels on either side of the step drop out, at rate
    ``edge_drop`` (within 3 standard errors); pixels away from it never."""
    K = intrinsics_from_fov(60.0, 400, 400)
    d = np.full((400, 400), 5.0, np.float32)
    d[:, 200:] = 8.0
    m = DepthSensorModel(max_range_m=100.0, noise_k=0.0, edge_drop=0.3, edge_jump=0.1)
    dropped = ~np.isfinite(m.apply(d, K, np.random.default_rng(4)))
    edge = np.zeros_like(dropped)
    edge[:, 199:201] = True
    assert not dropped[~edge].any()
    n = edge.sum()
    assert abs(dropped[edge].mean() - 0.3) < 3 * math.sqrt(0.3 * 0.7 / n)
