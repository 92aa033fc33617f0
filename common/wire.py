"""Wire codec: msgpack header + out-of-band array buffers, and the frame message (DESIGN §4).

Message layout (every schema)
-----------------------------
::

    [u32 little-endian header length L][msgpack map, L bytes][zero pad to 8][buf 0][pad][buf 1]...

* The msgpack header is a map ``{"schema": str, "v": int, **body}`` with string keys only.
* numpy arrays anywhere in the body (inside dicts and lists, any depth) are replaced by
  ``{"__nd__": [dtype.str, shape, offset, nbytes]}``; their bytes (C order, little-endian)
  are appended after the header. ``offset`` counts from the start of the buffer region,
  which begins at the first 8-byte boundary after the header; every buffer starts 8-byte
  aligned. The key ``"__nd__"`` is reserved.
* Allowed dtypes: ``bool, u1, i1, u2, i2, u4, i4, u8, i8, f2, f4, f8`` (little-endian).
  Big-endian input arrays are byte-swapped on encode; anything else is refused.
* numpy scalars are sent as Python scalars; tuples come back as lists.
* Decoded arrays are **zero-copy, read-only** ``np.frombuffer`` views over the input
  buffer (call ``.copy()`` before mutating). Keep the input alive as long as you use them.

Errors: every decode failure (and every encode of something that cannot go on the wire)
raises :class:`WireError` with a message naming the field, what was expected and what
was found. Decoders never raise anything else.

The frame message (schema ``"rayfronts.frame"``, v 1) is built on the generic codec by
:func:`encode_frame` / :func:`decode_frame`; see :func:`encode_frame` for its fields.
"""
from __future__ import annotations

import math
import re
import struct
import zlib
from dataclasses import dataclass
from typing import Any, Collection

import cv2
import msgpack
import numpy as np

from common.conventions import is_rigid
from common.frame import Frame

__all__ = [
    "WireError",
    "WireLimits",
    "DEFAULT_LIMITS",
    "ALLOWED_DTYPES",
    "encode_message",
    "decode_message",
    "FRAME_SCHEMA",
    "FRAME_VERSION",
    "DEPTH_CODECS",
    "RGB_CODECS",
    "PNG16MM_MAX_DEPTH",
    "encode_frame",
    "decode_frame",
    "validate_robot_id",
]


class WireError(Exception):
    """A message could not be decoded (or a value could not be encoded); the text says why."""


@dataclass
class WireLimits:
    """Upper bounds a decoder enforces before allocating or decoding anything.

    Sizes are in bytes, pixels or elements as named. Defaults suit a robot frame stream.
    """

    max_message_bytes: int = 64 << 20
    """Whole message (header + buffers)."""
    max_header_bytes: int = 16 << 20
    """The msgpack header alone."""
    max_container_len: int = 1 << 20
    """Entries of any msgpack array or map in the header."""
    max_nesting: int = 32
    """Nesting depth of dicts/lists in the body."""
    max_array_elems: int = 1 << 27
    """Elements of one out-of-band array (and of any one dimension)."""
    max_ndim: int = 8
    """Dimensions of one out-of-band array."""
    max_pixels: int = 4096 * 4096
    """Pixels (H·W) of a depth, RGB, label or confidence image."""
    max_channels: int = 4096
    """Feature channels C."""
    max_robot_id_len: int = 64
    """Robot ids match ``[A-Za-z0-9_-]{1,max_robot_id_len}``."""
    max_string_len: int = 4096
    """Characters of feature_space and of meta keys / string values."""
    max_meta_items: int = 64
    """Entries of a frame's meta dict."""


DEFAULT_LIMITS = WireLimits()

# --------------------------------------------------------------------------------------
# Generic codec
# --------------------------------------------------------------------------------------

_ND = "__nd__"
_ALIGN = 8
_DTYPES: dict[str, np.dtype] = {
    s: np.dtype(s)
    for s in ("|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8")
}
ALLOWED_DTYPES = frozenset(_DTYPES)
_HEADER_LEN = struct.Struct("<I")


def _align(n: int) -> int:
    return (n + _ALIGN - 1) & ~(_ALIGN - 1)


def _tname(x: Any) -> str:
    return type(x).__name__


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


class _Encoder:
    """Walks a body, replacing arrays by references and collecting their buffers."""

    __slots__ = ("bufs", "offset")

    def __init__(self) -> None:
        self.bufs: list[tuple[int, np.ndarray]] = []
        self.offset = 0

    def array(self, a: np.ndarray, path: str) -> dict:
        dt = a.dtype
        if dt.byteorder == ">":
            a = a.astype(dt.newbyteorder("<"))
            dt = a.dtype
        ds = dt.str
        if ds not in _DTYPES:
            raise WireError(
                f"{path or 'array'}: dtype {dt} cannot go on the wire "
                f"(allowed: {', '.join(sorted(_DTYPES))})"
            )
        if not a.flags.c_contiguous:
            a = np.ascontiguousarray(a)  # (never for 0-d arrays: it would make them 1-D)
        off = _align(self.offset)
        self.bufs.append((off, a.reshape(-1).view(np.uint8)))
        self.offset = off + a.nbytes
        return {_ND: [ds, list(a.shape), off, a.nbytes]}

    def walk(self, obj: Any, path: str, depth: int) -> Any:
        if obj is None or isinstance(obj, (bool, int, float, str, bytes)):
            return obj
        if isinstance(obj, np.ndarray):
            return self.array(obj, path)
        if isinstance(obj, np.generic):
            v = obj.item()
            if v is None or isinstance(v, (bool, int, float, str, bytes)):
                return v
            raise WireError(f"{path}: numpy scalar of dtype {obj.dtype} cannot go on the wire")
        if depth > 64:
            raise WireError(f"{path}: nesting deeper than 64 levels")
        if isinstance(obj, dict):
            out = {}
            for k, v in obj.items():
                if type(k) is not str:
                    raise WireError(f"{path or 'body'}: map key {k!r} is not a str")
                if k == _ND:
                    raise WireError(f"{path or 'body'}: key {_ND!r} is reserved for array references")
                out[k] = self.walk(v, _join(path, k), depth + 1)
            return out
        if isinstance(obj, (list, tuple)):
            return [self.walk(v, f"{path}[{i}]", depth + 1) for i, v in enumerate(obj)]
        if isinstance(obj, (bytearray, memoryview)):
            return bytes(obj)
        raise WireError(f"{path or 'body'}: cannot encode a value of type {_tname(obj)}")


