"""Fuzzing the frame decoder: every mutated message either decodes to a Frame that keeps the
frame contract, or raises WireError — nothing else. Seeded and deterministic."""
from __future__ import annotations

import math
import random
import re
import struct
import zlib
from collections import Counter

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.frame import Frame
from common.wire import WireError, WireLimits, decode_frame, encode_frame

N_BYTE = 6000
N_STRUCT = 5000
LIMITS = WireLimits()


# ---------------------------------------------------------------- base messages


def _frame(seed: int, h: int, w: int, *, optional: bool, rgb_hw=None) -> Frame:
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rng.standard_normal(3))[0]
    pose[:3, 3] = rng.uniform(-10, 10, 3)
    depth = rng.uniform(0.1, 20, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.1] = np.nan
    depth[rng.random((h, w)) < 0.1] = np.inf
    rh, rw = rgb_hw or (h, w)
    y, x = np.mgrid[0:rh, 0:rw]
    rgb = np.stack([x * 7 % 256, y * 11 % 256, (x + y) * 5 % 256], -1).astype(np.uint8)
    c = 6
    return Frame(
        robot=f"bot{seed}", seq=seed, stamp=100.0 + seed, pose=pose,
        intrinsics=np.array([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]]),
        depth=depth, rgb=rgb,
        features=rng.standard_normal((c, 3, 4)).astype(np.float16) if optional else None,
        feature_space="fs-1" if optional else "",
        labels=rng.integers(0, 300, (h, w)).astype(np.int32) if optional else None,
        confidence=rng.random((h, w)).astype(np.float32) if optional else None,
        global_feature=rng.standard_normal(c).astype(np.float16) if optional else None,
        meta={"i": seed, "s": "x"} if optional else {},
    )


def base_messages() -> list[bytes]:
    return [
        encode_frame(_frame(1, 12, 16, optional=True), depth_codec="png16mm", rgb_codec="jpeg"),
        encode_frame(_frame(2, 10, 14, optional=True), depth_codec="f32", rgb_codec="raw"),
        encode_frame(_frame(3, 12, 16, optional=True, rgb_hw=(24, 32)), depth_codec="f16", rgb_codec="jpeg"),
        encode_frame(_frame(4, 8, 8, optional=False), depth_codec="auto", rgb_codec="raw"),
    ]


# ---------------------------------------------------------------- the contract, checked independently

_ROBOT = re.compile(r"[A-Za-z0-9_-]{1,64}")


def check_contract(f: Frame) -> None:
    assert isinstance(f, Frame)
    assert isinstance(f.robot, str) and _ROBOT.fullmatch(f.robot)
    assert type(f.seq) is int and f.seq >= 0
    assert type(f.stamp) is float and math.isfinite(f.stamp)
    assert f.pose.dtype == np.float64 and f.pose.shape == (4, 4) and np.isfinite(f.pose).all()
    r = f.pose[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=2e-3) and abs(np.linalg.det(r) - 1) < 2e-3
    assert np.allclose(f.pose[3], [0, 0, 0, 1], atol=2e-3)
    K = f.intrinsics
    assert K.dtype == np.float64 and K.shape == (3, 3) and np.isfinite(K).all()
    assert K[0, 0] > 0 and K[1, 1] > 0
    d = f.depth
    assert d.dtype == np.float32 and d.ndim == 2 and d.size > 0
    assert d.shape[0] * d.shape[1] <= LIMITS.max_pixels
    assert not np.isneginf(d).any()
    with np.errstate(invalid="ignore"):
        assert not (d <= 0).any()
    H, W = d.shape
    assert f.rgb.dtype == np.uint8 and f.rgb.ndim == 3 and f.rgb.shape[2] == 3 and f.rgb.size > 0
    C = None
    if f.features is not None:
        assert f.features.dtype == np.float16 and f.features.ndim == 3
        C, h, w = f.features.shape
        assert 1 <= C <= LIMITS.max_channels and 1 <= h <= H and 1 <= w <= W
        assert np.isfinite(f.features.astype(np.float32)).all()
    assert isinstance(f.feature_space, str)
    if f.labels is not None:
        assert f.labels.dtype == np.int32 and f.labels.shape == (H, W)
        assert f.labels.min() >= 0 and f.labels.max() <= 65535
    if f.confidence is not None:
        assert f.confidence.dtype == np.float32 and f.confidence.shape == (H, W)
        assert f.confidence.min() >= 0 and f.confidence.max() <= 1
    if f.global_feature is not None:
        g = f.global_feature
        assert g.dtype == np.float16 and g.ndim == 1 and g.shape[0] >= 1
        assert np.isfinite(g.astype(np.float32)).all()
        if C is not None:
            assert g.shape[0] == C
    assert isinstance(f.meta, dict)
    for k, v in f.meta.items():
        assert isinstance(k, str) and (v is None or type(v) in (bool, int, float, str))


