"""Wire codec (docs/messages.md): the generic envelope and the frame message.

Module map
----------
* :mod:`common.wire.envelope`: the generic message layout (u32 header length, msgpack
  header, 8-byte aligned out-of-band numpy buffers), :class:`WireLimits`, :class:`WireError`,
  :func:`encode_message` / :func:`decode_message`. Every schema (frames, and the control
  messages of :mod:`common.messages`) is carried by it.
* :mod:`common.wire.frame`: the ``rayfronts.frame`` v2 schema (reads v1): :func:`encode_frame` /
  :func:`decode_frame`, field validation, :func:`validate_robot_id`.
* :mod:`common.wire.images`: depth / RGB / label / confidence image codecs (PNG, JPEG,
  zlib f32, f16) with the pre-decode PNG chunk walk and JPEG header parse. OpenCV is
  imported there on first use only.
* :mod:`common.wire.fields`: one-line field errors and the small type/shape checks shared by
  ``frame`` and ``images``.

Every public name is re-exported here: ``from common.wire import X`` is the supported import.
"""
from __future__ import annotations

from common.wire.envelope import (
    ALLOWED_DTYPES,
    DEFAULT_LIMITS,
    WireError,
    WireLimits,
    decode_message,
    encode_message,
)
from common.wire.frame import (
    FEATURE_CODECS,
    FRAME_SCHEMA,
    FRAME_VERSION,
    FRAME_VERSIONS,
    decode_frame,
    encode_frame,
    validate_robot_id,
)
from common.wire.images import DEPTH_CODECS, PNG16MM_MAX_DEPTH, RGB_CODECS

__all__ = [
    "WireError",
    "WireLimits",
    "DEFAULT_LIMITS",
    "ALLOWED_DTYPES",
    "encode_message",
    "decode_message",
    "FRAME_SCHEMA",
    "FRAME_VERSION",
    "FRAME_VERSIONS",
    "FEATURE_CODECS",
    "DEPTH_CODECS",
    "RGB_CODECS",
    "PNG16MM_MAX_DEPTH",
    "encode_frame",
    "decode_frame",
    "validate_robot_id",
]