def encode_message(schema: str, v: int, body: dict) -> bytes:
    """Encode ``body`` as a message of ``schema`` version ``v`` (layout: module docstring).

    ``body`` maps str keys to None/bool/int/float/str/bytes, numpy scalars, numpy arrays,
    and dicts/lists/tuples of those. Keys ``"schema"`` and ``"v"`` are reserved.
    Raises :class:`WireError` if something cannot be encoded.
    """
    if type(schema) is not str or not schema:
        raise WireError(f"schema: expected a non-empty str, got {schema!r}")
    if type(v) is not int or v < 0:
        raise WireError(f"v: expected an int >= 0, got {v!r}")
    if not isinstance(body, dict):
        raise WireError(f"body: expected a dict, got {_tname(body)}")
    for k in ("schema", "v"):
        if k in body:
            raise WireError(f"body: key {k!r} is reserved for the message header")
    enc = _Encoder()
    tree = enc.walk(body, "", 0)
    header = {"schema": schema, "v": v}
    header.update(tree)
    try:
        hdr = msgpack.packb(header, use_bin_type=True)
    except (OverflowError, ValueError, TypeError) as e:
        raise WireError(f"body: msgpack cannot encode it: {e}") from e
    hl = len(hdr)
    if hl >= 1 << 32:
        raise WireError(f"header: {hl} bytes does not fit the 4-byte length field")
    parts: list[Any] = [_HEADER_LEN.pack(hl), hdr]
    if enc.bufs:
        pad = _align(4 + hl) - (4 + hl)
        if pad:
            parts.append(b"\0" * pad)
        pos = 0
        for off, buf in enc.bufs:
            if off > pos:
                parts.append(b"\0" * (off - pos))
            parts.append(buf)
            pos = off + buf.nbytes
    return b"".join(parts)


class _Decoder:
    """Resolves array references of one message against its buffer region."""

    __slots__ = ("mv", "base", "region", "lim")

    def __init__(self, mv: memoryview, base: int, lim: WireLimits) -> None:
        self.mv = mv
        self.base = base
        self.region = max(0, len(mv) - base)
        self.lim = lim

    def array(self, ref: dict, path: str) -> np.ndarray:
        where = path or "array"
        if len(ref) != 1:
            raise WireError(f"{where}: an array reference must have only the key {_ND!r}, got {sorted(map(str, ref))}")
        r = ref[_ND]
        if type(r) is not list or len(r) != 4:
            raise WireError(f"{where}: array reference must be [dtype, shape, offset, nbytes], got {r!r:.200}")
        ds, shape, off, nbytes = r
        dt = _DTYPES.get(ds) if type(ds) is str else None
        if dt is None:
            raise WireError(f"{where}: dtype {ds!r:.50} not allowed (allowed: {', '.join(sorted(_DTYPES))})")
        lim = self.lim
        if type(shape) is not list or len(shape) > lim.max_ndim:
            raise WireError(f"{where}: shape must be a list of at most {lim.max_ndim} ints, got {shape!r:.200}")
        n = 1
        for s in shape:
            if type(s) is not int or s < 0 or s > lim.max_array_elems:
                raise WireError(
                    f"{where}: shape {shape!r:.200} has an invalid dimension {s!r:.50} "
                    f"(need ints in [0, {lim.max_array_elems}])"
                )
            n *= s
        if n > lim.max_array_elems:
            raise WireError(f"{where}: shape {shape} has {n} elements, more than the limit {lim.max_array_elems}")
        if type(off) is not int or off < 0:
            raise WireError(f"{where}: offset must be an int >= 0, got {off!r:.50}")
        if type(nbytes) is not int or nbytes != n * dt.itemsize:
            raise WireError(
                f"{where}: nbytes {nbytes!r:.50} != prod(shape {shape}) * itemsize {dt.itemsize} = {n * dt.itemsize}"
            )
        if off + nbytes > self.region:
            raise WireError(
                f"{where}: buffer [{off}, {off + nbytes}) is out of bounds "
                f"(the buffer region has {self.region} bytes)"
            )
        if n == 0:
            a = np.empty(tuple(shape), dtype=dt)
        else:
            a = np.frombuffer(self.mv, dtype=dt, count=n, offset=self.base + off).reshape(tuple(shape))
            if dt.kind == "b" and (a.view(np.uint8) > 1).any():
                raise WireError(f"{where}: bool array holds bytes other than 0/1")
        a.flags.writeable = False
        return a

    def walk(self, obj: Any, path: str, depth: int) -> Any:
        if depth > self.lim.max_nesting:
            raise WireError(f"{path}: nesting deeper than the limit {self.lim.max_nesting}")
        if type(obj) is dict:
            if _ND in obj:
                return self.array(obj, path)
            for k, v in obj.items():
                if type(k) is not str:
                    raise WireError(f"{path or 'header'}: map key {k!r:.50} is not a str")
                if type(v) is dict or type(v) is list:
                    obj[k] = self.walk(v, _join(path, k), depth + 1)
        else:  # list
            for i, v in enumerate(obj):
                if type(v) is dict or type(v) is list:
                    obj[i] = self.walk(v, f"{path}[{i}]", depth + 1)
        return obj


