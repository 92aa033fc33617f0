"""Wire codec: generic messages, frame round trips, zero copy, depth accuracy, error messages."""
from __future__ import annotations

import struct

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.frame import Frame
from common.wire import (
    ALLOWED_DTYPES,
    FRAME_SCHEMA,
    WireError,
    WireLimits,
    decode_frame,
    decode_message,
    encode_frame,
    encode_message,
)

# ---------------------------------------------------------------- helpers


def smooth_rgb(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth colour image (JPEG reproduces it to a few grey levels)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ph = np.random.default_rng(seed).uniform(0, 6, 3)
    img = np.stack([127 + 100 * np.sin(x / 17 + ph[0]), 127 + 100 * np.cos(y / 13 + ph[1]),
                    127 + 100 * np.sin((x + y) / 23 + ph[2])], axis=-1)
    return np.clip(img, 0, 255).astype(np.uint8)


def rot(axis: np.ndarray, ang: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64) * ang)[0]


def make_frame(
    h: int = 48, w: int = 64, *, c: int = 8, fh: int = 6, fw: int = 8, seed: int = 0,
    features: bool = True, labels: bool = True, confidence: bool = True,
    global_feature: bool = True, meta: bool = True, rgb_hw: tuple[int, int] | None = None,
) -> Frame:
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = rot(rng.standard_normal(3), rng.uniform(0, 3))
    pose[:3, 3] = rng.uniform(-50, 50, 3)
    K = np.array([[50.0, 0, w / 2], [0, 52.0, h / 2], [0, 0, 1]])
    depth = rng.uniform(0.2, 30.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.05] = np.nan
    depth[rng.random((h, w)) < 0.05] = np.inf
    rh, rw = rgb_hw or (h, w)
    return Frame(
        robot="robot_1-a", seq=int(rng.integers(0, 1000)), stamp=float(rng.uniform(0, 1e9)),
        pose=pose, intrinsics=K, depth=depth, rgb=smooth_rgb(rh, rw, seed),
        features=rng.standard_normal((c, fh, fw)).astype(np.float16) if features else None,
        feature_space="radio-v2.5-b/pca8/abc123" if features else "",
        labels=rng.integers(0, 65536, (h, w)).astype(np.int32) if labels else None,
        confidence=rng.uniform(0, 1, (h, w)).astype(np.float32) if confidence else None,
        global_feature=rng.standard_normal(c).astype(np.float16) if global_feature else None,
        meta={"source": "test", "index": 7, "ok": True, "x": 1.5, "none": None} if meta else {},
    )


def raw_header(data: bytes) -> tuple[dict, bytes]:
    """The msgpack header (array references left as dicts) and the buffer region."""
    (hl,) = struct.unpack_from("<I", data)
    base = (4 + hl + 7) & ~7
    return msgpack.unpackb(data[4:4 + hl], raw=False), data[base:]


def repack(header: dict, region: bytes) -> bytes:
    """Inverse of raw_header: same buffer region, new header."""
    hdr = msgpack.packb(header, use_bin_type=True)
    pad = ((4 + len(hdr) + 7) & ~7) - 4 - len(hdr)
    return struct.pack("<I", len(hdr)) + hdr + b"\0" * pad + region


def mutate_raw(data: bytes, fn) -> bytes:
    h, region = raw_header(data)
    fn(h)
    return repack(h, region)


def mutate_body(data: bytes, fn) -> bytes:
    """Decode to the body (arrays resolved), let fn change it, re-encode with encode_message."""
    schema, v, body = decode_message(data)
    body = {k: (dict(x) if isinstance(x, dict) else x) for k, x in body.items()}
    fn(body)
    return encode_message(schema, v, body)


def assert_rejected(data: bytes, *words: str, limits: WireLimits | None = None) -> str:
    with pytest.raises(WireError) as ei:
        decode_frame(data, limits)
    msg = str(ei.value)
    for word in words:
        assert word in msg, f"{word!r} not in {msg!r}"
    return msg


# ---------------------------------------------------------------- generic codec


