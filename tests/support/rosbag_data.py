"""ROS 2 messages (rosbags' Humble typestore) and the hand-written bag of the bag-source
tests: depth, colour, camera info, odometry or pose, and TF at known stamps, with poses
checked against hand-written matrices (:func:`expected_rdf`). Shared by
tests/test_sources_rosbag.py, tests/test_ros2_live.py and tests/test_ros2_e2e.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
H, W = 6, 8
T0 = 1_700_000_000.0


def stamp(t: float):
    sec = int(np.floor(t))
    return T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def header(t: float, frame: str):
    return T["std_msgs/msg/Header"](stamp=stamp(t), frame_id=frame)


def image(t, frame, arr: np.ndarray, encoding: str):
    arr = np.ascontiguousarray(arr)
    h, w = arr.shape[:2]
    data = arr.view(np.uint8).reshape(-1)
    return T["sensor_msgs/msg/Image"](header=header(t, frame), height=h, width=w, encoding=encoding,
                                      is_bigendian=0, step=data.size // h, data=data)


def camera_info(t, frame, K, h, w):
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(t, frame), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.asarray(K, float).ravel(), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def pose(p, q):
    return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))


def tf(t, parent, child, p, q):
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(t, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


def odom(t, p, q):
    cov = np.zeros(36)
    return T["nav_msgs/msg/Odometry"](
        header=header(t, "odom"), child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose(p, q), covariance=cov),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0, y=0, z=0),
                                               angular=T["geometry_msgs/msg/Vector3"](x=0, y=0, z=0)),
            covariance=cov))


def depth_values(k: int) -> np.ndarray:
    d = np.full((H, W), 1.0 + 0.5 * k, np.float32)
    d[0, 0] = 0.0  # → NaN
    d[1, 1] = np.nan
    d[2, 2] = np.inf  # beyond range stays +inf
    d[3, 3] = 12.25
    return d


def rgb_values(k: int) -> np.ndarray:
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


def yaw_q(a):
    return (0.0, 0.0, np.sin(a / 2), np.cos(a / 2))


def base_pose(t):
    """Ground truth of the body at time t (linear in x, yaw linear in time, exact for slerp)."""
    s = (t - POSE_T[0]) / 0.2
    return np.array([1.0 * s, 2.0, 0.5]), 0.25 * s  # position, yaw


def expected_rdf(t, optical_offset=None):
    """Hand-written RDF camera-to-world in ENU for a FLU body at (p, yaw):
    forward = (cos a, sin a, 0), left = (-sin a, cos a, 0), up = z;
    RDF columns: right = -left, down = -z, forward."""
    p, a = base_pose(t)
    f = np.array([np.cos(a), np.sin(a), 0.0])
    left = np.array([-np.sin(a), np.cos(a), 0.0])
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2] = -left, [0, 0, -1], f
    M[:3, 3] = p + M[:3, :3] @ (np.zeros(3) if optical_offset is None else optical_offset)
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
            tf(T0 - 1, "base_link", "camera_optical_frame", (0.2, 0.0, 0.1), (-0.5, 0.5, -0.5, 0.5))])))
        msgs.append((T0 - 1, c_info, "sensor_msgs/msg/CameraInfo",
                     camera_info(T0 - 1, "camera_optical_frame", K_INFO, 12, 16)))
        for t in POSE_T:
            p, a = base_pose(t)
            if pose_kind == "odom":
                msgs.append((t, c_pose, "nav_msgs/msg/Odometry", odom(t, p, yaw_q(a))))
            else:
                msgs.append((t, c_pose, "geometry_msgs/msg/PoseStamped",
                             T["geometry_msgs/msg/PoseStamped"](header=header(t, "map"), pose=pose(p, yaw_q(a)))))
            msgs.append((t, c_tf, "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=[
                tf(t, "map", "base_link", p, yaw_q(a))])))
        for k, (td, tr) in enumerate(zip(DEPTH_T, RGB_T, strict=True)):
            d = np.zeros((H, W), np.float32) if k == 4 else depth_values(k)
            if depth_encoding == "16UC1":
                with np.errstate(invalid="ignore"):
                    d = np.where(np.isfinite(d), np.round(d * 1000), 0).astype(np.uint16)
            msgs.append((td, c_d, "sensor_msgs/msg/Image", image(td, "camera_optical_frame", d, depth_encoding)))
            msgs.append((tr, c_rgb, "sensor_msgs/msg/Image", image(tr, "camera_optical_frame", rgb_values(k), "rgb8")))
        msgs.sort(key=lambda m: m[0])
        for t, conn, typ, msg in msgs:
            # receive time = stamp + 3 ms, so header stamps and bag times differ.
            raw = TS.serialize_cdr(msg, typ)
            if corrupt_depth is not None and conn is c_d and t == DEPTH_T[corrupt_depth]:
                raw = raw[:40]                       # a truncated message: does not deserialise
            w.write(conn, int((t + 0.003) * 1e9), raw)
    return path