def _byte_view(data: Any) -> memoryview:
    try:
        mv = memoryview(data)
    except TypeError:
        raise WireError(f"message: expected bytes, bytearray or memoryview, got {_tname(data)}") from None
    if mv.ndim != 1 or mv.format not in ("B", "b", "c"):
        if not mv.c_contiguous:
            raise WireError("message: buffer is not contiguous")
        mv = mv.cast("B")
    elif not mv.c_contiguous:
        raise WireError("message: buffer is not contiguous")
    return mv


def _unpack_header(raw: memoryview, lim: WireLimits) -> Any:
    n = len(raw)
    try:
        return msgpack.unpackb(
            raw,
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_str_len=n,
            max_bin_len=n,
            max_array_len=min(n, lim.max_container_len),
            max_map_len=min(n, lim.max_container_len),
            max_ext_len=0,
        )
    except msgpack.ExtraData as e:
        raise WireError(f"header: {len(e.extra)} bytes of trailing data after the msgpack map") from e
    except UnicodeDecodeError as e:
        raise WireError(f"header: a string is not valid UTF-8 ({e.reason})") from e
    except (ValueError, msgpack.UnpackException, TypeError, OverflowError, RecursionError) as e:
        raise WireError(f"header: invalid msgpack ({type(e).__name__}: {e})") from e


def _check_expected(name: str, got: Any, want: Any) -> None:
    if want is None:
        return
    if isinstance(want, (str, int)):
        if got != want:
            raise WireError(f"{name}: expected {want!r}, got {got!r:.100}")
    elif got not in want:
        raise WireError(f"{name}: expected one of {sorted(want)!r}, got {got!r:.100}")


def decode_message(
    data: bytes | bytearray | memoryview,
    *,
    schema: str | None = None,
    v: int | Collection[int] | None = None,
    limits: WireLimits | None = None,
) -> tuple[str, int, dict]:
    """Decode a message; returns ``(schema, v, body)`` with arrays as read-only views of ``data``.

    If ``schema`` / ``v`` are given, the message must match them (``v`` may be a collection
    of accepted versions). Cheap: nothing but the header is parsed, so it also serves to peek
    at a message. Raises :class:`WireError` for anything malformed or over ``limits``.
    """
    lim = limits or DEFAULT_LIMITS
    try:
        mv = _byte_view(data)
        n = len(mv)
        if n > lim.max_message_bytes:
            raise WireError(f"message: {n} bytes is over the limit {lim.max_message_bytes}")
        if n < 4:
            raise WireError(f"message: {n} bytes is too short for the 4-byte header length")
        (hl,) = _HEADER_LEN.unpack_from(mv, 0)
        if hl == 0:
            raise WireError("header: length is 0")
        if hl > lim.max_header_bytes:
            raise WireError(f"header: length {hl} is over the limit {lim.max_header_bytes}")
        if 4 + hl > n:
            raise WireError(f"header: length {hl} runs past the end of the {n}-byte message")
        header = _unpack_header(mv[4 : 4 + hl], lim)
        if type(header) is not dict:
            raise WireError(f"header: expected a msgpack map, got {_tname(header)}")
        if "schema" not in header:
            raise WireError("schema: required field missing")
        sch = header.pop("schema")
        if type(sch) is not str:
            raise WireError(f"schema: expected str, got {_tname(sch)}")
        _check_expected("schema", sch, schema)
        if "v" not in header:
            raise WireError("v: required field missing")
        ver = header.pop("v")
        if type(ver) is not int:
            raise WireError(f"v: expected int, got {_tname(ver)}")
        _check_expected(f"v (version of {sch!r})", ver, v)
        body = _Decoder(mv, _align(4 + hl), lim).walk(header, "", 0)
        return sch, ver, body
    except WireError:
        raise
    except Exception as e:  # safety net: nothing but WireError leaves a decoder
        raise WireError(f"message: malformed ({type(e).__name__}: {e})") from e


# --------------------------------------------------------------------------------------
# Frame message
# --------------------------------------------------------------------------------------

FRAME_SCHEMA = "rayfronts.frame"
FRAME_VERSION = 1
DEPTH_CODECS = ("auto", "png16mm", "f32", "f16")
RGB_CODECS = ("jpeg", "raw")
PNG16MM_MAX_DEPTH = 65.534
"""Largest depth (m) the ``png16mm`` codec stores without clipping."""

_ROBOT_RE = re.compile(r"[A-Za-z0-9_-]+")
_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_SEQUENTIAL = frozenset({0xC0, 0xC1})  # baseline / extended Huffman: what encoders send
_IMREAD_COLOR = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
_F16_TINY = np.float16(np.finfo(np.float16).tiny)


def validate_robot_id(robot: Any, limits: WireLimits | None = None) -> str:
    """Return ``robot`` if it matches ``[A-Za-z0-9_-]{1,max_robot_id_len}``, else raise WireError."""
    lim = limits or DEFAULT_LIMITS
    if type(robot) is not str:
        raise WireError(f"robot: expected str, got {_tname(robot)}")
    if not 1 <= len(robot) <= lim.max_robot_id_len or not _ROBOT_RE.fullmatch(robot):
        raise WireError(
            f"robot: id {robot!r:.80} must match [A-Za-z0-9_-]{{1,{lim.max_robot_id_len}}}"
        )
    return robot