def test_message_round_trip_nested_arrays_all_dtypes():
    rng = np.random.default_rng(1)
    arrays = {s: (rng.integers(0, 2, (3, 5)).astype(np.dtype(s)) if s != "|b1"
                  else rng.integers(0, 2, (3, 5)).astype(bool)) for s in sorted(ALLOWED_DTYPES)}
    body = {
        "a": arrays,
        "list": [np.arange(7, dtype=np.int16), {"deep": [np.ones((2, 0, 3), np.float32)]}],
        "scalar0d": np.array(3.5),
        "f_order": np.asfortranarray(rng.standard_normal((4, 6))),
        "strided": np.arange(20, dtype=np.int64)[::3],
        "big_endian": np.arange(5, dtype=">i4"),
        "np_scalars": [np.float32(1.5), np.int64(-3), np.bool_(True), np.uint8(7)],
        "tuple": (1, "x", None, 2.5, b"\x00\x01"),
    }
    data = encode_message("test.nested", 3, body)
    schema, v, out = decode_message(data, schema="test.nested", v=3)
    assert (schema, v) == ("test.nested", 3)
    for s, a in arrays.items():
        got = out["a"][s]
        assert got.dtype.str == s and got.shape == a.shape and np.array_equal(got, a)
    np.testing.assert_array_equal(out["list"][0], np.arange(7, dtype=np.int16))
    assert out["list"][1]["deep"][0].shape == (2, 0, 3)
    assert out["scalar0d"].shape == () and out["scalar0d"] == 3.5
    np.testing.assert_array_equal(out["f_order"], body["f_order"])
    np.testing.assert_array_equal(out["strided"], body["strided"])
    assert out["big_endian"].dtype.str == "<i4" and out["big_endian"].tolist() == [0, 1, 2, 3, 4]
    assert out["np_scalars"] == [1.5, -3, True, 7]
    assert [type(x) for x in out["np_scalars"]] == [float, int, bool, int]
    assert out["tuple"] == [1, "x", None, 2.5, b"\x00\x01"]


def test_message_arrays_are_zero_copy_read_only_and_aligned():
    body = {"x": np.arange(1000, dtype=np.float32), "y": [np.arange(3, dtype=np.uint8), np.ones(5)]}
    data = encode_message("t", 1, body)
    for buf in (data, bytearray(data), memoryview(data)):
        _, _, out = decode_message(buf)
        whole = np.frombuffer(buf, np.uint8)
        start = whole.__array_interface__["data"][0]
        for a in (out["x"], out["y"][0], out["y"][1]):
            assert np.shares_memory(a, whole)
            assert not a.flags.writeable
            # 8-byte aligned relative to the start of the message
            assert (a.__array_interface__["data"][0] - start) % 8 == 0
        with pytest.raises(ValueError):
            out["x"][0] = 1.0


def test_message_version_collection_and_mismatch():
    data = encode_message("a.b", 2, {"k": 1})
    assert decode_message(data, v=(1, 2))[2] == {"k": 1}
    with pytest.raises(WireError, match="schema"):
        decode_message(data, schema="other")
    with pytest.raises(WireError, match="expected 1"):
        decode_message(data, schema="a.b", v=1)
    with pytest.raises(WireError, match="one of"):
        decode_message(data, v={3, 4})


@pytest.mark.parametrize(
    "body, word",
    [
        ({"o": np.array([object()], dtype=object)}, "o"),
        ({"c": np.zeros(3, np.complex64)}, "c"),
        ({"s": {1, 2}}, "set"),
        ({1: 2}, "not a str"),
        ({"__nd__": 1}, "reserved"),
        ({"schema": "x"}, "reserved"),
        ({"n": {"deep": [object()]}}, "n.deep[0]"),
        ({"big": 2**70}, "msgpack"),
    ],
)
def test_encode_message_refuses(body, word):
    with pytest.raises(WireError) as ei:
        encode_message("t", 1, body)
    assert word in str(ei.value)


def test_encode_message_refuses_bad_schema_and_version():
    with pytest.raises(WireError, match="schema"):
        encode_message("", 1, {})
    with pytest.raises(WireError, match="v"):
        encode_message("t", -1, {})


def _generic(hdr: dict, region: bytes = b"") -> bytes:
    return repack(hdr, region)


