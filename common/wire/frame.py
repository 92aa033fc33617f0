"""The frame message ``rayfronts.frame`` v2 (docs/messages.md#frame): :func:`encode_frame` / :func:`decode_frame`.

Versions: v2 (written now) differs from v1 only in ``features``, which may also be a
compressed map ``{"codec": "q16z" | "q8z", "shape": [C, h, w], "scale": <f4 (C,), "data": <u1 (n,)}``:
the float16 feature map quantised per channel to int16 (``q16z``, T = 32767) or int8
(``q8z``, T = 127), ``q = round(f / scale_c)`` clipped to [-T, T] with
``scale_c = max|f_c| / T`` (any positive scale decodes), C-order little-endian integers
deflated with zlib; decoded as float16 ``q · scale_c`` (error ≤ scale_c / 2). The decoder
inflates at most C·h·w·itemsize bytes (a hostile stream cannot make it allocate more).
``f16`` (the v1 array) stays available (``feature_codec="f16"``). v1 messages (old
recordings) decode as before.

Why: a 640×480 frame with PCA-100 features at the patch grid (40×30) is 240 KB of float16.
Measured on the synthetic world with the label encoder (piecewise-constant maps): ``q16z``
~8 KB per frame with per-cell cosine changes ~2e-5 and the same top-1 class everywhere;
``q8z`` ~3-4 KB with changes up to ~0.006 and a few top-1 flips where two classes nearly
tie (``rayfronts bench e2e`` reports bytes and score changes).

Part of the ``common.wire`` package (module map in ``common/wire/__init__.py``). Built on the
generic envelope (:mod:`common.wire.envelope`); image payloads go through
:mod:`common.wire.images`. A new frame field goes in :func:`encode_frame` (header list in its
docstring, encode), :func:`_decode_frame_body` (validate) and :class:`common.frame.Frame`.
"""
from __future__ import annotations

import math
import re
import zlib
from typing import Any

import numpy as np

from common.conventions import is_rigid
from common.frame import Frame
from common.wire.envelope import (
    DEFAULT_LIMITS,
    WireError,
    WireLimits,
    _tname,
    decode_message,
    encode_message,
    frame_header_limits,
)
from common.wire.fields import _as_array, _bytes_array, _enc_err, _err, _image_spec, _nd, _req, _shape
from common.wire.images import (
    _decode_depth,
    _decode_rgb,
    _encode_depth,
    _encode_rgb,
    _jpeg_size,
    _png_check,
    _png_decode,
    _png_encode,
)

FRAME_SCHEMA = "rayfronts.frame"
FRAME_VERSION = 2
#: versions :func:`decode_frame` accepts (v1: old recordings; features only as a float16 array)
FRAME_VERSIONS = (1, 2)
#: feature encodings :func:`encode_frame` writes (module docstring)
FEATURE_CODECS = ("f16", "q16z", "q8z")
#: quantised feature codecs: integer dtype and largest level
_QCODECS = {"q8z": ("|i1", 127), "q16z": ("<i2", 32767)}