def _enc_err(field: str, msg: str) -> WireError:
    return WireError(f"cannot encode frame: {field}: {msg}")


def _as_array(x: Any, field: str) -> np.ndarray:
    try:
        return np.asarray(x)
    except Exception as e:
        raise _enc_err(field, f"not array-like ({e})") from e


def _imencode(ext: str, img: np.ndarray, params: list[int], field: str) -> np.ndarray:
    try:
        ok, buf = cv2.imencode(ext, img, params)
    except cv2.error as e:
        raise _enc_err(field, f"OpenCV could not encode {ext}: {e}") from e
    if not ok:
        raise _enc_err(field, f"OpenCV could not encode {ext}")
    return buf.reshape(-1)


def _encode_depth(depth: Any, codec: str) -> dict:
    d = _as_array(depth, "depth")
    if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
        raise _enc_err("depth", f"expected a non-empty (H, W) array, got shape {d.shape}")
    if d.dtype.kind != "f":
        raise _enc_err("depth", f"expected a float array in metres (convert integer mm first), got dtype {d.dtype}")
    d = d.astype(np.float32, copy=False)
    with np.errstate(invalid="ignore"):
        nodata = ~(d > 0)  # NaN, -inf and <= 0: no measurement
    posinf = np.isposinf(d)
    finite = ~(nodata | posinf)
    if codec == "auto":
        big = bool(finite.any()) and float(d[finite].max()) > PNG16MM_MAX_DEPTH + 0.0005
        codec = "f32" if big else "png16mm"
    h, w = d.shape
    if codec == "png16mm":
        with np.errstate(invalid="ignore", over="ignore"):
            mm = np.rint(d.astype(np.float64) * 1000.0)
            np.clip(mm, 1.0, 65534.0, out=mm)
        mm[nodata] = 0.0
        mm[posinf] = 65535.0
        data = _imencode(".png", mm.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1], "depth")
    elif codec == "f32":
        raw = np.array(d, dtype="<f4", order="C")
        raw[nodata] = np.nan
        data = np.frombuffer(zlib.compress(raw.tobytes(), 1), dtype=np.uint8)
    elif codec == "f16":
        with np.errstate(over="ignore"):
            data = d.astype("<f2")
        data[nodata] = np.nan
        data[finite & (data == 0)] = _F16_TINY  # tiny positive depths must stay > 0
    else:
        raise _enc_err("depth", f"unknown depth codec {codec!r} (known: {', '.join(DEPTH_CODECS)})")
    return {"codec": codec, "shape": [h, w], "data": data}


def _encode_rgb(rgb: Any, codec: str, quality: int) -> dict:
    a = _as_array(rgb, "rgb")
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise _enc_err("rgb", f"expected a (H, W, 3) uint8 array, got shape {a.shape} dtype {a.dtype}")
    if codec == "jpeg":
        if type(quality) is not int or not 0 <= quality <= 100:
            raise _enc_err("rgb", f"jpeg_quality must be an int in [0, 100], got {quality!r}")
        bgr = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2BGR)
        data = _imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality], "rgb")
    elif codec == "raw":
        data = np.ascontiguousarray(a)
    else:
        raise _enc_err("rgb", f"unknown rgb codec {codec!r} (known: {', '.join(RGB_CODECS)})")
    return {"codec": codec, "shape": list(a.shape), "data": data}


