"""Interop with an independent ROS 2-over-Zenoh implementation from PyPI (``zenoh-ros2-sdk``,
which mimics rmw_zenoh: it subscribes on the exact key with the type hash it computes itself,
and publishes with its own keys, attachments and graph tokens). It runs offline from a local
messages directory written here from rosbags' definitions (no git download).

* our mapper's PointCloud2 / MarkerArray keys and payloads reach the SDK's subscriber;
* the SDK's publishers feed our live ``ros2`` source, which builds the frames we expect.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from common.zenoh_session import free_tcp_port
from tests.support.ports import open_loopback_router

JAZZY = get_typestore(Stores.ROS2_JAZZY)


def write_msgs(root: Path, types) -> str:
    """A ROS-style messages directory (``<pkg>/msg/<Name>.msg``) with ``types`` and their dependencies."""
    for t in types:
        text = JAZZY.generate_msgdef(t, ros_version=2)[0]
        parts = text.split("\n" + "=" * 80 + "\n")
        defs = {t: parts[0]}
        for p in parts[1:]:
            head, _, body = p.partition("\n")
            pkg, name = head.removeprefix("MSG: ").split("/")
            defs[f"{pkg}/msg/{name}"] = body
        for name, body in defs.items():
            pkg, _, n = name.split("/")
            d = root / pkg / "msg"
            d.mkdir(parents=True, exist_ok=True)
            (d / f"{n}.msg").write_text(body)
    return str(root)


@pytest.fixture(scope="module")
def router():
    """One router for the module: the SDK's session singleton stays connected to it."""
    port = free_tcp_port()
    s = open_loopback_router(port)
    yield s, port
    s.close()


@pytest.fixture(scope="module")
def sdk(tmp_path_factory):
    """The SDK (its session and type registry are process-wide singletons: one per module)."""
    from zenoh_ros2_sdk import message_registry

    md = write_msgs(tmp_path_factory.mktemp("msgs"), ["sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Image",
                                        "sensor_msgs/msg/CameraInfo", "geometry_msgs/msg/PoseStamped",
                                        "visualization_msgs/msg/MarkerArray", "std_msgs/msg/String"])
    message_registry.get_registry(md)
    import zenoh_ros2_sdk

    yield zenoh_ros2_sdk
    from zenoh_ros2_sdk.session import ZenohSession

    inst = getattr(ZenohSession, "_instance", None)
    if inst is not None:
        inst.close()


def test_sdk_subscriber_receives_mapper_output(router, sdk):
    from common.ros2 import cdr
    from common.ros2.keys import publish_key
    from mapper.outputs.ros import pack_rgb, pointcloud2, ray_markers

    s, port = router
    got = {"cloud": [], "rays": []}
    subs = [sdk.ROS2Subscriber("/rayfronts/voxels", "sensor_msgs/msg/PointCloud2", got["cloud"].append,
                               router_port=port, domain_id=0),
            sdk.ROS2Subscriber("/rayfronts/rays", "visualization_msgs/msg/MarkerArray", got["rays"].append,
                               router_port=port, domain_id=0)]
    try:
        T = cdr.types("jazzy")
        xyz = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 0.25]], np.float32)
        msgs = {"/rayfronts/voxels": ("sensor_msgs/msg/PointCloud2", pointcloud2(
                    T, "map", 3.0, xyz, {"rgb": pack_rgb(np.array([[9, 8, 7], [1, 2, 3]], np.uint8))})),
                "/rayfronts/rays": ("visualization_msgs/msg/MarkerArray", ray_markers(
                    T, "map", 3.0, xyz, np.array([[1, 0, 0], [0, 1, 0]], np.float32), np.array([1.0, 2.0]), 2.0,
                    "jazzy"))}
        time.sleep(1.0)
        for i, (topic, (t, m)) in enumerate(msgs.items()):
            s.put(publish_key(topic, t, "rmw_zenoh", 0, cdr.type_hash(t, "jazzy")), cdr.serialize(m, t, "jazzy"),
                  attachment=cdr.attachment(i + 1, time.time_ns(), bytes(16)))
        end = time.monotonic() + 10
        while time.monotonic() < end and not (got["cloud"] and got["rays"]):
            time.sleep(0.1)
        assert got["cloud"] and got["rays"], "the SDK's rmw_zenoh-style subscribers got nothing"
        c = got["cloud"][0]
        assert c.width == 2 and [f.name for f in c.fields] == ["x", "y", "z", "rgb"]
        np.testing.assert_array_equal(np.frombuffer(bytes(c.data), "<f4").reshape(2, 4)[:, :3], xyz)
        assert len(got["rays"][0].markers) == 3
    finally:
        for sub in subs:
            sub.close()


def test_sdk_publishers_feed_the_live_source(router, sdk):
    from edge.sources import SourceConfig, open_source

    _, port = router
    H, W = 4, 6
    pubs = {n: sdk.ROS2Publisher(t, m, router_port=port, domain_id=0) for n, t, m in (
        ("rgb", "/cam/color", "sensor_msgs/msg/Image"), ("depth", "/cam/depth", "sensor_msgs/msg/Image"),
        ("pose", "/cam/pose", "geometry_msgs/msg/PoseStamped"))}
    stop = threading.Event()
    T0 = 1_760_000_000

    def publish():
        time.sleep(1.5)  # the source subscribes first
        T = JAZZY.types
        for k in range(6):
            if stop.is_set():
                return
            stamp = T["builtin_interfaces/msg/Time"](sec=T0 + k, nanosec=0)
            hdr = T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam_optical_frame")
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(k), y=0.0, z=1.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
            pubs["pose"].publish(header=hdr, pose=pose)
            d = np.full((H, W), 1.0 + k, np.float32)
            pubs["depth"].publish(header=hdr, height=H, width=W, encoding="32FC1", is_bigendian=0, step=W * 4,
                                  data=d.view(np.uint8).reshape(-1))
            rgb = np.full((H, W, 3), (10 * k, 20, 30), np.uint8)
            pubs["rgb"].publish(header=hdr, height=H, width=W, encoding="rgb8", is_bigendian=0, step=W * 3,
                                data=rgb.reshape(-1))
            time.sleep(0.1)

    th = threading.Thread(target=publish, daemon=True)
    th.start()
    try:
        src = open_source(SourceConfig(kind="ros2", ros_connect=[f"tcp/127.0.0.1:{port}"], rgb_topic="/cam/color",
                                       depth_topic="/cam/depth", pose_topic="/cam/pose", body_axes="RDF",
                                       intrinsics=[5.0, 5.0, 3.0, 2.0], ros_idle_timeout=2.0, ros_startup_timeout=20))
        frames = list(src)
    finally:
        stop.set()
        th.join(10)
        for p in pubs.values():
            p.close()
    assert [f.meta["index"] for f in frames] == list(range(6))
    for k, f in enumerate(frames):
        assert f.stamp == T0 + k
        np.testing.assert_array_equal(f.depth, np.full((H, W), 1.0 + k, np.float32))
        assert tuple(f.rgb[0, 0]) == (10 * k, 20, 30)
        np.testing.assert_array_equal(f.pose[:3, 3], [k, 0, 1])
