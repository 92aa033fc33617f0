"""Image codecs of the frame message: depth (16-bit PNG mm, zlib f32, f16), RGB (JPEG, raw),
and the 16-/8-bit greyscale PNGs of labels and confidence (``common.wire`` package).

Decoders check what they can before handing bytes to OpenCV: the PNG chunk walk
(:func:`_png_check`: sizes, CRCs) and the JPEG SOF parse (:func:`_jpeg_size`) reject corrupt
or oversized images cheaply. OpenCV is imported on first use, so code that only uses the
envelope or the control messages (a query client) never loads it.
"""
from __future__ import annotations

import struct
import zlib
from typing import Any

import numpy as np

from common.wire.envelope import WireLimits
from common.wire.fields import _as_array, _bytes_array, _enc_err, _err, _image_spec, _nd, _shape

DEPTH_CODECS = ("auto", "png16mm", "f32", "f16")
RGB_CODECS = ("jpeg", "raw")
PNG16MM_MAX_DEPTH = 65.534
"""Largest depth (m) the ``png16mm`` codec stores without clipping."""

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_SEQUENTIAL = frozenset({0xC0, 0xC1})  # baseline / extended Huffman: what encoders send
_F16_TINY = np.float16(np.finfo(np.float16).tiny)
_cv = None


def _cv2():
    """OpenCV, imported on first use (see the module docstring)."""
    global _cv
    if _cv is None:
        import cv2

        _cv = cv2
    return _cv


def _imencode(ext: str, img: np.ndarray, params: list[int], field: str) -> np.ndarray:
    cv2 = _cv2()
    try:
        ok, buf = cv2.imencode(ext, img, params)
    except cv2.error as e:
        raise _enc_err(field, f"OpenCV could not encode {ext}: {e}") from e
    if not ok:
        raise _enc_err(field, f"OpenCV could not encode {ext}")
    return buf.reshape(-1)



def _png_encode(img: np.ndarray, field: str) -> np.ndarray:
    """Greyscale PNG at compression level 1 (fast; the images are small)."""
    cv2 = _cv2()
    return _imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1], field)


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
        data = _png_encode(mm.astype(np.uint16), "depth")
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
        cv2 = _cv2()
        bgr = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2BGR)
        data = _imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality], "rgb")
    elif codec == "raw":
        data = np.ascontiguousarray(a)
    else:
        raise _enc_err("rgb", f"unknown rgb codec {codec!r} (known: {', '.join(RGB_CODECS)})")
    return {"codec": codec, "shape": list(a.shape), "data": data}



def _png_check(buf: np.ndarray, field: str, hw: tuple[int, int], bit_depth: int) -> None:
    """Walk the PNG's chunks before handing it to OpenCV: signature, IHDR first (size, bit
    depth, greyscale), every chunk inside the buffer with a correct CRC, IEND last.

    OpenCV trusts chunk lengths: one flipped bit in a length costs it a second of CPU."""
    mv = buf.data  # memoryview(buf); numpy's stubs give ndarray no __buffer__ before Python 3.12
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
    cv2 = _cv2()
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
    b = buf.data  # memoryview(buf), as in _png_check
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
            raw = z.decompress(buf.data, want)  # the array's buffer (see _png_check)
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
    cv2 = _cv2()
    try:
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error as e:
        raise _err("rgb.data", f"JPEG decode failed ({e})") from e
    if bgr is None or bgr.shape != (hw[0], hw[1], 3) or bgr.dtype != np.uint8:
        raise _err("rgb.data", "JPEG decode failed")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