def _encode_f16(x: Any, field: str, ndim: int) -> np.ndarray:
    a = _as_array(x, field)
    if a.ndim != ndim or a.dtype.kind not in "fiu" or 0 in a.shape:
        raise _enc_err(field, f"expected a non-empty {ndim}-D float array, got shape {a.shape} dtype {a.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        a16 = np.ascontiguousarray(a, dtype="<f2")
    if not np.isfinite(a16).all():
        raise _enc_err(field, "non-finite values (after conversion to float16, |x| must be <= 65504)")
    return a16


def _encode_meta(meta: Any) -> dict:
    if meta is None:
        return {}
    if not isinstance(meta, dict):
        raise _enc_err("meta", f"expected a dict, got {_tname(meta)}")
    out = {}
    for k, v in meta.items():
        if type(k) is not str:
            raise _enc_err("meta", f"key {k!r} is not a str")
        if isinstance(v, np.generic):
            v = v.item()
        if not (v is None or isinstance(v, (bool, int, float, str))):
            raise _enc_err(f"meta.{k}", f"values must be None/bool/int/float/str, got {_tname(v)}")
        out[k] = v
    return out


def encode_frame(
    frame: Frame,
    *,
    jpeg_quality: int = 90,
    depth_codec: str = "auto",
    rgb_codec: str = "jpeg",
) -> bytes:
    """Encode a :class:`~common.frame.Frame` as a ``rayfronts.frame`` v1 message.

    Header fields (arrays out of band):

    ``robot`` str · ``seq`` int ≥ 0 · ``stamp`` float s · ``pose`` <f8 (4,4) · ``intrinsics``
    <f8 (3,3) · ``feature_space`` str · ``meta`` map str → None/bool/int/float/str ·
    ``features`` <f2 (C,h,w) or nil · ``global_feature`` <f2 (C,) or nil ·
    ``depth`` {codec, shape [H,W], data} · ``rgb`` {codec, shape [H',W',3], data} ·
    ``labels`` {codec "png16", data} or nil · ``confidence`` {codec "png8", data} or nil.

    Depth codecs (``depth_codec``):

    * ``"png16mm"``: 16-bit PNG (level 1) of millimetres; 0 = NaN, 65535 = +inf; finite
      values rounded to the nearest mm and clipped to [1, 65534] mm (≤ 0.5 mm error up to
      65.534 m, ≤ 1 mm below 1 mm).
    * ``"f32"``: zlib-compressed float32, lossless for every value.
    * ``"f16"``: float16, explicitly lossy (finite values > 65504 m become +inf).
    * ``"auto"``: ``png16mm`` if every finite depth ≤ 65.534 m, else ``f32``.

    With every codec, −inf and values ≤ 0 are stored as NaN ("no measurement").

    RGB: ``"jpeg"`` (``jpeg_quality``) or ``"raw"`` (lossless, zero-copy on decode).
    Features / global feature: cast to float16 (must stay finite). Labels: ints in
    [0, 65535], lossless 16-bit PNG. Confidence: NaN → 0, clipped to [0, 1], quantised to
    uint8 ``round(c·255)`` (8-bit PNG); decoded as ``q / 255`` (error ≤ 1/510).

    Raises :class:`WireError` (message prefixed ``cannot encode frame: <field>``) if the frame
    breaks the contract (bad robot id, non-rigid pose, mismatched shapes, ...).
    """
    if not isinstance(frame, Frame):
        raise WireError(f"cannot encode frame: expected a common.frame.Frame, got {_tname(frame)}")
    try:
        validate_robot_id(frame.robot)
    except WireError as e:
        raise WireError(f"cannot encode frame: {e}") from None
    seq = frame.seq
    if isinstance(seq, np.integer):
        seq = int(seq)
    if type(seq) is not int or seq < 0 or seq >= 1 << 64:
        raise _enc_err("seq", f"expected an int in [0, 2**64), got {seq!r}")
    try:
        stamp = float(frame.stamp)
    except (TypeError, ValueError):
        raise _enc_err("stamp", f"expected a float, got {_tname(frame.stamp)}") from None
    if isinstance(frame.stamp, bool) or not math.isfinite(stamp):
        raise _enc_err("stamp", f"expected a finite float, got {frame.stamp!r}")
    pose = _as_array(frame.pose, "pose")
    if pose.shape != (4, 4) or pose.dtype.kind not in "fiu":
        raise _enc_err("pose", f"expected a (4, 4) float array, got shape {pose.shape} dtype {pose.dtype}")
    pose = np.ascontiguousarray(pose, dtype="<f8")
    if not is_rigid(pose):
        raise _enc_err("pose", "not a finite rigid transform (proper rotation, last row 0 0 0 1)")
    K = _as_array(frame.intrinsics, "intrinsics")
    if K.shape != (3, 3) or K.dtype.kind not in "fiu":
        raise _enc_err("intrinsics", f"expected a (3, 3) float array, got shape {K.shape} dtype {K.dtype}")
    K = np.ascontiguousarray(K, dtype="<f8")
    _check_intrinsics(K, _enc_err)

    depth = _encode_depth(frame.depth, depth_codec)
    h, w = depth["shape"]
    rgb = _encode_rgb(frame.rgb, rgb_codec, jpeg_quality)

    features = None
    if frame.features is not None:
        features = _encode_f16(frame.features, "features", 3)
        c, fh, fw = features.shape
        if fh > h or fw > w:
            raise _enc_err("features", f"feature map {fh}x{fw} is larger than the depth image {h}x{w}")
    global_feature = None
    if frame.global_feature is not None:
        global_feature = _encode_f16(frame.global_feature, "global_feature", 1)
        if features is not None and global_feature.shape[0] != features.shape[0]:
            raise _enc_err(
                "global_feature",
                f"length {global_feature.shape[0]} != feature channels {features.shape[0]}",
            )

    labels = None
    if frame.labels is not None:
        lab = _as_array(frame.labels, "labels")
        if lab.shape != (h, w) or lab.dtype.kind not in "biu":
            raise _enc_err("labels", f"expected an ({h}, {w}) int array, got shape {lab.shape} dtype {lab.dtype}")
        if lab.size and (int(lab.min()) < 0 or int(lab.max()) > 65535):
            raise _enc_err("labels", f"values must be in [0, 65535], got [{lab.min()}, {lab.max()}]")
        labels = {
            "codec": "png16",
            "data": _imencode(".png", lab.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1], "labels"),
        }

    confidence = None
    if frame.confidence is not None:
        conf = _as_array(frame.confidence, "confidence")
        if conf.shape != (h, w) or conf.dtype.kind not in "fiub":
            raise _enc_err(
                "confidence", f"expected an ({h}, {w}) float array, got shape {conf.shape} dtype {conf.dtype}"
            )
        q = np.nan_to_num(conf.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
        q = np.rint(np.clip(q, 0.0, 1.0) * 255.0).astype(np.uint8)
        confidence = {
            "codec": "png8",
            "data": _imencode(".png", q, [cv2.IMWRITE_PNG_COMPRESSION, 1], "confidence"),
        }

    fs = frame.feature_space if frame.feature_space is not None else ""
    if type(fs) is not str:
        raise _enc_err("feature_space", f"expected str, got {_tname(fs)}")

    # Refuse what a decoder with the default limits would reject, rather than send it.
    lim = DEFAULT_LIMITS
    meta = _encode_meta(frame.meta)
    for field, npix in (("depth", h * w), ("rgb", rgb["shape"][0] * rgb["shape"][1])):
        if npix > lim.max_pixels:
            raise _enc_err(field, f"{npix} pixels is over the wire limit {lim.max_pixels}")
    for field, arr in (("features", features), ("global_feature", global_feature)):
        if arr is not None and arr.shape[0] > lim.max_channels:
            raise _enc_err(field, f"{arr.shape[0]} channels is over the wire limit {lim.max_channels}")
    if len(fs) > lim.max_string_len:
        raise _enc_err("feature_space", f"{len(fs)} chars is over the wire limit {lim.max_string_len}")
    try:
        _decode_meta(meta, lim)
    except WireError as e:
        raise WireError(f"cannot encode {e}") from None

    body = {
        "robot": frame.robot,
        "seq": seq,
        "stamp": stamp,
        "pose": pose,
        "intrinsics": K,
        "depth": depth,
        "rgb": rgb,
        "features": features,
        "feature_space": fs,
        "labels": labels,
        "confidence": confidence,
        "global_feature": global_feature,
        "meta": meta,
    }
    return encode_message(FRAME_SCHEMA, FRAME_VERSION, body)


# ---- frame decoding -------------------------------------------------------------------


def _err(field: str, msg: str) -> WireError:
    return WireError(f"frame.{field}: {msg}")


def _check_intrinsics(K: np.ndarray, err) -> None:
    if not np.isfinite(K).all():
        raise err("intrinsics", "not finite")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise err("intrinsics", f"fx and fy must be > 0, got fx={K[0, 0]} fy={K[1, 1]}")
    if abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9 or abs(K[2, 2] - 1.0) > 1e-9 or abs(K[1, 0]) > 1e-9:
        raise err("intrinsics", f"expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")


def _req(body: dict, key: str) -> Any:
    if key not in body:
        raise _err(key, "required field missing")
    return body[key]


def _nd(x: Any, field: str, dtype: str, ndim: int) -> np.ndarray:
    if type(x) is not np.ndarray:
        raise _err(field, f"expected an array, got {_tname(x)}")
    if x.dtype.str != dtype or x.ndim != ndim:
        raise _err(field, f"expected a {ndim}-D {dtype} array, got {x.ndim}-D {x.dtype.str} shape {x.shape}")
    return x


def _image_spec(body: dict, field: str, keys: tuple[str, ...]) -> dict:
    if field not in body:
        raise _err(field, "required field missing")
    spec = body[field]
    if type(spec) is not dict:
        raise _err(field, f"expected a map with keys {list(keys)}, got {_tname(spec)}")
    for k in keys:
        if k not in spec:
            raise _err(f"{field}.{k}", "required field missing")
    if type(spec["codec"]) is not str:
        raise _err(f"{field}.codec", f"expected str, got {_tname(spec['codec'])}")
    return spec


def _shape(x: Any, field: str, n: int, lim: WireLimits) -> list[int]:
    if type(x) is not list or len(x) != n or any(type(s) is not int or s < 1 for s in x):
        raise _err(field, f"expected {n} ints >= 1, got {x!r:.100}")
    if x[0] * x[1] > lim.max_pixels:
        raise _err(field, f"{x[0]}x{x[1]} pixels is over the limit {lim.max_pixels}")
    return x


def _bytes_array(x: Any, field: str) -> np.ndarray:
    a = _nd(x, field, "|u1", 1)
    if a.size == 0:
        raise _err(field, "empty")
    return a


def _png_check(buf: np.ndarray, field: str, hw: tuple[int, int], bit_depth: int) -> None:
    """Walk the PNG's chunks before handing it to OpenCV: signature, IHDR first (size, bit
    depth, greyscale), every chunk inside the buffer with a correct CRC, IEND last.

    OpenCV trusts chunk lengths: one flipped bit in a length costs it a second of CPU."""
    mv = memoryview(buf)
    n = len(mv)
    if n < 8 + 25 + 12 or bytes(mv[:8]) != _PNG_SIG:
        raise _err(field, "not a PNG image")
    i = 8
    while True:
        if i + 12 > n:
            raise _err(field, "corrupt PNG (truncated, no IEND chunk)")
        ln, typ = struct.unpack_from(">I4s", mv, i)
        end = i + 12 + ln
        if end > n:
            raise _err(field, f"corrupt PNG (chunk {typ!r} of {ln} bytes runs past the end)")
        (crc,) = struct.unpack_from(">I", mv, end - 4)
        if zlib.crc32(mv[i + 4 : end - 4]) != crc:
            raise _err(field, f"corrupt PNG (CRC mismatch in chunk {typ!r})")
        if i == 8:
            if typ != b"IHDR" or ln != 13:
                raise _err(field, "corrupt PNG (IHDR is not the first chunk)")
            w, h, depth, colour = struct.unpack_from(">IIBB", mv, i + 8)
            if (h, w) != tuple(hw):
                raise _err(field, f"PNG is {h}x{w}, expected {hw[0]}x{hw[1]}")
            if depth != bit_depth or colour != 0:
                raise _err(field, f"expected a {bit_depth}-bit greyscale PNG, "
                                  f"got bit depth {depth} colour type {colour}")
        if typ == b"IEND":
            break
        i = end
    if end != n:
        raise _err(field, f"corrupt PNG ({n - end} bytes after IEND)")


def _png_decode(buf: np.ndarray, field: str, hw: tuple[int, int], dtype: type) -> np.ndarray:
    _png_check(buf, field, hw, np.dtype(dtype).itemsize * 8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise _err(field, f"PNG decode failed ({e})") from e
    if img is None or img.dtype != dtype or img.shape != tuple(hw):
        got = None if img is None else (img.shape, img.dtype)
        raise _err(field, f"PNG decode failed (expected {hw} {np.dtype(dtype)}, got {got})")
    return img


def _jpeg_size(buf: np.ndarray, field: str) -> tuple[int, int, int]:
    """(height, width, components) from the JPEG's SOF segment, without decoding it."""
    b = memoryview(buf)
    n = len(b)
    if n < 4 or b[0] != 0xFF or b[1] != 0xD8:
        raise _err(field, "not a JPEG image (no SOI marker)")
    if b[n - 2] != 0xFF or b[n - 1] != 0xD9:
        raise _err(field, "corrupt JPEG (truncated: no EOI marker at the end)")
    i = 2
    while i + 4 <= n:
        if b[i] != 0xFF:
            raise _err(field, f"corrupt JPEG (expected a marker at byte {i})")
        m = b[i + 1]
        if m == 0xFF:
            i += 1
            continue
        if m == 0x01 or 0xD0 <= m <= 0xD8:
            i += 2
            continue
        if m in (0xD9, 0xDA):
            break
        seg = (b[i + 2] << 8) | b[i + 3]
        if seg < 2:
            raise _err(field, f"corrupt JPEG (segment length {seg} at byte {i})")
        if m in _JPEG_SOF:
            if m not in _JPEG_SEQUENTIAL:  # progressive/lossless/arithmetic: slow paths, not ours
                raise _err(field, f"unsupported JPEG process (SOF marker 0x{m:02X}; need baseline)")
            if seg < 8 or i + 10 > n:
                raise _err(field, "corrupt JPEG (truncated frame header)")
            return (b[i + 5] << 8) | b[i + 6], (b[i + 7] << 8) | b[i + 8], b[i + 9]
        i += 2 + seg
    raise _err(field, "corrupt JPEG (no frame header before the scan)")


def _decode_depth(body: dict, lim: WireLimits) -> np.ndarray:
    spec = _image_spec(body, "depth", ("codec", "shape", "data"))
    h, w = _shape(spec["shape"], "depth.shape", 2, lim)
    codec, data = spec["codec"], spec["data"]
    if codec == "png16mm":
        u = _png_decode(_bytes_array(data, "depth.data"), "depth.data", (h, w), np.uint16)
        d = u.astype(np.float32)
        d /= np.float32(1000.0)
        d[u == 0] = np.nan
        d[u == 65535] = np.inf
        return d
    if codec == "f32":
        buf = _bytes_array(data, "depth.data")
        want = h * w * 4
        try:
            z = zlib.decompressobj()
            raw = z.decompress(buf, want)
            extra = False
            if len(raw) == want and not z.eof:  # stopped at max_length: is there more?
                extra = bool(z.decompress(z.unconsumed_tail, 1))
        except zlib.error as e:
            raise _err("depth.data", f"corrupt zlib stream ({e})") from e
        if len(raw) != want or extra or not z.eof:
            raise _err("depth.data", f"zlib stream does not hold exactly {h}x{w} float32 ({want} bytes)")
        d = np.frombuffer(raw, dtype="<f4").reshape(h, w).copy()
    elif codec == "f16":
        a = _nd(data, "depth.data", "<f2", 2)
        if a.shape != (h, w):
            raise _err("depth.data", f"shape {a.shape} != declared {(h, w)}")
        d = a.astype(np.float32)
    else:
        raise _err("depth.codec", f"unknown codec {codec!r:.50} (known: png16mm, f32, f16)")
    if (d <= 0).any():  # NaN compares False; catches -inf and non-positive values
        raise _err("depth.data", "holds values <= 0 or -inf (no-measurement must be NaN)")
    return d


def _decode_rgb(body: dict, lim: WireLimits) -> np.ndarray:
    spec = _image_spec(body, "rgb", ("codec", "shape", "data"))
    shape = _shape(spec["shape"], "rgb.shape", 3, lim)
    if shape[2] != 3:
        raise _err("rgb.shape", f"expected 3 channels, got {shape[2]}")
    hw = (shape[0], shape[1])
    codec, data = spec["codec"], spec["data"]
    if codec == "raw":
        a = _nd(data, "rgb.data", "|u1", 3)
        if list(a.shape) != shape:
            raise _err("rgb.data", f"shape {list(a.shape)} != declared {shape}")
        return a
    if codec != "jpeg":
        raise _err("rgb.codec", f"unknown codec {codec!r:.50} (known: jpeg, raw)")
    buf = _bytes_array(data, "rgb.data")
    jh, jw, nc = _jpeg_size(buf, "rgb.data")
    if (jh, jw) != hw or nc != 3:
        raise _err("rgb.data", f"JPEG is {jh}x{jw} with {nc} components, expected {hw[0]}x{hw[1]} with 3")
    try:
        bgr = cv2.imdecode(buf, _IMREAD_COLOR)
    except cv2.error as e:
        raise _err("rgb.data", f"JPEG decode failed ({e})") from e
    if bgr is None or bgr.shape != (hw[0], hw[1], 3) or bgr.dtype != np.uint8:
        raise _err("rgb.data", "JPEG decode failed")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _f16_finite(a: np.ndarray) -> bool:
    # exponent bits all ones <=> inf or NaN; integer ops are faster than isfinite on f16
    return not ((a.view(np.uint16) & 0x7C00) == 0x7C00).any()


def _decode_meta(meta: Any, lim: WireLimits) -> dict:
    if meta is None:
        return {}
    if type(meta) is not dict:
        raise _err("meta", f"expected a map, got {_tname(meta)}")
    if len(meta) > lim.max_meta_items:
        raise _err("meta", f"{len(meta)} entries is over the limit {lim.max_meta_items}")
    for k, v in meta.items():
        if len(k) > lim.max_string_len:
            raise _err("meta", f"key of {len(k)} chars is over the limit {lim.max_string_len}")
        if not (v is None or type(v) in (bool, int, float, str)):
            raise _err(f"meta.{k:.50}", f"values must be None/bool/int/float/str, got {_tname(v)}")
        if type(v) is str and len(v) > lim.max_string_len:
            raise _err(f"meta.{k:.50}", f"string of {len(v)} chars is over the limit {lim.max_string_len}")
    return meta


def decode_frame(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> Frame:
    """Decode and validate a ``rayfronts.frame`` v1 message (see :func:`encode_frame`).

    Returns a :class:`Frame` whose fields satisfy the frame contract: depth float32 (H, W)
    with NaN / +inf / positive values, rgb (H', W', 3) uint8 RGB, features (C, h, w) float16
    finite with h ≤ H and w ≤ W, labels int32 (H, W), confidence float32 (H, W) in [0, 1],
    global_feature float16 (C,), pose float64 rigid, intrinsics float64.
    ``features``, ``global_feature`` and raw RGB are zero-copy read-only views of ``data``;
    the other arrays are fresh. Raises :class:`WireError` for anything malformed.
    """
    lim = limits or DEFAULT_LIMITS
    _, _, b = decode_message(data, schema=FRAME_SCHEMA, v=FRAME_VERSION, limits=lim)
    try:
        return _decode_frame_body(b, lim)
    except WireError:
        raise
    except Exception as e:  # safety net: nothing but WireError leaves a decoder
        raise WireError(f"frame: malformed ({type(e).__name__}: {e})") from e


def _decode_frame_body(b: dict, lim: WireLimits) -> Frame:
    robot = _req(b, "robot")
    try:
        validate_robot_id(robot, lim)
    except WireError as e:
        raise WireError(f"frame.{e}") from None
    seq = _req(b, "seq")
    if type(seq) is not int or seq < 0:
        raise _err("seq", f"expected an int >= 0, got {seq!r:.50}")
    stamp = _req(b, "stamp")
    if type(stamp) not in (float, int) or not math.isfinite(stamp):
        raise _err("stamp", f"expected a finite float, got {stamp!r:.50}")
    pose = _nd(_req(b, "pose"), "pose", "<f8", 2)
    if pose.shape != (4, 4):
        raise _err("pose", f"expected shape (4, 4), got {pose.shape}")
    with np.errstate(all="ignore"):  # huge finite entries overflow r @ r.T: not rigid either
        rigid = is_rigid(pose)
    if not rigid:
        raise _err("pose", "not a finite rigid transform (proper rotation, last row 0 0 0 1)")
    K = _nd(_req(b, "intrinsics"), "intrinsics", "<f8", 2)
    if K.shape != (3, 3):
        raise _err("intrinsics", f"expected shape (3, 3), got {K.shape}")
    _check_intrinsics(K, _err)
    fs = b.get("feature_space", "")
    if fs is None:
        fs = ""
    if type(fs) is not str or len(fs) > lim.max_string_len:
        raise _err("feature_space", f"expected a str of at most {lim.max_string_len} chars, got {_tname(fs)}")
    meta = _decode_meta(b.get("meta"), lim)

    features = b.get("features")
    if features is not None:
        features = _nd(features, "features", "<f2", 3)
        c = features.shape[0]
        if not 1 <= c <= lim.max_channels:
            raise _err("features", f"{c} channels, expected 1..{lim.max_channels}")
    gf = b.get("global_feature")
    if gf is not None:
        gf = _nd(gf, "global_feature", "<f2", 1)
        if not 1 <= gf.shape[0] <= lim.max_channels:
            raise _err("global_feature", f"length {gf.shape[0]}, expected 1..{lim.max_channels}")
        if features is not None and gf.shape[0] != features.shape[0]:
            raise _err("global_feature", f"length {gf.shape[0]} != feature channels {features.shape[0]}")
        if not _f16_finite(gf):
            raise _err("global_feature", "holds NaN or inf")

    # Cheap checks on the declared sizes come before any image decoding.
    dspec = b.get("depth")
    if type(dspec) is dict and "shape" in dspec:
        h, w = _shape(dspec["shape"], "depth.shape", 2, lim)
        if features is not None:
            _, fh, fw = features.shape
            if not (1 <= fh <= h and 1 <= fw <= w):
                raise _err("features", f"feature map {fh}x{fw} must be non-empty and at most the depth size {h}x{w}")
    if features is not None and not _f16_finite(features):
        raise _err("features", "holds NaN or inf")

    depth = _decode_depth(b, lim)
    hw = depth.shape
    rgb = _decode_rgb(b, lim)

    labels = b.get("labels")
    if labels is not None:
        spec = _image_spec(b, "labels", ("codec", "data"))
        if spec["codec"] != "png16":
            raise _err("labels.codec", f"unknown codec {spec['codec']!r:.50} (known: png16)")
        labels = _png_decode(_bytes_array(spec["data"], "labels.data"), "labels.data", hw, np.uint16)
        labels = labels.astype(np.int32)
    conf = b.get("confidence")
    if conf is not None:
        spec = _image_spec(b, "confidence", ("codec", "data"))
        if spec["codec"] != "png8":
            raise _err("confidence.codec", f"unknown codec {spec['codec']!r:.50} (known: png8)")
        q = _png_decode(_bytes_array(spec["data"], "confidence.data"), "confidence.data", hw, np.uint8)
        conf = q.astype(np.float32)
        conf /= np.float32(255.0)

    return Frame(
        robot=robot,
        seq=seq,
        stamp=float(stamp),
        pose=pose.copy(),
        intrinsics=K.copy(),
        depth=depth,
        rgb=rgb,
        features=features,
        feature_space=fs,
        labels=labels,
        confidence=conf,
        global_feature=gf,
        meta=meta,
    )
