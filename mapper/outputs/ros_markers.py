"""Pieces of ROS 2 messages shared by the mapper's ROS outputs (``ros``, ``ros_search``,
``ros_robots``, ``ros_msg_serv``): headers, PointCloud2, the marker fields of newer distros."""
from __future__ import annotations

from typing import Any

import numpy as np

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
#: message classes by name (:func:`common.ros2.cdr.types`)
MsgTypes = dict[str, type]


def stamp_msg(types: MsgTypes, t: float) -> Any:
    sec = int(t)
    """builtin_interfaces/Time of ``t`` (s)."""
    return types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int((t - sec) * 1e9))


def header_msg(types: MsgTypes, frame_id: str, t: float) -> Any:
    """std_msgs/Header stamped ``t`` (s) in ``frame_id``."""
    return types["std_msgs/msg/Header"](stamp=stamp_msg(types, t), frame_id=frame_id)


def pointcloud2(types: MsgTypes, frame_id: str, t: float, xyz: np.ndarray,
                extra: dict[str, np.ndarray] | None = None) -> Any:
    """PointCloud2 with float32 fields x, y, z and then ``extra`` (name → (N,) float32), dense,
    little endian, one row."""
    xyz = np.asarray(xyz, "<f4").reshape(-1, 3)
    extra = extra or {}
    names = ["x", "y", "z", *extra]
    n = len(xyz)
    data = np.empty((n, len(names)), "<f4")  # column copies keep the bits (packed rgb)
    data[:, :3] = xyz
    for i, v in enumerate(extra.values()):
        data[:, 3 + i] = np.asarray(v, "<f4").reshape(-1)
    point_field: Any = types["sensor_msgs/msg/PointField"]
    fields = [point_field(name=nm, offset=4 * i, datatype=point_field.FLOAT32, count=1) for i, nm in enumerate(names)]
    step = 4 * len(names)
    return types[POINTCLOUD2](header=header_msg(types, frame_id, t), height=1, width=n, fields=fields,
                              is_bigendian=False, point_step=step, row_step=step * n,
                              data=np.ascontiguousarray(data).view(np.uint8).reshape(-1), is_dense=True)


def marker_extra_fields(types: Any, hdr: Any) -> dict:
    """The empty texture / mesh fields a ``visualization_msgs/Marker`` has from Jazzy on
    (nothing for Humble's definition)."""
    if "texture" not in types["visualization_msgs/msg/Marker"].__dataclass_fields__:
        return {}
    return dict(texture_resource="", uv_coordinates=[], mesh_file=types["visualization_msgs/msg/MeshFile"](
        filename="", data=np.zeros(0, np.uint8)),
        texture=types["sensor_msgs/msg/CompressedImage"](header=hdr, format="", data=np.zeros(0, np.uint8)))
