"""CDR (de)serialisation of ROS 2 messages through ``rosbags``' typestore.

``rosbags`` is imported lazily (it is the ``ros`` extra); a missing package raises
:class:`CdrError` naming the install command. The message definitions we use (sensor_msgs,
geometry_msgs, nav_msgs, tf2_msgs, std_msgs) are identical from Humble on, so one typestore
decodes every distro's inputs; for output, ``distro`` picks the definitions and the type hash
we advertise (``humble``: ``TypeHashNotSupported``; ``jazzy`` and later: ``RIHS01_...``).
"""
from __future__ import annotations

import struct
from functools import cache
from typing import TYPE_CHECKING, Any

from common.ros2.keys import TYPE_HASH_NONE

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

DISTROS = ("humble", "iron", "jazzy", "kilted")


class CdrError(ValueError):
    """A payload cannot be decoded as the given type (or rosbags is missing)."""


@cache
def typestore(distro: str = "humble") -> Typestore:
    """The ``rosbags`` typestore of ``distro`` (cached)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as e:
        raise CdrError(f"ROS 2 messages need the 'rosbags' package (pip install 'rayfronts-zenoh[ros]'): {e}") from None
    names = {"humble": Stores.ROS2_HUMBLE, "iron": Stores.ROS2_IRON, "jazzy": Stores.ROS2_JAZZY,
             "kilted": getattr(Stores, "ROS2_KILTED", Stores.ROS2_JAZZY)}
    if distro not in names:
        raise CdrError(f"unknown ROS 2 distro {distro!r}; choose one of {', '.join(DISTROS)}")
    return get_typestore(names[distro])


def types(distro: str = "humble") -> dict[str, type]:
    """The typestore's message classes, by name (``types()['sensor_msgs/msg/Image']``)."""
    return typestore(distro).types


def deserialize(raw: bytes | bytearray | memoryview, msgtype: str) -> Any:
    """CDR bytes (with the 4-byte encapsulation header) → message object; CdrError on failure."""
    if len(raw) < 4:
        raise CdrError(f"payload of {len(raw)} bytes is too short for CDR")
    try:
        return typestore().deserialize_cdr(memoryview(raw), msgtype)
    except CdrError:
        raise
    except KeyError:
        raise CdrError(f"unknown message type {msgtype!r}") from None
    except Exception as e:  # rosbags raises SerdeError and a few others
        raise CdrError(f"cannot decode as {msgtype}: {e}") from None


def deserialize_any(raw: bytes | bytearray | memoryview, candidates: tuple[str, ...]) -> tuple[Any, str]:
    """Try each type in order; ``(msg, type)`` of the first that decodes the whole payload
    (rosbags rejects a size mismatch), else CdrError listing the reasons."""
    errs = []
    for t in candidates:
        try:
            return deserialize(raw, t), t
        except CdrError as e:
            errs.append(str(e))
    raise CdrError("; ".join(errs) or "no candidate types")


def serialize(msg: Any, msgtype: str, distro: str = "humble") -> bytes:
    """Message object (a class of ``types(distro)``) → little-endian CDR bytes (with the
    encapsulation header). Jazzy's visualization_msgs/Marker has fields Humble's lacks, so
    build and serialise with the distro whose type hash you advertise."""
    return bytes(typestore(distro).serialize_cdr(msg, msgtype, little_endian=True))


def type_hash(msgtype: str, distro: str = "jazzy") -> str:
    """The type hash rmw_zenoh of ``distro`` puts in keys and graph tokens."""
    if distro == "humble":
        return TYPE_HASH_NONE
    return typestore(distro).hash_rihs01(msgtype)


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment: int64 sequence number, int64 source timestamp (ns),
    then the 16-byte gid as a length-prefixed byte sequence (Zenoh's serializer format)."""
    if len(gid) != 16:
        raise ValueError("gid must be 16 bytes")
    return struct.pack("<qqB", int(seq), int(stamp_ns), 16) + bytes(gid)


def parse_attachment(data: bytes | bytearray | memoryview) -> tuple[int, int, bytes] | None:
    """Inverse of :func:`attachment`: ``(seq, stamp_ns, gid)``, or None when ``data`` is not one."""
    b = bytes(data)
    if len(b) != 33 or b[16] != 16:
        return None
    seq, ts = struct.unpack_from("<qq", b)
    return seq, ts, b[17:]