def outcome(data) -> str:
    """'ok' (and the contract holds) or 'rejected'. Anything else propagates and fails the test."""
    try:
        f = decode_frame(data, LIMITS)
    except WireError as e:
        assert str(e), "WireError without a message"
        return "rejected"
    check_contract(f)
    return "ok"


# ---------------------------------------------------------------- byte-level mutations


def split(data: bytes) -> tuple[dict, bytes, int]:
    (hl,) = struct.unpack_from("<I", data)
    return msgpack.unpackb(data[4:4 + hl], raw=False), data[(4 + hl + 7) & ~7:], hl


def repack(header, region: bytes) -> bytes:
    hdr = msgpack.packb(header, use_bin_type=True)
    pad = ((4 + len(hdr) + 7) & ~7) - 4 - len(hdr)
    return struct.pack("<I", len(hdr)) + hdr + b"\0" * pad + region


def byte_mutation(rnd: random.Random, data: bytes) -> tuple[str, bytes]:
    b = bytearray(data)
    (hl,) = struct.unpack_from("<I", data)
    kind = rnd.choice(["flip", "flip_header", "truncate", "insert", "delete", "random", "overwrite"])
    if kind in ("flip", "flip_header"):
        hi = 4 + hl if kind == "flip_header" else len(b)
        for _ in range(rnd.randint(1, 8)):
            i = rnd.randrange(hi)
            b[i] ^= 1 << rnd.randrange(8)
    elif kind == "truncate":
        del b[rnd.randrange(len(b)):]
    elif kind == "insert":
        i = rnd.randrange(len(b) + 1)
        b[i:i] = rnd.randbytes(rnd.randint(1, 16))
    elif kind == "delete":
        i = rnd.randrange(len(b))
        del b[i:i + rnd.randint(1, 16)]
    elif kind == "random":
        b = bytearray(rnd.randbytes(rnd.choice([0, 1, 3, 4, 8, 64, 512, len(data)])))
        if len(b) >= 4 and rnd.random() < 0.5:  # plausible header length
            b[:4] = struct.pack("<I", rnd.randint(1, len(b)))
    else:  # overwrite a run in the header with random bytes
        i = rnd.randrange(4, 4 + hl)
        n = rnd.randint(1, 6)
        b[i:i + n] = rnd.randbytes(n)
    return kind, bytes(b)


# ---------------------------------------------------------------- structural mutations

REQUIRED = ("robot", "seq", "stamp", "pose", "intrinsics", "depth", "rgb")
NESTED_REQUIRED = {"depth": ("codec", "shape", "data"), "rgb": ("codec", "shape", "data"),
                   "labels": ("codec", "data"), "confidence": ("codec", "data")}
BAD_VALUES = [None, True, False, -1, 0, 7, 2**63, -2**63, 1.5, float("nan"), float("inf"), "",
              "x" * 100, b"\x00bytes", [], [1, 2, 3], {}, {"a": 1}, [[1, 0], [0, 1]]]
BAD_DTYPES = ["<c8", "|O", "<U4", ">f4", ">f8", "<f16", "|V8", "<M8[s]", "", 5, None, "<f2", "<f4",
              "<f8", "|u1", "<i4", "<u2", "|b1", "<i8"]


def refs(h: dict) -> list[tuple[str, dict]]:
    out = []

    def walk(x, path):
        if isinstance(x, dict):
            if "__nd__" in x:
                out.append((path, x))
                return
            for k, v in x.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif isinstance(x, list):
            for i, v in enumerate(x):
                walk(v, f"{path}[{i}]")

    walk(h, "")
    return out