_ROBOT_RE = re.compile(r"[A-Za-z0-9_-]+")


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
    feature_codec: str = "f16",
) -> bytes:
    """Encode a :class:`~common.frame.Frame` as a ``rayfronts.frame`` v2 message.

    Header fields (arrays out of band):

    ``robot`` str · ``seq`` int ≥ 0 · ``stamp`` float s · ``pose`` <f8 (4,4) · ``intrinsics``
    <f8 (3,3) · ``feature_space`` str · ``meta`` map str → None/bool/int/float/str ·
    ``features`` <f2 (C,h,w), a ``q8z`` map (``feature_codec="q8z"``, module docstring) or nil ·
    ``global_feature`` <f2 (C,) or nil · ``depth`` {codec, shape [H,W], data} · ``rgb`` {codec, shape [H',W',3], data} ·
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
    if feature_codec not in FEATURE_CODECS:
        raise _enc_err("features", f"unknown feature codec {feature_codec!r}; choose one of {FEATURE_CODECS}")
    seq, stamp = _encode_id_fields(frame)
    pose, K = _encode_geometry(frame)

    depth = _encode_depth(frame.depth, depth_codec)
    h, w = depth["shape"]
    rgb = _encode_rgb(frame.rgb, rgb_codec, jpeg_quality)
    features, global_feature = _encode_features(frame, h, w)
    labels = _encode_labels(frame.labels, h, w)
    confidence = _encode_confidence(frame.confidence, h, w)

    fs = frame.feature_space if frame.feature_space is not None else ""
    if type(fs) is not str:
        raise _enc_err("feature_space", f"expected str, got {_tname(fs)}")

    # Refuse what a decoder with the default limits would reject, rather than send it.
    lim = DEFAULT_LIMITS
    meta = _encode_meta(frame.meta)
    _check_encode_limits(lim, (h, w), rgb, features, global_feature, fs, meta)

    body = {
        "robot": frame.robot,
        "seq": seq,
        "stamp": stamp,
        "pose": pose,
        "intrinsics": K,
        "depth": depth,
        "rgb": rgb,
        "features": _encode_q(features, feature_codec) if features is not None and feature_codec != "f16" else features,
        "feature_space": fs,
        "labels": labels,
        "confidence": confidence,
        "global_feature": global_feature,
        "meta": meta,
    }
    out = encode_message(FRAME_SCHEMA, FRAME_VERSION, body)
    hl = int.from_bytes(out[:4], "little")
    if hl > lim.max_frame_header_bytes:
        raise _enc_err("meta", f"the frame header is {hl} bytes, over the wire limit {lim.max_frame_header_bytes} "
                               "(meta too large)")
    return out


def _encode_id_fields(frame: Frame) -> tuple[int, float]:
    """Validate the robot id; ``(seq, stamp)`` as a plain int and a finite float (seconds)."""
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
    return seq, stamp


def _encode_geometry(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """``(pose, K)`` as little-endian float64: a rigid (4, 4) camera-to-world pose, (3, 3) intrinsics."""
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
    return pose, K


def _encode_features(frame: Frame, h: int, w: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(features, global_feature)`` as float16 (or None), checked against the depth size ``h`` × ``w``."""
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
    return features, global_feature


def _encode_labels(labels: Any, h: int, w: int) -> dict | None:
    """The ``labels`` map (16-bit PNG) or None."""
    if labels is None:
        return None
    lab = _as_array(labels, "labels")
    if lab.shape != (h, w) or lab.dtype.kind not in "biu":
        raise _enc_err("labels", f"expected an ({h}, {w}) int array, got shape {lab.shape} dtype {lab.dtype}")
    if lab.size and (int(lab.min()) < 0 or int(lab.max()) > 65535):
        raise _enc_err("labels", f"values must be in [0, 65535], got [{lab.min()}, {lab.max()}]")
    return {
        "codec": "png16",
        "data": _png_encode(lab.astype(np.uint16), "labels"),
    }


