"""Pieces of ROS 2 marker messages shared by the mapper's ROS outputs (``ros``, ``ros_search``)."""
from __future__ import annotations

from typing import Any

import numpy as np


def marker_extra_fields(types: Any, hdr: Any) -> dict:
    """The empty texture / mesh fields a ``visualization_msgs/Marker`` has from Jazzy on
    (nothing for Humble's definition)."""
    if "texture" not in types["visualization_msgs/msg/Marker"].__dataclass_fields__:
        return {}
    return dict(texture_resource="", uv_coordinates=[], mesh_file=types["visualization_msgs/msg/MeshFile"](
        filename="", data=np.zeros(0, np.uint8)),
        texture=types["sensor_msgs/msg/CompressedImage"](header=hdr, format="", data=np.zeros(0, np.uint8)))