@pytest.mark.parametrize(
    "data, word",
    [
        (b"", "too short"),
        (b"\x01\x00", "too short"),
        (struct.pack("<I", 0), "length is 0"),
        (struct.pack("<I", 100) + b"\x80", "runs past the end"),
        (struct.pack("<I", 1) + b"\xc1", "invalid msgpack"),
        (struct.pack("<I", 2) + b"\x80\x80", "trailing data"),
        (_generic([1, 2]), "expected a msgpack map"),
        (_generic({"v": 1}), "schema: required"),
        (_generic({"schema": "t"}), "v: required"),
        (_generic({"schema": 3, "v": 1}), "schema: expected str"),
        (_generic({"schema": "t", "v": "1"}), "v: expected int"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<c8", [1], 0, 8]}}, b"\0" * 8), "x: dtype"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [3], 0, 12]}}, b"\0" * 8), "out of bounds"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [3], -8, 12]}}, b"\0" * 16), "offset"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [3], 0, 8]}}, b"\0" * 16), "nbytes"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [-1], 0, 0]}}), "invalid dimension"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [1 << 40], 0, 4 << 40]}}), "invalid dimension"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [1 << 20, 1 << 20], 0, 4 << 40]}}), "elements"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [1.0], 0, 4]}}, b"\0" * 8), "invalid dimension"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [1], 0, 4], "y": 1}}, b"\0" * 8), "only the key"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["<f4", [1], 0]}}, b"\0" * 8), "[dtype, shape"),
        (_generic({"schema": "t", "v": 1, "x": {"__nd__": ["|b1", [2], 0, 2]}}, b"\x01\x07" + b"\0" * 6), "bool"),
        (_generic({"schema": "t", "v": 1, b"a": 1}), "not a str"),
        (struct.pack("<I", 4) + b"\x81\xa1\xff\x01", "UTF-8"),
        (struct.pack("<I", 4) + b"\xd6\xff\x00\x00", "invalid msgpack"),  # ext type
    ],
)
def test_decode_message_rejects(data, word):
    with pytest.raises(WireError) as ei:
        decode_message(data)
    assert word in str(ei.value), str(ei.value)


def test_decode_message_limits_and_types():
    data = encode_message("t", 1, {"x": np.zeros((10, 100))})
    with pytest.raises(WireError, match="over the limit"):
        decode_message(data, limits=WireLimits(max_message_bytes=1000))
    with pytest.raises(WireError, match="elements"):
        decode_message(data, limits=WireLimits(max_array_elems=999))
    with pytest.raises(WireError, match="invalid dimension"):
        decode_message(data, limits=WireLimits(max_array_elems=99))
    with pytest.raises(WireError, match="at most 1"):
        decode_message(data, limits=WireLimits(max_ndim=1))
    with pytest.raises(WireError, match="nesting"):
        decode_message(encode_message("t", 1, {"a": [[[[[1]]]]]}), limits=WireLimits(max_nesting=3))
    with pytest.raises(WireError, match="invalid msgpack"):  # msgpack's own container limit
        decode_message(encode_message("t", 1, {"a": list(range(100))}), limits=WireLimits(max_container_len=50))
    with pytest.raises(WireError, match="expected bytes"):
        decode_message(12345)  # type: ignore[arg-type]
    with pytest.raises(WireError):
        decode_message(struct.pack("<I", 5000) + b"\x80" * 5000)  # deeply nested / garbage


# ---------------------------------------------------------------- frame round trips


def assert_frames_close(a: Frame, b: Frame, *, rgb_exact: bool) -> None:
    assert (b.robot, b.seq, b.stamp, b.feature_space, b.meta) == (a.robot, a.seq, a.stamp, a.feature_space, a.meta)
    np.testing.assert_array_equal(b.pose, a.pose)
    np.testing.assert_array_equal(b.intrinsics, a.intrinsics)
    assert b.pose.dtype == np.float64 and b.intrinsics.dtype == np.float64
    assert b.depth.dtype == np.float32 and b.depth.shape == a.depth.shape
    assert np.array_equal(np.isnan(b.depth), np.isnan(a.depth))
    assert np.array_equal(np.isposinf(b.depth), np.isposinf(a.depth))
    fin = np.isfinite(a.depth)
    assert np.abs(b.depth[fin] - a.depth[fin]).max() <= 0.0005 + 1e-6
    assert b.rgb.dtype == np.uint8 and b.rgb.shape == a.rgb.shape
    err = np.abs(b.rgb.astype(int) - a.rgb.astype(int))
    if rgb_exact:
        assert err.max() == 0
    else:
        assert err.mean() < 3.0  # JPEG q90 on a smooth image; BGR/RGB mix-ups give ~100
    for name in ("features", "global_feature"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None)
        if x is not None:
            assert y.dtype == np.float16 and np.array_equal(x, y)
    assert (a.labels is None) == (b.labels is None)
    if a.labels is not None:
        assert b.labels.dtype == np.int32 and np.array_equal(a.labels, b.labels)
    assert (a.confidence is None) == (b.confidence is None)
    if a.confidence is not None:
        assert b.confidence.dtype == np.float32 and b.confidence.shape == a.confidence.shape
        assert np.abs(b.confidence - a.confidence).max() <= 1 / 510 + 1e-6


@pytest.mark.parametrize("optional", [True, False])
@pytest.mark.parametrize("rgb_codec", ["jpeg", "raw"])
def test_frame_round_trip(optional, rgb_codec):
    f = make_frame(features=optional, labels=optional, confidence=optional,
                   global_feature=optional, meta=optional, seed=3)
    data = encode_frame(f, rgb_codec=rgb_codec)
    g = decode_frame(data)
    assert_frames_close(f, g, rgb_exact=rgb_codec == "raw")


def test_frame_round_trip_each_optional_field_alone():
    names = ("features", "labels", "confidence", "global_feature", "meta")
    for name in names:
        kw = {n: n == name for n in names}
        f = make_frame(seed=11, **kw)
        assert_frames_close(f, decode_frame(encode_frame(f, rgb_codec="raw")), rgb_exact=True)


def test_frame_rgb_resolution_differs_and_rgb_order():
    f = make_frame(32, 40, rgb_hw=(96, 120), fh=4, fw=5)
    f.rgb = np.zeros((96, 120, 3), np.uint8)
    f.rgb[..., 0] = 250  # pure red: a BGR mix-up would give blue
    g = decode_frame(encode_frame(f, jpeg_quality=95))
    assert g.rgb.shape == (96, 120, 3)
    assert g.rgb[..., 0].min() > 240 and g.rgb[..., 2].max() < 10


def test_frame_features_zero_copy_and_float32_cast():
    f = make_frame(seed=4)
    f.features = f.features.astype(np.float32) * 3
    data = encode_frame(f, rgb_codec="raw")
    g = decode_frame(data)
    whole = np.frombuffer(data, np.uint8)
    assert g.features.dtype == np.float16
    assert np.array_equal(g.features, f.features.astype(np.float16))
    for a in (g.features, g.global_feature, g.rgb):
        assert np.shares_memory(a, whole) and not a.flags.writeable
    assert g.depth.flags.writeable and not np.shares_memory(g.depth, whole)
    bigger = decode_frame(bytearray(data))
    assert not bigger.features.flags.writeable


def test_frame_decode_accepts_memoryview_slice():
    f = make_frame(seed=5)
    data = b"xyz" + encode_frame(f) + b"tail"
    g = decode_frame(memoryview(data)[3:-4])
    assert g.seq == f.seq


# ---------------------------------------------------------------- depth accuracy

SPECIAL = np.array([0.001, 0.0004, 0.0006, 0.0015, 0.5005, 1.23456, 12.3456, 65.0, 65.5, 65.534,
                    np.nan, np.inf, -np.inf, 0.0, -3.0], dtype=np.float32)


def depth_frame(depth: np.ndarray) -> Frame:
    h, w = depth.shape
    return Frame(robot="r", seq=0, stamp=0.0, pose=np.eye(4),
                 intrinsics=np.array([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]]),
                 depth=depth, rgb=np.zeros((h, w, 3), np.uint8))


def expected_depth(d: np.ndarray) -> np.ndarray:
    """The convention: -inf and <= 0 mean no measurement (NaN)."""
    e = d.astype(np.float32).copy()
    with np.errstate(invalid="ignore"):
        e[~(e > 0)] = np.nan
    return e


@pytest.mark.parametrize("codec", ["png16mm", "auto"])
def test_depth_png16mm_accuracy(codec):
    d = SPECIAL.reshape(3, 5)
    data = encode_frame(depth_frame(d), depth_codec=codec)
    assert raw_header(data)[0]["depth"]["codec"] == "png16mm"
    g = decode_frame(data).depth
    e = expected_depth(d)
    assert np.array_equal(np.isnan(g), np.isnan(e)) and np.array_equal(np.isposinf(g), np.isposinf(e))
    fin = np.isfinite(e)
    err = np.abs(g[fin].astype(np.float64) - e[fin].astype(np.float64))
    assert err.max() <= 0.001 + 1e-6
    # ≤ 0.5 mm for everything at or above 1 mm (incl. 65.0 m and 65.534 m)
    assert err[e[fin] >= 0.001].max() <= 0.0005 + 1e-6
    assert abs(g[1, 2] - 65.0) < 1e-5 and abs(g[0, 0] - 0.001) < 1e-7
    assert g[0, 1] == pytest.approx(0.001)  # 0.4 mm is clipped up to 1 mm, not dropped


def test_depth_png16mm_clips_beyond_range():
    d = np.array([[70.0, 1000.0]], np.float32)
    g = decode_frame(encode_frame(depth_frame(d), depth_codec="png16mm")).depth
    assert np.allclose(g, 65.534)


def test_depth_auto_switches_to_f32_and_is_exact():
    d = np.concatenate([SPECIAL, [70.0, 1e6, 123.456789]]).astype(np.float32).reshape(3, 6)
    data = encode_frame(depth_frame(d), depth_codec="auto")
    assert raw_header(data)[0]["depth"]["codec"] == "f32"
    g = decode_frame(data).depth
    e = expected_depth(d)
    assert np.array_equal(g, e, equal_nan=True)


def test_depth_f16_keeps_nan_inf_and_is_lossy():
    d = np.array([[0.00001, 1.0, 33.3, 70000.0, np.nan, np.inf, -np.inf, -1.0]], np.float32)
    data = encode_frame(depth_frame(d), depth_codec="f16")
    g = decode_frame(data).depth
    assert g.dtype == np.float32
    assert np.isnan(g[0, 4:]).tolist() == [True, False, True, True]
    assert np.isposinf(g[0, 5]) and np.isposinf(g[0, 3])  # > 65504 overflows to +inf (documented)
    assert g[0, 0] > 0  # tiny depths stay measurements
    assert abs(g[0, 2] - 33.3) < 0.02


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 12), st.integers(1, 12), st.integers(0, 2**32 - 1),
    st.sampled_from(["auto", "png16mm", "f32"]), st.floats(0.0005, 65.0),
)
def test_depth_round_trip_property(h, w, seed, codec, top):
    rng = np.random.default_rng(seed)
    d = rng.uniform(0, top, (h, w)).astype(np.float32)
    pick = rng.random((h, w))
    d[pick < 0.1] = np.nan
    d[(pick >= 0.1) & (pick < 0.2)] = np.inf
    d[(pick >= 0.2) & (pick < 0.25)] = -np.inf
    d[(pick >= 0.25) & (pick < 0.3)] = 0.0
    g = decode_frame(encode_frame(depth_frame(d), depth_codec=codec)).depth
    e = expected_depth(d)
    assert np.array_equal(np.isnan(g), np.isnan(e)) and np.array_equal(np.isposinf(g), np.isposinf(e))
    fin = np.isfinite(e)
    if fin.any():
        assert np.abs(g[fin] - e[fin]).max() <= 0.001