def ref_mutation(rnd: random.Random, h: dict, region_len: int) -> tuple[str, bool]:
    """Mutate one array reference. Returns (kind, must_reject)."""
    path, ref = rnd.choice(refs(h))
    r = ref["__nd__"]
    what = rnd.choice(["dtype", "shape", "offset", "nbytes", "form"])
    if what == "dtype":
        dt = rnd.choice(BAD_DTYPES)
        if dt == r[0]:
            return "ref.same", False
        r[0] = dt
        # a dtype outside the whitelist must always be rejected
        allowed = {"|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"}
        return "ref.dtype", dt not in allowed
    if what == "shape":
        choice = rnd.randrange(6)
        if choice == 0:
            r[1] = [-rnd.randint(1, 10)] + list(r[1])[1:]
            return "ref.shape.negative", True
        if choice == 1:
            r[1] = [2**rnd.randint(28, 62)] + list(r[1])[1:]
            return "ref.shape.huge", True
        if choice == 2:
            r[1] = list(reversed(r[1]))
            return "ref.shape.reversed", False
        if choice == 3:
            r[1] = list(r[1]) + [1] * rnd.randint(1, 3)
            return "ref.shape.extra_dims", False
        if choice == 4:
            r[1] = [float(s) for s in r[1]] or [1.0]
            return "ref.shape.floats", True
        r[1] = rnd.choice([None, "3", 4, {}])
        return "ref.shape.type", True
    if what == "offset":
        choice = rnd.randrange(4)
        if choice == 0:
            r[2] = region_len + rnd.randint(1, 1000)
            return "ref.offset.past_end", True
        if choice == 1:
            r[2] = -rnd.randint(1, 64)
            return "ref.offset.negative", True
        if choice == 2:
            r[2] = max(0, r[2] + rnd.choice([-8, -1, 1, 8]))
            return "ref.offset.shift", False
        r[2] = rnd.choice([1.0, "0", None])
        return "ref.offset.type", True
    if what == "nbytes":
        if r[3] == 0:
            return "ref.same", False
        r[3] = rnd.choice([r[3] + 1, r[3] - 1, r[3] * 2, 0, -1, 2**40])
        return "ref.nbytes", True
    ref["__nd__"] = rnd.choice([r[:3], r + [0], "x", None, {"a": 1}])
    return "ref.form", True


def _valid_pose_changes(rnd: random.Random, p: np.ndarray) -> tuple[str, np.ndarray, bool]:
    p = p.copy()
    k = rnd.randrange(6)
    if k == 0:
        p[rnd.randrange(4), rnd.randrange(4)] = rnd.choice([np.nan, np.inf, -np.inf])
        return "pose.nonfinite", p, True
    if k == 1:
        p[:3, :3] *= rnd.choice([0.5, 2.0, 0.0])
        return "pose.scaled", p, True
    if k == 2:
        p[:3, rnd.randrange(3)] *= -1
        return "pose.reflection", p, True
    if k == 3:
        p[3, rnd.randrange(3)] = rnd.choice([0.5, 1.0])
        return "pose.bottom_row", p, True
    if k == 4:
        p[rnd.randrange(3), rnd.randrange(3)] += rnd.choice([0.1, -0.3])
        return "pose.skewed", p, True
    p[:3, 3] += rnd.uniform(-1e6, 1e6)  # still rigid: must decode
    return "pose.translated", p, False


