"""ROS 2 bag source: tiny bags written with rosbags' Writer + typestore serializer, read
back through edge.sources; poses checked against hand-written matrices."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

from edge.sources import SourceConfig, SourceError, open_source  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
H, W = 6, 8
T0 = 1_700_000_000.0
S = np.sqrt(0.5)


def _time(t: float):
    sec = int(np.floor(t))
    return T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _header(t: float, frame: str):
    return T["std_msgs/msg/Header"](stamp=_time(t), frame_id=frame)


def _image(t, frame, arr: np.ndarray, encoding: str):
    arr = np.ascontiguousarray(arr)
    h, w = arr.shape[:2]
    data = arr.view(np.uint8).reshape(-1)
    return T["sensor_msgs/msg/Image"](header=_header(t, frame), height=h, width=w, encoding=encoding,
                                      is_bigendian=0, step=data.size // h, data=data)


def _camera_info(t, frame, K, h, w):
    return T["sensor_msgs/msg/CameraInfo"](
        header=_header(t, frame), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.asarray(K, float).ravel(), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def _pose(p, q):
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))


def _tf(t, parent, child, p, q):
    return T["geometry_msgs/msg/TransformStamped"](
        header=_header(t, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


def _odom(t, p, q):
    cov = np.zeros(36)
    return T["nav_msgs/msg/Odometry"](
        header=_header(t, "odom"), child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(p, q), covariance=cov),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0, y=0, z=0),
                                               angular=T["geometry_msgs/msg/Vector3"](x=0, y=0, z=0)),
            covariance=cov))


def _depth_values(k: int) -> np.ndarray:
    d = np.full((H, W), 1.0 + 0.5 * k, np.float32)
    d[0, 0] = 0.0  # → NaN
    d[1, 1] = np.nan
    d[2, 2] = np.inf  # beyond range stays +inf
    d[3, 3] = 12.25
    return d


def _rgb_values(k: int) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    return np.stack([u * 20 + k, v * 30, np.full_like(u, 100 + k)], -1).astype(np.uint8)


K_INFO = np.array([[40.0, 0, 16.0], [0, 40.0, 12.0], [0, 0, 1]])  # for a 12×16 camera info: 2× depth size

# Frames: depth stamps at T0 + 0.1 k, k = 0..5, and T0 + 0.7 for k = 6.
#   k = 3: colour 0.07 s away → no colour;  k = 4: all-zero depth → no valid depth;
#   k = 6: 0.15 s after the last pose sample (beyond tolerance, no extrapolation) → no pose.
DEPTH_T = [T0 + 0.1 * k for k in range(6)] + [T0 + 0.7]
RGB_T = [t + (0.07 if k == 3 else 0.01) for k, t in enumerate(DEPTH_T)]
# Base poses (odom / map → base_link), FLU body in ENU: moving along x and yawing.
POSE_T = [T0 - 0.05 + 0.2 * j for j in range(4)]  # T0-0.05 .. T0+0.55


def _yaw_q(a):
    return (0.0, 0.0, np.sin(a / 2), np.cos(a / 2))


def _base_pose(t):
    """Ground truth of the body at time t (linear in x, yaw linear in time, exact for slerp)."""
    s = (t - POSE_T[0]) / 0.2
    return np.array([1.0 * s, 2.0, 0.5]), 0.25 * s  # position, yaw


def _expected_rdf(t, optical_offset=np.zeros(3)):
    """Hand-written RDF camera-to-world in ENU for a FLU body at (p, yaw):
    forward = (cos a, sin a, 0), left = (-sin a, cos a, 0), up = z;
    RDF columns: right = -left, down = -z, forward."""
    p, a = _base_pose(t)
    f = np.array([np.cos(a), np.sin(a), 0.0])
    left = np.array([-np.sin(a), np.cos(a), 0.0])
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2] = -left, [0, 0, -1], f
    M[:3, 3] = p + M[:3, :3] @ optical_offset
    return M


def write_bag(path: Path, *, pose_kind: str = "odom", depth_encoding: str = "32FC1",
              corrupt_depth: int | None = None) -> Path:
    with Writer(path, version=9) as w:
        c_rgb = w.add_connection("/cam/color", "sensor_msgs/msg/Image", typestore=TS)
        c_d = w.add_connection("/cam/depth", "sensor_msgs/msg/Image", typestore=TS)
        c_info = w.add_connection("/cam/depth/info", "sensor_msgs/msg/CameraInfo", typestore=TS)
        c_pose = (w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TS) if pose_kind == "odom" else
                  w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=TS))
        c_tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=TS)
        c_tfs = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
        msgs = []
        # Static: base_link → camera_optical_frame, 0.2 m forward, 0.1 m up, optical rotation.
        msgs.append((T0 - 1, c_tfs, "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=[
            _tf(T0 - 1, "base_link", "camera_optical_frame", (0.2, 0.0, 0.1), (-0.5, 0.5, -0.5, 0.5))])))
        msgs.append((T0 - 1, c_info, "sensor_msgs/msg/CameraInfo", _camera_info(T0 - 1, "camera_optical_frame", K_INFO, 12, 16)))
        for t in POSE_T:
            p, a = _base_pose(t)
            if pose_kind == "odom":
                msgs.append((t, c_pose, "nav_msgs/msg/Odometry", _odom(t, p, _yaw_q(a))))
            else:
                msgs.append((t, c_pose, "geometry_msgs/msg/PoseStamped",
                             T["geometry_msgs/msg/PoseStamped"](header=_header(t, "map"), pose=_pose(p, _yaw_q(a)))))
            msgs.append((t, c_tf, "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=[
                _tf(t, "map", "base_link", p, _yaw_q(a))])))
        for k, (td, tr) in enumerate(zip(DEPTH_T, RGB_T)):
            d = np.zeros((H, W), np.float32) if k == 4 else _depth_values(k)
            if depth_encoding == "16UC1":
                with np.errstate(invalid="ignore"):
                    d = np.where(np.isfinite(d), np.round(d * 1000), 0).astype(np.uint16)
            msgs.append((td, c_d, "sensor_msgs/msg/Image", _image(td, "camera_optical_frame", d, depth_encoding)))
            msgs.append((tr, c_rgb, "sensor_msgs/msg/Image", _image(tr, "camera_optical_frame", _rgb_values(k), "rgb8")))
        msgs.sort(key=lambda m: m[0])
        for t, conn, typ, msg in msgs:
            # receive time = stamp + 3 ms, so header stamps and bag times differ.
            raw = TS.serialize_cdr(msg, typ)
            if corrupt_depth is not None and conn is c_d and t == DEPTH_T[corrupt_depth]:
                raw = raw[:40]                       # a truncated message: does not deserialise
            w.write(conn, int((t + 0.003) * 1e9), raw)
    return path


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    return write_bag(tmp_path_factory.mktemp("bags") / "odom_bag")


def _cfg(bag, **kw):
    base = dict(kind="rosbag", path=str(bag), rgb_topic="/cam/color", depth_topic="/cam/depth",
                camera_info_topic="/cam/depth/info")
    base.update(kw)
    return SourceConfig(**base)


def _check_images(f):
    k = f.meta["index"]
    exp = _depth_values(k)
    exp[exp == 0] = np.nan
    np.testing.assert_array_equal(f.depth, exp)
    np.testing.assert_array_equal(f.rgb, _rgb_values(k))
    np.testing.assert_allclose(f.intrinsics, K_INFO * [[0.5], [0.5], [1]])


def test_rosbag_odometry_flu_body(bag):
    """Odometry of base_link, no camera_frame: the FLU body itself is the camera (REP-103)."""
    src = open_source(_cfg(bag, pose_topic="/odom"))
    assert src.body_axes == "FLU"
    assert len(src) == 4
    assert dict(src.skipped) == {"no colour image within sync_tolerance": 1, "no valid depth pixel": 1,
                                 "no pose at the depth stamp": 1}
    frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 1, 2, 5]
    for f in frames:
        k = f.meta["index"]
        assert f.stamp == pytest.approx(DEPTH_T[k], abs=1e-6)
        np.testing.assert_allclose(f.pose, _expected_rdf(DEPTH_T[k]), atol=1e-6)
        _check_images(f)
    # yaw 0 at the first sample: hand-written RDF for a FLU body at identity in ENU.
    f0 = frames[0]
    p, a = _base_pose(DEPTH_T[0])
    R = np.array([[np.sin(a), 0, np.cos(a)], [-np.cos(a), 0, np.sin(a)], [0, -1, 0]])
    np.testing.assert_allclose(f0.pose[:3, :3], R, atol=1e-6)


def test_rosbag_tf_chain_optical_frame(bag):
    """Pose from /tf map → base_link (dynamic, interpolated) + /tf_static base_link → optical frame."""
    src = open_source(_cfg(bag, world_frame="map", camera_frame="camera_optical_frame"))
    assert src.body_axes == "RDF"
    frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 1, 2, 5]
    for f in frames:
        # the optical frame sits 0.2 m forward, 0.1 m up of base_link: in RDF, (0, -0.1, 0.2)
        np.testing.assert_allclose(f.pose, _expected_rdf(f.stamp, np.array([0.0, -0.1, 0.2])), atol=1e-6)
        _check_images(f)


def test_rosbag_odometry_plus_static_extrinsics(bag):
    src = open_source(_cfg(bag, pose_topic="/odom", camera_frame="camera_optical_frame"))
    for f in src:
        np.testing.assert_allclose(f.pose, _expected_rdf(f.stamp, np.array([0.0, -0.1, 0.2])), atol=1e-6)


def test_rosbag_posestamped_16uc1_nearest_pose(tmp_path):
    bag = write_bag(tmp_path / "b16", pose_kind="pose", depth_encoding="16UC1")
    src = open_source(_cfg(bag, pose_topic="/pose", interpolate_pose=False, sync_tolerance=0.06,
                           frame_skip=1, depth_limit=2.0))
    frames = list(src)
    # frame_skip=1 keeps depth ordinals 0, 2, 4, 6; 4 has no valid depth; 6 no pose.
    # Nearest pose within 0.06 s: depth 0 (T0) ← sample T0-0.05; depth 2 (T0+0.2) ← T0+0.15.
    assert [f.meta["index"] for f in frames] == [0, 2]
    for f, tp in zip(frames, (POSE_T[0], POSE_T[1])):
        np.testing.assert_allclose(f.pose, _expected_rdf(tp), atol=1e-6)
        k = f.meta["index"]
        exp = _depth_values(k)
        exp[~np.isfinite(exp) | (exp == 0)] = np.nan  # 16UC1 cannot carry inf: 0 → NaN
        exp[np.isfinite(exp) & (exp > 2.0)] = np.inf
        np.testing.assert_allclose(f.depth, exp, atol=5e-4)


def test_rosbag_max_frames_resolution(bag):
    src = open_source(_cfg(bag, pose_topic="/odom", max_frames=2, resolution="3x4"))
    assert len(src) == 2
    np.testing.assert_allclose(src.intrinsics, K_INFO * [[0.25], [0.25], [1]])
    frames = list(src)
    assert len(frames) == 2 and frames[0].depth.shape == (3, 4) and frames[0].rgb.shape == (3, 4, 3)


def test_rosbag_errors(bag, tmp_path):
    with pytest.raises(SourceError, match="nothere"):
        open_source(_cfg(tmp_path / "nothere", pose_topic="/odom"))
    with pytest.raises(SourceError, match="(?s)/cam/colour.*/cam/color "):
        open_source(_cfg(bag, rgb_topic="/cam/colour", pose_topic="/odom"))
    with pytest.raises(SourceError, match="no pose source"):
        open_source(_cfg(bag))
    with pytest.raises(SourceError, match="no tf chain"):
        open_source(_cfg(bag, world_frame="map", camera_frame="lidar"))
    with pytest.raises(SourceError, match="expected one of"):
        open_source(_cfg(bag, pose_topic="/cam/depth"))


def test_rosbag_compressed_images_and_static_intrinsics(tmp_path):
    """CompressedImage colour (PNG, lossless) and image_transport compressedDepth 16UC1 depth,
    no CameraInfo (intrinsics from the config), PoseStamped of an optical frame (RDF body)."""

    path = tmp_path / "comp"
    with Writer(path, version=9) as w:
        c_rgb = w.add_connection("/rgb/compressed", "sensor_msgs/msg/CompressedImage", typestore=TS)
        c_d = w.add_connection("/depth/compressedDepth", "sensor_msgs/msg/CompressedImage", typestore=TS)
        c_p = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=TS)
        for k in range(3):
            t = T0 + k
            rgb = _rgb_values(k)
            ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            m = T["sensor_msgs/msg/CompressedImage"](header=_header(t, "cam"), format="rgb8; png compressed bgr8",
                                                     data=np.frombuffer(png.tobytes(), np.uint8))
            w.write(c_rgb, int(t * 1e9), TS.serialize_cdr(m, "sensor_msgs/msg/CompressedImage"))
            dmm = np.full((H, W), 1500 + k, np.uint16)
            dmm[0, :] = 0
            ok, dpng = cv2.imencode(".png", dmm)
            head = np.array([0], "<i4").tobytes() + np.array([0.0, 0.0], "<f4").tobytes()
            m = T["sensor_msgs/msg/CompressedImage"](header=_header(t, "cam"), format="16UC1; compressedDepth",
                                                     data=np.frombuffer(head + dpng.tobytes(), np.uint8))
            w.write(c_d, int(t * 1e9), TS.serialize_cdr(m, "sensor_msgs/msg/CompressedImage"))
            ps = T["geometry_msgs/msg/PoseStamped"](header=_header(t, "map"), pose=_pose((k, 0, 1), (0, 0, 0, 1)))
            w.write(c_p, int(t * 1e9), TS.serialize_cdr(ps, "geometry_msgs/msg/PoseStamped"))
    src = open_source(SourceConfig(kind="rosbag", path=str(path), rgb_topic="/rgb/compressed",
                                   depth_topic="/depth/compressedDepth", pose_topic="/pose", body_axes="RDF",
                                   intrinsics=[10.0, 11.0, 4.0, 3.0]))
    frames = list(src)
    assert len(frames) == 3
    np.testing.assert_allclose(src.intrinsics, [[10, 0, 4], [0, 11, 3], [0, 0, 1]])
    for k, f in enumerate(frames):
        np.testing.assert_array_equal(f.rgb, _rgb_values(k))
        assert np.isnan(f.depth[0]).all()
        np.testing.assert_allclose(f.depth[1:], (1500 + k) / 1000.0, rtol=1e-6)
        exp = np.eye(4)
        exp[:3, 3] = (k, 0, 1)
        np.testing.assert_allclose(f.pose, exp)
    with pytest.raises(SourceError, match="no intrinsics"):
        open_source(SourceConfig(kind="rosbag", path=str(path), rgb_topic="/rgb/compressed",
                                 depth_topic="/depth/compressedDepth", pose_topic="/pose"))


def test_rosbag_corrupt_depth_message_skipped_and_counted(tmp_path):
    """A depth message that does not deserialise is skipped and counted; the frames after it come."""
    src = open_source(_cfg(write_bag(tmp_path / "corrupt_bag", corrupt_depth=1), pose_topic="/odom"))
    assert src.skipped["corrupt frame"] == 1
    frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 2, 5]
    for f in frames:
        _check_images(f)