# ---------------------------------------------------------------- frame errors


@pytest.fixture(scope="module")
def good() -> bytes:
    return encode_frame(make_frame(seed=7), rgb_codec="jpeg")


@pytest.fixture(scope="module")
def good_raw() -> bytes:
    return encode_frame(make_frame(seed=8), rgb_codec="raw", depth_codec="f32")


def _set(key, value):
    def fn(h):
        h[key] = value
    return fn


def _del(key):
    def fn(h):
        del h[key]
    return fn


@pytest.mark.parametrize(
    "fn, words",
    [
        (_set("schema", "rayfronts.query"), ["schema", "rayfronts.frame"]),
        (_set("v", 3), ["v", "expected"]),
        (_del("robot"), ["robot", "missing"]),
        (_set("robot", "bad id!"), ["robot"]),
        (_set("robot", "r" * 65), ["robot"]),
        (_set("robot", 5), ["robot", "str"]),
        (_set("seq", -1), ["seq"]),
        (_set("seq", "3"), ["seq"]),
        (_set("seq", True), ["seq"]),
        (_del("seq"), ["seq", "missing"]),
        (_set("stamp", float("nan")), ["stamp"]),
        (_set("stamp", None), ["stamp"]),
        (_del("pose"), ["pose", "missing"]),
        (_set("pose", [[1, 0, 0, 0]] * 4), ["pose", "array"]),
        (_del("depth"), ["depth", "missing"]),
        (_set("depth", 3), ["depth", "map"]),
        (_del("rgb"), ["rgb", "missing"]),
        (_set("feature_space", 7), ["feature_space"]),
        (_set("meta", {"a": {"b": 1}}), ["meta.a"]),
        (_set("meta", [1]), ["meta"]),
        (_set("meta", {f"k{i}": i for i in range(100)}), ["meta", "limit"]),
        (lambda h: h["depth"].update(codec="jpeg"), ["depth.codec"]),
        (lambda h: h["depth"].update(shape=[48, 65]), ["depth.data", "PNG"]),
        (lambda h: h["depth"].update(shape=[48]), ["depth.shape"]),
        (lambda h: h["depth"].update(shape=[5000, 5000]), ["depth.shape", "limit"]),
        (lambda h: h["depth"].pop("data"), ["depth.data", "missing"]),
        (lambda h: h["rgb"].update(shape=[48, 64, 4]), ["rgb.shape"]),
        (lambda h: h["rgb"].update(shape=[40, 64, 3]), ["rgb.data", "JPEG"]),
        (lambda h: h["rgb"].update(codec="png"), ["rgb.codec"]),
        (lambda h: h["labels"].update(codec="png8"), ["labels.codec"]),
        (lambda h: h["confidence"].update(codec="f32"), ["confidence.codec"]),
        (lambda h: h["features"]["__nd__"].__setitem__(0, "<f4"), ["features"]),
        (lambda h: h["features"]["__nd__"].__setitem__(0, "<c8"), ["features", "dtype"]),
        (lambda h: h["features"]["__nd__"].__setitem__(0, ">f2"), ["features", "dtype"]),
        (lambda h: h["features"]["__nd__"].__setitem__(2, 10**9), ["features", "out of bounds"]),
        (lambda h: h["features"]["__nd__"].__setitem__(2, -8), ["features", "offset"]),
        (lambda h: h["features"]["__nd__"].__setitem__(3, 2), ["features", "nbytes"]),
        (lambda h: h["features"]["__nd__"].__setitem__(1, [8, 6, -8]), ["features", "dimension"]),
        (lambda h: h["features"]["__nd__"].__setitem__(1, [8, 48]), ["features", "3-D"]),
        (lambda h: h["pose"]["__nd__"].__setitem__(1, [2, 8]), ["pose", "(4, 4)"]),
        (lambda h: h["intrinsics"]["__nd__"].__setitem__(1, [9]), ["intrinsics"]),
        (lambda h: h["global_feature"]["__nd__"].__setitem__(1, [4]), ["global_feature"]),
    ],
)
def test_frame_rejects_structural(good, fn, words):
    assert_rejected(mutate_raw(good, fn), *words)


