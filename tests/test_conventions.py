"""Conventions and pinhole geometry against independent, hand-written computations."""
import numpy as np
import pytest
import torch

from common import conventions as cv
from common import geometry as g


def _rot_z(deg):
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_body_axes_flu_to_rdf_hand_matrix():
    # FLU x=forward,y=left,z=up  ->  RDF x=right,y=down,z=forward
    expected = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], dtype=float)
    np.testing.assert_array_equal(cv.body_axes_matrix("FLU", "RDF"), expected)
    # FRD x=forward,y=right,z=down -> RDF
    expected_frd = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], dtype=float)
    np.testing.assert_array_equal(cv.body_axes_matrix("FRD", "RDF"), expected_frd)


def test_world_axes_ned_to_enu_hand_matrix():
    expected = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=float)
    np.testing.assert_array_equal(cv.world_axes_matrix("NED", "ENU"), expected)


def test_convert_pose_ned_frd_camera_facing_north():
    # A NED/FRD body at the origin with identity rotation looks north (NED x), right = east,
    # down = down. As RDF camera in ENU: optical axis (z) = north = +y, x (right) = east = +x,
    # y (down) = -z.
    p = np.eye(4)
    p[:3, 3] = [10.0, 5.0, -2.0]  # 10 m north, 5 m east, 2 m up (NED z down)
    out = cv.convert_pose(p, body="FRD", world="NED")
    np.testing.assert_allclose(out[:3, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(out[:3, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(out[:3, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(out[:3, 3], [5.0, 10.0, 2.0], atol=1e-12)
    assert cv.is_rigid(out)


def test_convert_pose_flu_body_yawed():
    # ROS FLU body yawed 90 deg left in an ENU world: forward = world +y (north).
    p = np.eye(4)
    p[:3, :3] = _rot_z(90)
    out = cv.convert_pose(p, body="FLU", world="ENU")
    np.testing.assert_allclose(out[:3, 2], [0, 1, 0], atol=1e-12)  # optical axis north
    np.testing.assert_allclose(out[:3, 0], [1, 0, 0], atol=1e-12)  # right = east
    np.testing.assert_allclose(out[:3, 1], [0, 0, -1], atol=1e-12)  # down


def test_convert_pose_identity_for_rdf_enu():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = q, rng.normal(size=3)
    np.testing.assert_allclose(cv.convert_pose(p, "RDF", "ENU"), p)


@pytest.mark.parametrize("bad", ["RDX", "RRF", "R", ""])
def test_bad_axis_convention(bad):
    with pytest.raises(ValueError):
        cv.body_axes_matrix(bad)


def test_voxel_index_is_floor_including_negatives():
    xyz = np.array([[-0.05, 0.0, 0.29999], [-0.3, 0.3, -0.30001]])
    np.testing.assert_array_equal(cv.voxel_index(xyz, 0.3), [[-1, 0, 0], [-1, 1, -2]])
    t = cv.voxel_index(torch.tensor(xyz, dtype=torch.float64), 0.3)
    assert t.dtype == torch.int64
    np.testing.assert_array_equal(t.numpy(), [[-1, 0, 0], [-1, 1, -2]])
    c = cv.voxel_center(np.array([[-1, 0, 2]]), 0.5)
    np.testing.assert_allclose(c, [[-0.25, 0.25, 1.25]])
    with pytest.raises(ValueError):
        cv.voxel_index(xyz, 0.0)


def test_sanitize_depth_semantics():
    d = np.array([[1.0, np.nan, np.inf, -np.inf], [0.0, -2.0, 25.0, 19.99]], dtype=np.float32)
    out = cv.sanitize_depth(d, depth_limit=20.0)
    assert np.isnan(out[0, 1]) and np.isnan(out[0, 3]) and np.isnan(out[1, 0]) and np.isnan(out[1, 1])
    assert np.isposinf(out[0, 2]) and np.isposinf(out[1, 2])
    assert out[0, 0] == 1.0 and out[1, 3] == np.float32(19.99)
    zero = cv.sanitize_depth(d, depth_limit=0.0)
    assert np.all(np.isposinf(zero[np.isfinite(d) & (d > 0)]))
    t = cv.sanitize_depth(torch.tensor(d), depth_limit=20.0)
    np.testing.assert_array_equal(np.isnan(t.numpy()), np.isnan(out))
    np.testing.assert_array_equal(t.numpy()[np.isfinite(out)], out[np.isfinite(out)])


def test_project_unproject_roundtrip():
    K = g.intrinsics_from_fov(90.0, 48, 64)
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 30.0, size=(48, 64))
    pts = g.unproject(depth, K).reshape(-1, 3)
    uv, z = g.project(pts, K)
    u, v = g.pixel_grid(48, 64)
    np.testing.assert_allclose(uv[:, 0], u.ravel(), atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], v.ravel(), atol=1e-9)
    np.testing.assert_allclose(z, depth.ravel())


def test_intrinsics_fov_hand_values():
    K = g.intrinsics_from_fov(90.0, 480, 640)
    assert K[0, 0] == pytest.approx(320.0) and K[1, 1] == pytest.approx(320.0)
    assert (K[0, 2], K[1, 2]) == (320.0, 240.0)
    h, v = g.fov_deg(K, 480, 640)
    assert h == pytest.approx(90.0)
    assert v == pytest.approx(np.rad2deg(2 * np.arctan(240 / 320)))
    K2 = g.scale_intrinsics(K, (480, 640), (240, 320))
    np.testing.assert_allclose(K2, [[160, 0, 160], [0, 160, 120], [0, 0, 1]])


def test_look_at_and_transforms():
    T = g.look_at([0, 0, 1.5], [10, 0, 1.5])
    assert cv.is_rigid(T)
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-12)  # forward = +x (east)
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # down
    np.testing.assert_allclose(T[:3, 0], [0, -1, 0], atol=1e-12)  # right = south
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(g.transform(g.invert_pose(T), g.transform(T, p)), p)


def test_is_rigid_rejects():
    assert not cv.is_rigid(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = -1  # reflection
    assert not cv.is_rigid(bad)
    nan = np.eye(4)
    nan[0, 3] = np.nan
    assert not cv.is_rigid(nan)
    scaled = np.eye(4) * 2
    scaled[3, 3] = 1
    assert not cv.is_rigid(scaled)