def value_mutation(rnd: random.Random, data: bytes) -> tuple[str, bytes, bool]:
    """Mutations that need new array contents: rebuild the buffer region with numpy."""
    h, region, _ = split(data)

    def arr(name):
        dt, shape, off, n = h[name]["__nd__"]
        return np.frombuffer(region, dtype=dt, count=n // np.dtype(dt).itemsize, offset=off).reshape(shape).copy()

    extra: dict[str, np.ndarray] = {}
    k = rnd.randrange(9)
    must = True
    if k == 0:
        kind, p, must = _valid_pose_changes(rnd, arr("pose"))
        extra["pose"] = p
    elif k == 1:
        K = arr("intrinsics")
        kind = _intrinsics_change(rnd, K)
        extra["intrinsics"] = K
    elif k == 2 and h.get("features") is not None:
        kind, extra["features"] = _features_change(rnd, arr("features"), h["depth"]["shape"])
    elif k == 3 and h.get("global_feature") is not None:
        g = arr("global_feature")
        extra["global_feature"] = np.concatenate([g, g[:1]])
        kind = "global_feature.length"
    elif k == 4 and h.get("labels") is not None:
        H, W = h["depth"]["shape"]
        img = np.zeros((H + 1, W), np.uint16) if rnd.random() < 0.5 else np.zeros((H, W), np.uint8)
        h["labels"]["data"] = cv2.imencode(".png", img)[1].reshape(-1)
        kind = "labels.size_or_depth"
    elif k == 5:
        H, W = h["depth"]["shape"]
        h["depth"]["shape"] = [H, W + rnd.choice([-1, 1])] if W > 1 else [H + 1, W]
        kind = "depth.shape_mismatch"
    elif k == 6:
        H, W, _ = h["rgb"]["shape"]
        h["rgb"]["shape"] = [H + rnd.choice([-1, 1, 100]), W, 3]
        kind = "rgb.shape_mismatch"
    elif k == 7 and h["depth"]["codec"] == "f32":
        H, W = h["depth"]["shape"]
        d = np.full((H, W), rnd.choice([-1.0, 0.0, -np.inf]), np.float32)
        h["depth"]["data"] = np.frombuffer(zlib.compress(d.tobytes()), np.uint8)
        kind = "depth.f32_nonpositive"
    else:
        H, W = h["depth"]["shape"]
        h["depth"]["shape"] = [rnd.randint(5000, 2**31), rnd.randint(5000, 2**31)]
        kind = "depth.shape_huge"

    return kind, _rebuild(h, region, extra), must


def _intrinsics_change(rnd: random.Random, K: np.ndarray) -> str:
    """Break the 3x3 intrinsics ``K`` in place; the mutation's kind."""
    i = rnd.randrange(3)
    if i == 0:
        j = rnd.choice([0, 1])
        K[j, j] = rnd.choice([0.0, -5.0, -1e-9])
        return "intrinsics.focal"
    if i == 1:
        K[rnd.randrange(3), rnd.randrange(3)] = np.nan
        return "intrinsics.nan"
    K[2] = [0.0, 0.0, 2.0]
    return "intrinsics.last_row"


def _features_change(rnd: random.Random, F: np.ndarray, depth_shape) -> tuple[str, np.ndarray]:
    """(kind, broken feature array) from the message's features ``F``."""
    j = rnd.randrange(3)
    if j == 0:
        F.reshape(-1)[rnd.randrange(F.size)] = rnd.choice([np.nan, np.inf])
        return "features.nonfinite", F
    if j == 1:
        H, W = depth_shape
        return "features.taller_than_depth", np.zeros((F.shape[0], H + rnd.randint(1, 5), 2), np.float16)
    return "features.no_channels", np.zeros((0, 2, 2), np.float16)


def _rebuild(h: dict, region: bytes, extra: dict[str, np.ndarray]) -> bytes:
    """The message with header ``h``: refs for the replaced arrays ``extra`` (and the re-encoded
    depth / labels data) point at new buffers appended after the old region."""
    region = bytearray(region)
    for name, a in extra.items():
        a = np.ascontiguousarray(a)
        off = (len(region) + 7) & ~7
        region += b"\0" * (off - len(region)) + a.tobytes()
        h[name] = {"__nd__": [a.dtype.str, list(a.shape), off, a.nbytes]}
    for spec in ("depth", "labels"):
        if isinstance(h.get(spec), dict) and isinstance(h[spec].get("data"), np.ndarray):
            a = h[spec]["data"]
            off = (len(region) + 7) & ~7
            region += b"\0" * (off - len(region)) + a.tobytes()
            h[spec]["data"] = {"__nd__": ["|u1", [a.size], off, a.size]}
    return repack(h, bytes(region))


def structural_mutation(rnd: random.Random, data: bytes) -> tuple[str, bytes, bool]:
    """Returns (kind, message, must_reject)."""
    h, region, _ = split(data)
    r = rnd.random()
    if r < 0.30:
        return value_mutation(rnd, data)
    if r < 0.55:
        kind, must = ref_mutation(rnd, h, len(region))
        return kind, repack(h, region), must
    if r < 0.65:
        key = rnd.choice(list(h))
        del h[key]
        return f"delete.{key}", repack(h, region), key in REQUIRED + ("schema", "v")
    if r < 0.72:
        key = rnd.choice([k for k, v in h.items() if isinstance(v, dict) and k in NESTED_REQUIRED] or ["depth"])
        sub = rnd.choice(list(h[key]))
        del h[key][sub]
        return f"delete.{key}.{sub}", repack(h, region), True
    if r < 0.87:
        key = rnd.choice(list(h))
        val = rnd.choice(BAD_VALUES)
        old = h[key]
        h[key] = val
        # which replacements are legal? optional fields accept nil; a few keys accept some scalars
        legal = (
            (val is None and key in ("features", "labels", "confidence", "global_feature", "meta", "feature_space"))
            or (key == "seq" and type(val) is int and val >= 0)
            or (key == "stamp" and type(val) in (int, float) and math.isfinite(val))
            or (key == "robot" and val == old)
            or (key == "feature_space" and isinstance(val, str))
            or (key == "meta" and val in ({}, {"a": 1}))
        )
        return f"type.{key}", repack(h, region), not legal
    if r < 0.92:
        k = rnd.randrange(4)
        if k == 0:
            h["schema"] = rnd.choice(["rayfronts.frames", "rayfronts.query", "", "RAYFRONTS.FRAME"])
            return "schema", repack(h, region), True
        if k == 1:
            h["v"] = rnd.choice([0, 3, 99, -1])  # v1 and v2 are valid frame versions
            return "version", repack(h, region), True
        if k == 2:
            h["seq"] = -rnd.randint(1, 2**63)
            return "seq.negative", repack(h, region), True
        h["robot"] = rnd.choice(["a b", "robot/1", "", "x" * 65, "é", "r;rm"])
        return "robot.invalid", repack(h, region), True
    if r < 0.96:
        key = rnd.choice([k for k, v in h.items() if isinstance(v, dict) and "codec" in v] or ["depth"])
        h[key]["codec"] = rnd.choice(["png", "jpeg", "f64", "raw", "png16", "png8", "f32", "f16", "png16mm", 3])
        return f"codec.{key}", repack(h, region), False
    h["meta"] = rnd.choice([{"a": [1]}, {"a": {"b": 1}}, {str(i): i for i in range(200)}, {"k": "v" * 5000}])
    return "meta.invalid", repack(h, region), True


# ---------------------------------------------------------------- tests


def test_base_messages_decode():
    for data in base_messages():
        assert outcome(data) == "ok"


def test_fuzz_byte_mutations():
    rnd = random.Random(20240611)
    bases = base_messages()
    counts: Counter = Counter()
    for _ in range(N_BYTE):
        kind, data = byte_mutation(rnd, rnd.choice(bases))
        counts[(kind, outcome(data))] += 1
    total = sum(counts.values())
    assert total == N_BYTE
    # truncations (of the header or of any buffer) and random bytes can never decode
    assert counts[("truncate", "ok")] == 0, counts
    assert counts[("random", "ok")] == 0, counts
    rejected = sum(v for (k, o), v in counts.items() if o == "rejected")
    assert rejected > 0.5 * total, counts


def test_fuzz_structural_mutations():
    rnd = random.Random(777)
    bases = base_messages()
    counts: Counter = Counter()
    must_total = must_rejected = 0
    escaped: list[str] = []
    for _ in range(N_STRUCT):
        kind, data, must = structural_mutation(rnd, rnd.choice(bases))
        res = outcome(data)
        counts[(kind.split(".")[0], res)] += 1
        if must:
            must_total += 1
            if res == "rejected":
                must_rejected += 1
            else:
                escaped.append(kind)
    total = sum(counts.values())
    rejected = sum(v for (k, o), v in counts.items() if o == "rejected")
    assert not escaped, f"mutations that must be rejected decoded: {Counter(escaped)}"
    assert must_total > 0.5 * N_STRUCT, must_total
    assert rejected > 0.6 * total, counts
    # every family of mutation was exercised
    for family in ("pose", "ref", "delete", "type", "schema", "version", "seq", "robot", "codec", "meta"):
        assert any(k == family for k, _ in counts), (family, counts)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=2048), st.integers(0, 3))
def test_fuzz_hypothesis_header_bytes(blob, which):
    """Arbitrary msgpack-ish bytes in place of the header, with the real buffer region."""
    data = base_messages_cache()[which]
    _, region, _ = split(data)
    msg = struct.pack("<I", len(blob)) + blob + b"\0" * (((4 + len(blob) + 7) & ~7) - 4 - len(blob)) + region
    assert outcome(msg) in ("ok", "rejected")


_CACHE: list[bytes] = []


def base_messages_cache() -> list[bytes]:
    if not _CACHE:
        _CACHE.extend(base_messages())
    return _CACHE


@pytest.mark.parametrize("i", range(4))
def test_every_single_byte_truncation_is_rejected(i):
    data = base_messages_cache()[i]
    for cut in range(len(data)):
        assert outcome(data[:cut]) == "rejected", cut