def _arr(key, f):
    def fn(b):
        b[key] = f(np.array(b[key]))
    return fn


def _nested(key, sub, f):
    def fn(b):
        b[key][sub] = f(b[key][sub])
    return fn


def _poke(x: np.ndarray, i: int, bit: int) -> np.ndarray:
    """Flip bits of byte i (33 = the high byte of the first chunk after IHDR's length)."""
    y = np.array(x)
    y[i] ^= bit
    return y


def _scaled_pose(p):
    p[:3, :3] *= 2
    return p


def _nan_pose(p):
    p[1, 3] = np.nan
    return p


def _reflect_pose(p):
    p[:3, 0] *= -1
    return p


def _bottom_row(p):
    p[3, 0] = 0.5
    return p


@pytest.mark.parametrize(
    "fn, words",
    [
        (_arr("pose", _scaled_pose), ["pose", "rigid"]),
        (_arr("pose", _nan_pose), ["pose", "rigid"]),
        (_arr("pose", _reflect_pose), ["pose", "rigid"]),
        (_arr("pose", _bottom_row), ["pose", "rigid"]),
        (_arr("pose", lambda p: p.astype(np.float32)), ["pose", "<f8"]),
        (_arr("intrinsics", lambda k: k * np.array([[0, 1, 1], [1, 1, 1], [1, 1, 1]])), ["intrinsics", "fx"]),
        (_arr("intrinsics", lambda k: k * np.array([[1, 1, 1], [1, -1, 1], [1, 1, 1]])), ["intrinsics", "fy"]),
        (_arr("intrinsics", lambda k: k + np.array([[0, 0, np.nan], [0, 0, 0], [0, 0, 0]])),
         ["intrinsics", "finite"]),
        (_arr("intrinsics", lambda k: k + np.array([[0, 0, 0], [0, 0, 0], [0.1, 0, 0]])), ["intrinsics"]),
        (_arr("features", lambda x: x[:, :, :0]), ["features"]),
        (_arr("features", lambda x: np.zeros((8, 49, 8), np.float16)), ["features", "depth size"]),
        (_arr("features", lambda x: np.zeros((8, 6, 65), np.float16)), ["features", "depth size"]),
        (_arr("features", lambda x: np.where(x > 1, np.float16(np.nan), x)), ["features", "NaN"]),
        (_arr("features", lambda x: np.zeros((5000, 1, 1), np.float16)), ["features", "channels"]),
        (_arr("global_feature", lambda x: x[:5]), ["global_feature", "length"]),
        (_arr("global_feature", lambda x: np.full_like(x, np.inf)), ["global_feature", "inf"]),
        (_arr("global_feature", lambda x: x.reshape(2, 4)), ["global_feature"]),
        (_nested("labels", "data", lambda x: np.frombuffer(
            cv2.imencode(".png", np.zeros((48, 63), np.uint16))[1], np.uint8)), ["labels.data", "48x63"]),
        (_nested("labels", "data", lambda x: np.frombuffer(
            cv2.imencode(".png", np.zeros((48, 64), np.uint8))[1], np.uint8)), ["labels.data", "16-bit"]),
        (_nested("confidence", "data", lambda x: np.frombuffer(
            cv2.imencode(".png", np.zeros((47, 64), np.uint8))[1], np.uint8)), ["confidence.data"]),
        (_nested("rgb", "data", lambda x: np.frombuffer(b"\xff\xd8garbage", np.uint8)), ["rgb.data", "JPEG"]),
        (_nested("rgb", "data", lambda x: x[: len(x) // 3]), ["rgb.data"]),
        (_nested("rgb", "data", lambda x: np.frombuffer(
            cv2.imencode(".jpg", np.zeros((48, 64), np.uint8))[1], np.uint8)), ["rgb.data", "components"]),
        (_nested("rgb", "data", lambda x: np.frombuffer(cv2.imencode(
            ".jpg", np.zeros((48, 64, 3), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1], np.uint8)),
         ["rgb.data", "unsupported JPEG process"]),
        (_nested("rgb", "data", lambda x: x[:-2]), ["rgb.data", "EOI"]),
        (_nested("labels", "data", lambda x: _poke(x, 40, 0x01)), ["labels.data", "CRC"]),
        (_nested("labels", "data", lambda x: _poke(x, 33, 0x80)), ["labels.data", "runs past the end"]),
        (_nested("labels", "data", lambda x: np.concatenate([x, x[:5]])), ["labels.data", "after IEND"]),
        (_nested("depth", "data", lambda x: x[:100]), ["depth.data"]),
        (_nested("depth", "data", lambda x: np.zeros(0, np.uint8)), ["depth.data", "empty"]),
        (_nested("depth", "data", lambda x: np.arange(100, dtype=np.uint8)), ["depth.data", "PNG"]),
    ],
)
def test_frame_rejects_values(good, fn, words):
    assert_rejected(mutate_body(good, fn), *words)


def _f32_depth(values):
    def fn(b):
        d = np.array(values, np.float32)
        b["depth"]["data"] = np.frombuffer(__import__("zlib").compress(d.tobytes()), np.uint8)
    return fn


@pytest.mark.parametrize(
    "fn, words",
    [
        (_f32_depth(np.full((48, 64), -1.0)), ["depth.data", "<= 0"]),
        (_f32_depth(np.full((48, 64), -np.inf)), ["depth.data", "-inf"]),
        (_f32_depth(np.ones((48, 63))), ["depth.data", "exactly"]),
        (_f32_depth(np.ones((48, 65))), ["depth.data", "exactly"]),
        (_nested("depth", "data", lambda x: x[: len(x) - 5]), ["depth.data"]),
        (_nested("depth", "data", lambda x: np.frombuffer(b"not zlib at all", np.uint8)), ["depth.data", "zlib"]),
        (_nested("rgb", "data", lambda x: x[:, :10]), ["rgb.data", "shape"]),
        (_nested("rgb", "data", lambda x: x.astype(np.uint16)), ["rgb.data", "|u1"]),
    ],
)
def test_frame_rejects_f32_depth_and_raw_rgb(good_raw, fn, words):
    assert_rejected(mutate_body(good_raw, fn), *words)


def test_frame_depth_f16_rejects_negative():
    data = encode_frame(make_frame(seed=9), depth_codec="f16")
    bad = mutate_body(data, _nested("depth", "data", lambda x: -np.abs(np.array(x))))
    assert_rejected(bad, "depth.data", "<= 0")
    bad = mutate_body(data, _nested("depth", "data", lambda x: np.array(x)[:, :3]))
    assert_rejected(bad, "depth.data", "shape")


def test_frame_limits(good):
    assert_rejected(good, "depth.shape", limits=WireLimits(max_pixels=100))
    assert_rejected(good, "features", limits=WireLimits(max_channels=4))
    assert_rejected(good, "robot", limits=WireLimits(max_robot_id_len=4))
    assert_rejected(good, "message", limits=WireLimits(max_message_bytes=100))


def test_frame_truncated_everywhere_raises_wire_error(good):
    for cut in range(0, len(good), max(1, len(good) // 300)):
        try:
            decode_frame(good[:cut])
        except WireError:
            continue
        raise AssertionError(f"truncation at {cut} decoded")


def test_frame_tolerates_unknown_extra_fields(good):
    g = decode_frame(mutate_raw(good, _set("future_field", [1, 2, 3])))
    assert g.robot == "robot_1-a"


# ---------------------------------------------------------------- frame encode errors


def _frame_with(**kw) -> Frame:
    f = make_frame(seed=10)
    for k, v in kw.items():
        setattr(f, k, v)
    return f


@pytest.mark.parametrize(
    "kw, enc, words",
    [
        ({"robot": "a b"}, {}, ["robot"]),
        ({"seq": -2}, {}, ["seq"]),
        ({"stamp": float("inf")}, {}, ["stamp"]),
        ({"pose": np.diag([2.0, 1, 1, 1])}, {}, ["pose", "rigid"]),
        ({"pose": np.eye(3)}, {}, ["pose"]),
        ({"intrinsics": np.eye(3) * -1}, {}, ["intrinsics"]),
        ({"depth": np.zeros((2, 3, 4), np.float32)}, {}, ["depth"]),
        ({"depth": np.full((48, 64), 1000, np.uint16)}, {}, ["depth", "metres"]),
        ({"rgb": np.zeros((48, 64, 3), np.float32)}, {}, ["rgb", "uint8"]),
        ({"rgb": np.zeros((48, 64), np.uint8)}, {}, ["rgb"]),
        ({"features": np.full((8, 6, 8), 1e6, np.float32)}, {}, ["features", "finite"]),
        ({"features": np.zeros((8, 60, 8), np.float16)}, {}, ["features", "larger"]),
        ({"global_feature": np.zeros(3, np.float16)}, {}, ["global_feature", "length"]),
        ({"labels": np.full((48, 64), 70000)}, {}, ["labels", "65535"]),
        ({"labels": np.full((48, 64), -1)}, {}, ["labels"]),
        ({"labels": np.zeros((10, 10), np.int32)}, {}, ["labels"]),
        ({"confidence": np.zeros((10, 10), np.float32)}, {}, ["confidence"]),
        ({"meta": {"x": [1, 2]}}, {}, ["meta.x"]),
        ({"meta": {1: 2}}, {}, ["meta"]),
        ({"meta": {str(i): i for i in range(65)}}, {}, ["meta", "limit"]),
        ({"meta": {"k": "v" * 5000}}, {}, ["meta.k", "limit"]),
        ({"features": np.zeros((5000, 2, 2), np.float16), "global_feature": None}, {}, ["features", "limit"]),
        ({"feature_space": "f" * 5000}, {}, ["feature_space", "limit"]),
        ({"feature_space": 3}, {}, ["feature_space"]),
        ({}, {"depth_codec": "png"}, ["depth codec"]),
        ({}, {"rgb_codec": "webp"}, ["rgb codec"]),
        ({}, {"jpeg_quality": 150}, ["jpeg_quality"]),
    ],
)
def test_encode_frame_refuses(kw, enc, words):
    with pytest.raises(WireError) as ei:
        encode_frame(_frame_with(**kw), **enc)
    for w in words:
        assert w in str(ei.value), str(ei.value)


def test_encode_frame_confidence_quantisation_and_sanitising():
    f = make_frame(seed=12)
    c = np.linspace(-0.5, 1.5, 48 * 64, dtype=np.float32).reshape(48, 64)
    c[0, 0] = np.nan
    f.confidence = c
    g = decode_frame(encode_frame(f)).confidence
    expected = np.clip(np.nan_to_num(c, nan=0.0), 0, 1)
    assert np.abs(g - expected).max() <= 1 / 510 + 1e-6
    assert g.min() >= 0 and g.max() <= 1 and g[0, 0] == 0


def test_encode_frame_accepts_numpy_scalars_and_other_numeric_dtypes():
    f = make_frame(seed=13)
    f.seq, f.stamp = np.int64(5), np.float32(2.5)
    f.depth = f.depth.astype(np.float64)
    f.labels = f.labels.astype(np.uint16)
    f.meta = {"n": np.int32(3), "f": np.float64(0.25), "b": np.bool_(False)}
    g = decode_frame(encode_frame(f))
    assert (g.seq, g.stamp) == (5, 2.5) and g.meta == {"n": 3, "f": 0.25, "b": False}
    assert g.labels.dtype == np.int32 and np.array_equal(g.labels, f.labels)


def test_decode_frame_schema_name_constant(good):
    assert decode_message(good)[0] == FRAME_SCHEMA
