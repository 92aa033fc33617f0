"""ROS 2 bag source: tiny bags written with rosbags' Writer + typestore serializer, read
back through edge.sources; poses checked against hand-written matrices."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Writer

from edge.sources import SourceConfig, SourceError, open_source  # noqa: E402
from tests.support.rosbag_data import (
    DEPTH_T,
    K_INFO,
    POSE_T,
    T0,
    TS,
    H,
    T,
    W,
    base_pose,
    depth_values,
    expected_rdf,
    header,
    pose,
    rgb_values,
    write_bag,
)


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
    exp = depth_values(k)
    exp[exp == 0] = np.nan
    np.testing.assert_array_equal(f.depth, exp)
    np.testing.assert_array_equal(f.rgb, rgb_values(k))
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
        np.testing.assert_allclose(f.pose, expected_rdf(DEPTH_T[k]), atol=1e-6)
        _check_images(f)
    # yaw 0 at the first sample: hand-written RDF for a FLU body at identity in ENU.
    f0 = frames[0]
    p, a = base_pose(DEPTH_T[0])
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
        np.testing.assert_allclose(f.pose, expected_rdf(f.stamp, np.array([0.0, -0.1, 0.2])), atol=1e-6)
        _check_images(f)


def test_rosbag_odometry_plus_static_extrinsics(bag):
    src = open_source(_cfg(bag, pose_topic="/odom", camera_frame="camera_optical_frame"))
    for f in src:
        np.testing.assert_allclose(f.pose, expected_rdf(f.stamp, np.array([0.0, -0.1, 0.2])), atol=1e-6)


def test_rosbag_posestamped_16uc1_nearest_pose(tmp_path):
    bag = write_bag(tmp_path / "b16", pose_kind="pose", depth_encoding="16UC1")
    src = open_source(_cfg(bag, pose_topic="/pose", interpolate_pose=False, sync_tolerance=0.06,
                           frame_skip=1, depth_limit=2.0))
    frames = list(src)
    # frame_skip=1 keeps depth ordinals 0, 2, 4, 6; 4 has no valid depth; 6 no pose.
    # Nearest pose within 0.06 s: depth 0 (T0) ← sample T0-0.05; depth 2 (T0+0.2) ← T0+0.15.
    assert [f.meta["index"] for f in frames] == [0, 2]
    for f, tp in zip(frames, (POSE_T[0], POSE_T[1]), strict=True):
        np.testing.assert_allclose(f.pose, expected_rdf(tp), atol=1e-6)
        k = f.meta["index"]
        exp = depth_values(k)
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
            rgb = rgb_values(k)
            ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            m = T["sensor_msgs/msg/CompressedImage"](header=header(t, "cam"), format="rgb8; png compressed bgr8",
                                                     data=np.frombuffer(png.tobytes(), np.uint8))
            w.write(c_rgb, int(t * 1e9), TS.serialize_cdr(m, "sensor_msgs/msg/CompressedImage"))
            dmm = np.full((H, W), 1500 + k, np.uint16)
            dmm[0, :] = 0
            ok, dpng = cv2.imencode(".png", dmm)
            head = np.array([0], "<i4").tobytes() + np.array([0.0, 0.0], "<f4").tobytes()
            m = T["sensor_msgs/msg/CompressedImage"](header=header(t, "cam"), format="16UC1; compressedDepth",
                                                     data=np.frombuffer(head + dpng.tobytes(), np.uint8))
            w.write(c_d, int(t * 1e9), TS.serialize_cdr(m, "sensor_msgs/msg/CompressedImage"))
            ps = T["geometry_msgs/msg/PoseStamped"](header=header(t, "map"), pose=pose((k, 0, 1), (0, 0, 0, 1)))
            w.write(c_p, int(t * 1e9), TS.serialize_cdr(ps, "geometry_msgs/msg/PoseStamped"))
    src = open_source(SourceConfig(kind="rosbag", path=str(path), rgb_topic="/rgb/compressed",
                                   depth_topic="/depth/compressedDepth", pose_topic="/pose", body_axes="RDF",
                                   intrinsics=[10.0, 11.0, 4.0, 3.0]))
    frames = list(src)
    assert len(frames) == 3
    np.testing.assert_allclose(src.intrinsics, [[10, 0, 4], [0, 11, 3], [0, 0, 1]])
    for k, f in enumerate(frames):
        np.testing.assert_array_equal(f.rgb, rgb_values(k))
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
