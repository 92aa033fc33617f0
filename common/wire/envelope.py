"""Generic wire envelope: msgpack header + 8-byte aligned out-of-band array buffers (docs/messages.md#envelope).

Part of the ``common.wire`` package (module map in ``common/wire/__init__.py``). This module
knows nothing of any schema; :mod:`common.wire.frame` and :mod:`common.messages` build on it.

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

Limits: :class:`WireLimits` (one place for every size bound a decoder enforces). The
header's size, container entries, string / binary lengths are bounded *inside* msgpack
(``msgpack.unpackb``'s ``max_*_len`` limits, checked before it allocates), so the cost of
a rejected header is bounded by its byte length; the frame schema uses a tight profile
(:func:`frame_header_limits`: a 64 KiB header, at most 2·``max_meta_items`` entries per
container, no binary, nesting 8, at most 256 maps/lists in all: msgpack hooks stop the unpack
at the 257th), measured at < 2 ms of CPU for the worst header of that size, 0.3 ms for
the worst container flood (``tests/test_faults.py``). Deep nesting stops in msgpack's own
fixed stack.

The message must end exactly where its last buffer ends (or at the header when it has no
buffers): trailing bytes are an error, like everything else the encoder never writes.

Reasons: :attr:`WireError.reason` is a short code from a fixed vocabulary
(``frame.<field>`` for a frame field, else ``header``, ``schema``, ``version``,
``message``, ``array``), so counting rejects by reason stays bounded whatever the input.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from typing import Any, Collection

import msgpack
import numpy as np

#: frame fields a reject reason may name (``frame.<field>``); anything else is ``frame.malformed``
FRAME_FIELDS = frozenset({"robot", "seq", "stamp", "pose", "intrinsics", "feature_space", "meta", "features",
                          "global_feature", "depth", "rgb", "labels", "confidence"})
_TOP_REASONS = {"header": "header", "schema": "schema", "v": "version", "message": "message"}


class WireError(Exception):
    """A message could not be decoded (or a value could not be encoded); the text says why."""

    @property
    def reason(self) -> str:
        """A short, stable reject reason from a fixed vocabulary (module docstring)."""
        return reject_reason(str(self))


def reject_reason(text: str) -> str:
    """The bounded reason code of a decode error text: ``frame.depth``, ``frame.pose``, ...,
    ``header``, ``schema``, ``version``, ``message``, ``array`` (never attacker text)."""
    head = text.split(":", 1)[0].strip()
    if head.startswith("cannot encode"):
        return "encode"
    if head.startswith("frame"):
        field = head[len("frame"):].lstrip(".").split(".")[0].split("[")[0].split(" ")[0]
        return f"frame.{field}" if field in FRAME_FIELDS else "frame.malformed"
    word = head.split(" ")[0].split(".")[0].split("[")[0]
    if word in FRAME_FIELDS:   # an array reference inside a frame field (envelope errors name the path)
        return f"frame.{word}"
    return _TOP_REASONS.get(word, "array")


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
    max_frame_header_bytes: int = 64 << 10
    """The msgpack header of a frame message (its arrays travel out of band; a real one is
    ~300 bytes). See :func:`frame_header_limits`."""
    max_str_bytes: int = 0
    """Bytes of one msgpack string in the header; 0 = up to the header size."""
    max_bin_bytes: int = -1
    """Bytes of one msgpack binary in the header; -1 = up to the header size, 0 = none."""
    max_containers: int = 1 << 20
    """Maps and lists in the whole header (each costs a step of the array-reference walk)."""


def frame_header_limits(lim: "WireLimits") -> "WireLimits":
    """The tight header profile of the frame schema, derived from ``lim``: header at most
    ``max_frame_header_bytes``, containers at most ``max(2·max_meta_items, 16)`` entries,
    strings at most 4·``max_string_len`` bytes (UTF-8), no binary, nesting at most 8, at
    most 256 maps/lists in all (a real frame header has about 12)."""
    return replace(lim, max_header_bytes=min(lim.max_header_bytes, lim.max_frame_header_bytes),
                   max_container_len=min(lim.max_container_len, max(2 * lim.max_meta_items, 16)),
                   max_str_bytes=4 * lim.max_string_len, max_bin_bytes=0, max_nesting=min(lim.max_nesting, 8),
                   max_containers=min(lim.max_containers, 256))


DEFAULT_LIMITS = WireLimits()

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

    __slots__ = ("mv", "base", "region", "lim", "end", "budget")

    def __init__(self, mv: memoryview, base: int, lim: WireLimits) -> None:
        self.mv = mv
        self.base = base
        self.region = max(0, len(mv) - base)
        self.lim = lim
        self.end = -1   # end of the furthest buffer (relative to base); -1 = no array seen
        self.budget = lim.max_containers

    def array(self, ref: dict, path: str) -> np.ndarray:
        where = path or "array"
        if len(ref) != 1:
            raise WireError(f"{where}: an array reference must have only the key {_ND!r}, got {sorted(map(str, ref))}")
        r = ref[_ND]
        if type(r) is not list or len(r) != 4:
            raise WireError(f"{where}: array reference must be [dtype, shape, offset, nbytes], got {_short(r)}")
        ds, shape, off, nbytes = r
        dt = _DTYPES.get(ds) if type(ds) is str else None
        if dt is None:
            raise WireError(f"{where}: dtype {ds!r:.50} not allowed (allowed: {', '.join(sorted(_DTYPES))})")
        lim = self.lim
        if type(shape) is not list or len(shape) > lim.max_ndim:
            raise WireError(f"{where}: shape must be a list of at most {lim.max_ndim} ints, got {_short(shape)}")
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
        self.end = max(self.end, off + nbytes)
        return a

    def walk(self, obj: Any, path: str, depth: int) -> Any:
        if depth > self.lim.max_nesting:
            raise WireError(f"header: {path}: nesting deeper than the limit {self.lim.max_nesting}")
        self.budget -= 1
        if self.budget < 0:
            raise WireError(f"header: more than {self.lim.max_containers} maps/lists")
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


def _short(x: Any) -> str:
    """A bounded repr (never builds the repr of a huge container)."""
    if type(x) in (list, dict) and len(x) > 16:
        return f"a {_tname(x)} of {len(x)} entries"
    return f"{x!r:.200}" if type(x) not in (list, dict) else repr(x)[:200]


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


class _TooMany(Exception):
    pass


def _counting_hooks(limit: int) -> dict:
    """msgpack hooks that abort the unpack at the ``limit+1``-th map/list it completes, so a
    header made of many tiny containers costs ``limit`` steps, not one per container."""
    left = [limit]

    def hook(obj):
        left[0] -= 1
        if left[0] < 0:
            raise _TooMany
        return obj

    return {"object_hook": hook, "list_hook": hook}


def _unpack_header(raw: memoryview, lim: WireLimits) -> Any:
    n = len(raw)
    hooks = _counting_hooks(lim.max_containers) if lim.max_containers <= 4096 else {}
    try:
        return msgpack.unpackb(
            raw,
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_str_len=min(n, lim.max_str_bytes) if lim.max_str_bytes > 0 else n,
            max_bin_len=min(n, lim.max_bin_bytes) if lim.max_bin_bytes >= 0 else n,
            max_array_len=min(n, lim.max_container_len),
            max_map_len=min(n, lim.max_container_len),
            max_ext_len=0,
            **hooks,
        )
    except _TooMany:
        raise WireError(f"header: more than {lim.max_containers} maps/lists") from None
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
        dec = _Decoder(mv, _align(4 + hl), lim)
        body = dec.walk(header, "", 0)
        end = 4 + hl if dec.end < 0 else dec.base + dec.end
        if n != end:
            raise WireError(f"message: {n - end} bytes after the end of the message's data "
                            f"({end} bytes: header{' and buffers' if dec.end >= 0 else ''})")
        return sch, ver, body
    except WireError:
        raise
    except Exception as e:  # safety net: nothing but WireError leaves a decoder
        raise WireError(f"message: malformed ({type(e).__name__}: {e})") from e
