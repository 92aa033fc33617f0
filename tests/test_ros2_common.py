"""ROS 2 helpers: key layouts and graph tokens against rmw_zenoh's documented examples
(written out by hand here), the rmw attachment layout, and the mapper's ROS message
builders decoded by rosbags for both Humble and Jazzy definitions."""
from __future__ import annotations

import struct

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from common.ros2 import cdr
from common.ros2.keys import (
    RosKeyError,
    dds_type,
    liveliness_token,
    parse_key,
    parse_liveliness,
    publish_key,
    ros_type,
    subscribe_key,
)

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
JAZZY = get_typestore(Stores.ROS2_JAZZY)


def test_key_layouts():
    assert dds_type("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    assert ros_type("nav_msgs::msg::dds_::Odometry_") == "nav_msgs/msg/Odometry"
    assert subscribe_key("/camera/color/image_raw", "rmw_zenoh", 7) == "7/camera/color/image_raw/*/*"
    assert subscribe_key("/camera/color/image_raw", "bridge") == "camera/color/image_raw"
    # rmw_zenoh's own example: 0/chatter/std_msgs::msg::dds_::Int32_/TypeHashNotSupported
    assert publish_key("/chatter", "std_msgs/msg/Int32", "rmw_zenoh", 0) == \
        "0/chatter/std_msgs::msg::dds_::Int32_/TypeHashNotSupported"
    h = "RIHS01_" + "ab" * 32
    assert parse_key(f"3/a/b/sensor_msgs::msg::dds_::Image_/{h}", "rmw_zenoh", 3) == \
        ("/a/b", "sensor_msgs/msg/Image", h)
    assert parse_key("a/b", "bridge") == ("/a/b", None, None)
    for bad in ("", "/", "/a/*", "/a//b", "/a b"):
        with pytest.raises(RosKeyError):
            subscribe_key(bad, "rmw_zenoh")
    with pytest.raises(RosKeyError):
        parse_key("1/a/t/h", "rmw_zenoh", 0)  # another domain
    with pytest.raises(RosKeyError):
        subscribe_key("/a", "dds")


def test_graph_tokens():
    # the token format of rmw_zenoh's design: @ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/<ns>/<node>/...
    tok = ("@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%/talker/%chatter/"
           "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/"
           "::,7:,:,:,,")
    p = parse_liveliness(tok)
    assert p["kind"] == "publisher" and p["topic"] == "/chatter" and p["type"] == "std_msgs/msg/String"
    assert p["node"] == "talker" and p["namespace"] == "/" and p["type_hash"].startswith("RIHS01_")
    assert parse_liveliness("@ros2_lv/0/zid/0/0/NN/%/%/talker")["kind"] == "node"
    assert parse_liveliness("rayfronts/mapper/alive") is None
    mine = liveliness_token(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 11, "MP", "talker", topic="/chatter",
                            msgtype="std_msgs/msg/String", type_hash=JAZZY.hash_rihs01("std_msgs/msg/String"),
                            qos="::,7:,:,:,,")
    assert mine == tok
    assert liveliness_token(0, "z", 0, 3, "MS", "n", namespace="/robot1", topic="/a/b", msgtype="std_msgs/msg/String") \
        == "@ros2_lv/0/z/0/3/MS/%/%robot1/n/%a%b/std_msgs::msg::dds_::String_/TypeHashNotSupported/::,:,:,:,,"


def test_type_hash_and_attachment():
    assert cdr.type_hash("std_msgs/msg/String", "humble") == "TypeHashNotSupported"
    # the published RIHS01 of std_msgs/msg/String (Jazzy)
    assert cdr.type_hash("std_msgs/msg/String", "jazzy") == \
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    gid = bytes(range(16))
    a = cdr.attachment(5, 123456789, gid)
    assert a == struct.pack("<qq", 5, 123456789) + b"\x10" + gid
    assert cdr.parse_attachment(a) == (5, 123456789, gid)
    with pytest.raises(cdr.CdrError, match="too short"):
        cdr.deserialize(b"\x00", "std_msgs/msg/String")
    with pytest.raises(cdr.CdrError, match="Odometry"):
        cdr.deserialize(bytes(HUMBLE.serialize_cdr(HUMBLE.types["std_msgs/msg/String"](data="x"),
                                                   "std_msgs/msg/String")), "nav_msgs/msg/Odometry")


@pytest.mark.parametrize("distro,store", [("humble", HUMBLE), ("jazzy", JAZZY)])
def test_output_messages_decode(distro, store):
    from mapper.outputs.ros import pack_rgb, pointcloud2, query_id, ray_markers

    T = cdr.types(distro)
    xyz = np.array([[0.25, -1.5, 3.0], [10.0, 20.0, -0.5]], np.float32)
    rgb = np.array([[255, 0, 10], [1, 2, 3]], np.uint8)
    raw = cdr.serialize(pointcloud2(T, "map", 12.5, xyz, {"rgb": pack_rgb(rgb)}), "sensor_msgs/msg/PointCloud2",
                        distro)
    m = store.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")
    assert (m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec) == ("map", 12, 500_000_000)
    assert [(f.name, f.offset, f.datatype, f.count) for f in m.fields] == \
        [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("rgb", 12, 7, 1)]
    assert (m.width, m.height, m.point_step, m.row_step, m.is_dense) == (2, 1, 16, 32, True)
    rec = np.frombuffer(bytes(m.data), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), xyz)
    assert list(rec["rgb"]) == [0xFF000A, 0x010203]
    empty = store.deserialize_cdr(cdr.serialize(pointcloud2(T, "map", 0.0, np.zeros((0, 3))),
                                                "sensor_msgs/msg/PointCloud2", distro), "sensor_msgs/msg/PointCloud2")
    assert empty.width == 0 and len(empty.data) == 0

    o = np.array([[0, 0, 0], [1, 1, 1]], np.float32)
    d = np.array([[1, 0, 0], [0, 0, 1]], np.float32)
    ma = store.deserialize_cdr(cdr.serialize(ray_markers(T, "odom", 1.0, o, d, np.array([1.0, 4.0]), 2.0, distro),
                                             "visualization_msgs/msg/MarkerArray", distro),
                               "visualization_msgs/msg/MarkerArray")
    assert [mk.action for mk in ma.markers] == [3, 0, 0]
    a1, a2 = ma.markers[1:]
    assert (a1.points[1].x, a2.points[1].z) == (2.0, 3.0) and a1.type == 0
    assert (a2.color.r, a2.color.b) == (1.0, 0.0) and a1.color.b > a1.color.r  # heavy = red, light = blue
    assert query_id("  Red door!") == "ros_red_door"