def _encode_confidence(confidence: Any, h: int, w: int) -> dict | None:
    """The ``confidence`` map (8-bit PNG of ``round(c·255)``, c clipped to [0, 1]) or None."""
    if confidence is None:
        return None
    conf = _as_array(confidence, "confidence")
    if conf.shape != (h, w) or conf.dtype.kind not in "fiub":
        raise _enc_err(
            "confidence", f"expected an ({h}, {w}) float array, got shape {conf.shape} dtype {conf.dtype}"
        )
    q = np.nan_to_num(conf.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    q = np.rint(np.clip(q, 0.0, 1.0) * 255.0).astype(np.uint8)
    return {
        "codec": "png8",
        "data": _png_encode(q, "confidence"),
    }


def _check_encode_limits(
    lim: WireLimits,
    hw: tuple[int, int],
    rgb: dict,
    features: np.ndarray | None,
    global_feature: np.ndarray | None,
    fs: str,
    meta: dict,
) -> None:
    """Raise what a decoder with the limits ``lim`` would reject."""
    h, w = hw
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


def _encode_q(f16: np.ndarray, codec: str) -> dict:
    """float16 ``(C, h, w)`` → the ``q8z`` / ``q16z`` map (per-channel integers + zlib; module docstring)."""
    dt, top = _QCODECS[codec]
    c, h, w = f16.shape
    y = f16.astype(np.float32)
    s = np.abs(y).reshape(c, -1).max(1) / top
    s = np.where(s > 0, s, 1.0).astype("<f4")
    q = np.clip(np.rint(y / s[:, None, None]), -top, top).astype(dt)
    data = zlib.compress(np.ascontiguousarray(q).tobytes(), 6)
    return {"codec": codec, "shape": [int(c), int(h), int(w)], "scale": s, "data": np.frombuffer(data, np.uint8)}


def _decode_q(x: Any, lim: WireLimits) -> np.ndarray:
    """A ``q8z`` / ``q16z`` map → float16 ``(C, h, w)`` (validated, bounded inflate)."""
    if type(x) is not dict or set(x) != {"codec", "shape", "scale", "data"}:
        raise _err("features", "expected a float16 array or a map with codec, shape, scale, data")
    if x["codec"] not in _QCODECS:
        raise _err("features", f"unknown codec {x['codec']!r:.40} (known: {', '.join(_QCODECS)})")
    dt, top = _QCODECS[x["codec"]]
    shp = x["shape"]
    if type(shp) is not list or len(shp) != 3 or any(type(v) is not int or v < 1 for v in shp):
        raise _err("features", f"shape: expected 3 ints >= 1, got {shp!r:.100}")
    c, h, w = shp
    if c > lim.max_channels or h * w > lim.max_pixels or c * h * w > lim.max_array_elems:
        raise _err("features", f"shape {c}x{h}x{w} is over the limits")
    scale = _nd(x["scale"], "features.scale", "<f4", 1)
    if scale.shape != (c,) or not (np.isfinite(scale).all() and (scale > 0).all() and (scale <= 65504 / top).all()):
        raise _err("features", f"scale: expected ({c},) finite values in (0, {65504 / top:.3g}]")
    data = _bytes_array(x["data"], "features.data")
    n = c * h * w * np.dtype(dt).itemsize
    z = zlib.decompressobj()
    try:
        raw = z.decompress(data.tobytes(), n + 1)
    except zlib.error as e:
        raise _err("features", f"data: not a zlib stream ({e})") from None
    if len(raw) != n or not z.eof or z.unused_data:
        raise _err("features", f"data: inflates to {len(raw)}{'+' if len(raw) > n else ''} bytes, expected {n} "
                               "(one complete zlib stream)")
    q = np.frombuffer(raw, dt).reshape(c, h, w)
    return (q.astype(np.float32) * scale[:, None, None]).astype(np.float16)


# ---- frame decoding -------------------------------------------------------------------

def _check_intrinsics(K: np.ndarray, err) -> None:
    if not np.isfinite(K).all():
        raise err("intrinsics", "not finite")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise err("intrinsics", f"fx and fy must be > 0, got fx={K[0, 0]} fy={K[1, 1]}")
    if abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9 or abs(K[2, 2] - 1.0) > 1e-9 or abs(K[1, 0]) > 1e-9:
        raise err("intrinsics", f"expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")



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
    """Decode and validate a ``rayfronts.frame`` v2 or v1 message (see :func:`encode_frame`).

    Returns a :class:`Frame` whose fields satisfy the frame contract: depth float32 (H, W)
    with NaN / +inf / positive values, rgb (H', W', 3) uint8 RGB, features (C, h, w) float16
    finite with h ≤ H and w ≤ W, labels int32 (H, W), confidence float32 (H, W) in [0, 1],
    global_feature float16 (C,), pose float64 rigid, intrinsics float64.
    ``features`` (float16 codec), ``global_feature`` and raw RGB are zero-copy read-only views of ``data``;
    the other arrays are fresh. Raises :class:`WireError` for anything malformed.
    """
    lim = limits or DEFAULT_LIMITS
    # the header under the tight frame profile: its decode cost is bounded by 64 KiB of msgpack
    _, ver, b = decode_message(data, schema=FRAME_SCHEMA, v=FRAME_VERSIONS, limits=frame_header_limits(lim))
    try:
        return _decode_frame_body(b, lim, ver)
    except WireError:
        raise
    except Exception as e:  # safety net: nothing but WireError leaves a decoder
        raise WireError(f"frame: malformed ({type(e).__name__}: {e})") from e


def _decode_frame_body(b: dict, lim: WireLimits, version: int = FRAME_VERSION) -> Frame:
    robot, seq, stamp = _decode_id_fields(b, lim)
    pose, K = _decode_geometry(b)
    fs = b.get("feature_space", "")
    if fs is None:
        fs = ""
    if type(fs) is not str or len(fs) > lim.max_string_len:
        raise _err("feature_space", f"expected a str of at most {lim.max_string_len} chars, got {_tname(fs)}")
    meta = _decode_meta(b.get("meta"), lim)
    features, gf = _decode_features(b, lim, version)
    _precheck_images(b, lim, features)

    depth = _decode_depth(b, lim)
    hw = (depth.shape[0], depth.shape[1])
    rgb = _decode_rgb(b, lim)
    labels = _decode_labels(b, hw)
    conf = _decode_confidence(b, hw)

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


def _decode_id_fields(b: dict, lim: WireLimits) -> tuple[str, int, float | int]:
    """``(robot, seq, stamp)`` of a frame header, validated (stamp in seconds, as sent)."""
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
    return robot, seq, stamp


def _decode_geometry(b: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(pose, K)`` of a frame header: a rigid (4, 4) camera-to-world pose and (3, 3) intrinsics."""
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
    return pose, K


def _decode_features(b: dict, lim: WireLimits, version: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(features, global_feature)`` as float16 (or None); the feature map's finiteness is
    checked later (:func:`_precheck_images`), after its size."""
    features = b.get("features")
    if features is not None:
        if version >= 2 and type(features) is dict:
            features = _decode_q(features, lim)
        else:
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
    return features, gf


def _precheck_images(b: dict, lim: WireLimits, features: np.ndarray | None) -> None:
    """Cheap checks before any image decoding: the declared sizes, the feature map's values,
    then the structure of every compressed image."""
    dspec = b.get("depth")
    declared = dspec if type(dspec) is dict and "shape" in dspec else None
    if declared is not None:
        h, w = _shape(declared["shape"], "depth.shape", 2, lim)
        if features is not None:
            _, fh, fw = features.shape
            if not (1 <= fh <= h and 1 <= fw <= w):
                raise _err("features", f"feature map {fh}x{fw} must be non-empty and at most the depth size {h}x{w}")
    if features is not None and not _f16_finite(features):
        raise _err("features", "holds NaN or inf")
    if declared is not None:
        _check_image_structure(b, declared, (h, w))


def _check_image_structure(b: dict, dspec: dict, hw: tuple[int, int]) -> None:
    """The structure of every compressed image (PNG chunk walk with CRCs, JPEG frame header)
    is checked before any of them is decoded, so a broken one costs no image decode."""
    if dspec.get("codec") == "png16mm" and "data" in dspec:
        _png_check(_bytes_array(dspec["data"], "depth.data"), "depth.data", hw, 16)
    rspec = b.get("rgb")
    if type(rspec) is dict and rspec.get("codec") == "jpeg" and "data" in rspec:
        _jpeg_size(_bytes_array(rspec["data"], "rgb.data"), "rgb.data")
    for field, codec, bits in (("labels", "png16", 16), ("confidence", "png8", 8)):
        if b.get(field) is not None:
            spec = _image_spec(b, field, ("codec", "data"))
            if spec["codec"] == codec:
                _png_check(_bytes_array(spec["data"], f"{field}.data"), f"{field}.data", hw, bits)


def _decode_png_field(b: dict, field: str, codec: str, hw: tuple[int, int], dtype: type) -> np.ndarray | None:
    """The PNG image of ``field`` (codec ``codec``, shape ``hw``, ``dtype``) or None if absent."""
    if b.get(field) is None:
        return None
    spec = _image_spec(b, field, ("codec", "data"))
    if spec["codec"] != codec:
        raise _err(f"{field}.codec", f"unknown codec {spec['codec']!r:.50} (known: {codec})")
    return _png_decode(_bytes_array(spec["data"], f"{field}.data"), f"{field}.data", hw, dtype)


def _decode_labels(b: dict, hw: tuple[int, int]) -> np.ndarray | None:
    """The labels as int32 ``hw`` (16-bit PNG) or None."""
    labels = _decode_png_field(b, "labels", "png16", hw, np.uint16)
    return None if labels is None else labels.astype(np.int32)


def _decode_confidence(b: dict, hw: tuple[int, int]) -> np.ndarray | None:
    """The confidence as float32 ``hw`` in [0, 1] (8-bit PNG, ``q / 255``) or None."""
    q = _decode_png_field(b, "confidence", "png8", hw, np.uint8)
    if q is None:
        return None
    conf = q.astype(np.float32)
    conf /= np.float32(255.0)
    return conf
