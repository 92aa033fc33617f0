"""Frame v2 feature encoding (``q16z`` / ``q8z``: per-channel int16 / int8 + zlib): bytes per 640×480 frame,
error bounds, validation of hostile streams, old v1 messages still decoding, and the map it
builds answering like the float16 one (query cosines, top-1 class of every voxel)."""
from __future__ import annotations

import zlib

import msgpack
import numpy as np
import pytest
import torch

from common.frame import Frame
from common.wire import FRAME_VERSION, WireError, decode_frame, encode_frame


def _frame(c=100, h=30, w=40, H=480, W=640, seed=0, feats=None):
    rng = np.random.default_rng(seed)
    f = feats if feats is not None else rng.standard_normal((c, h, w)).astype(np.float16)
    return Frame(robot="r1", seq=3, stamp=1.5, pose=np.eye(4), intrinsics=np.array([[300.0, 0, W / 2], [0, 300, H / 2],
                                                                                      [0, 0, 1]]),
                 depth=np.full((H, W), 5.0, np.float32), rgb=np.zeros((H, W, 3), np.uint8), features=f,
                 global_feature=f[:, 0, 0].copy(), feature_space="label-x-raw-100")


def _header(data: bytes) -> tuple[dict, int]:
    n = int.from_bytes(data[:4], "little")
    return msgpack.unpackb(data[4:4 + n], raw=False, strict_map_key=False), n


def _repack(data: bytes, h: dict) -> bytes:
    """The same message with header ``h`` (buffers re-aligned at their old offsets)."""
    _, n = _header(data)
    old = (4 + n + 7) // 8 * 8
    hb = msgpack.packb(h, use_bin_type=True)
    start = (4 + len(hb) + 7) // 8 * 8
    return len(hb).to_bytes(4, "little") + hb + b"\0" * (start - 4 - len(hb)) + data[old:]


@pytest.mark.parametrize("codec, top", [("q8z", 127), ("q16z", 32767)])
def test_quantised_roundtrip_error_bound_and_version(codec, top):
    fr = _frame()
    data = encode_frame(fr, feature_codec=codec)
    h, _ = _header(data)
    assert h["v"] == FRAME_VERSION == 2 and h["features"]["codec"] == codec
    assert len(data) < len(encode_frame(fr, feature_codec="f16"))
    got = decode_frame(data)
    f = fr.features.astype(np.float32)
    scale = np.abs(f).reshape(100, -1).max(1) / top
    err = np.abs(got.features.astype(np.float32) - f)
    assert got.features.dtype == np.float16 and got.features.shape == fr.features.shape
    # half a step of int8 plus float16 rounding of the result
    assert (err <= scale[:, None, None] / 2 + np.abs(f) * 2e-3 + 1e-6).all()
    assert np.array_equal(got.global_feature, fr.global_feature)   # the image vector stays float16


def test_f16_codec_is_exact_and_v1_messages_still_decode():
    fr = _frame(seed=1)
    data = encode_frame(fr, feature_codec="f16")
    got = decode_frame(data)
    assert np.array_equal(got.features, fr.features)
    # an old-format (v1) message: the same body under "v": 1 decodes to the same frame
    h, _ = _header(data)
    h["v"] = 1
    old = decode_frame(_repack(data, h))
    assert np.array_equal(old.features, fr.features) and old.seq == 3 and old.robot == "r1"
    # v1 never carried compressed features: a q16z body under v1 is refused
    hq, _ = _header(encode_frame(fr, feature_codec="q16z"))
    hq["v"] = 1
    with pytest.raises(WireError, match="features"):
        decode_frame(_repack(encode_frame(fr, feature_codec="q16z"), hq))
    with pytest.raises(WireError, match="feature codec"):
        encode_frame(fr, feature_codec="int4")


@pytest.mark.parametrize("mutate, words", [
    (lambda f: f.__setitem__("codec", "lz4"), "unknown codec"),
    (lambda f: f.__setitem__("shape", [100, 30]), "shape"),
    (lambda f: f.__setitem__("shape", [100, 30, 41]), "inflates"),
    (lambda f: f.__setitem__("codec", "q8z"), "inflates"),              # int16 bytes read as int8
    (lambda f: f.pop("scale"), "map with codec"),
])
def test_quantised_malformed_rejected(mutate, words):
    data = encode_frame(_frame(seed=2), feature_codec="q16z")
    h, _ = _header(data)
    mutate(h["features"])
    with pytest.raises(WireError, match=words) as e:
        decode_frame(_repack(data, h))
    assert e.value.reason == "frame.features"


def test_quantised_zip_bomb_and_garbage_bounded():
    """A stream that inflates to far more than C·h·w bytes, or is no zlib stream, is refused
    after inflating at most C·h·w + 1 bytes."""
    from common.wire.envelope import decode_message, encode_message
    from common.wire.frame import FRAME_SCHEMA

    fr = _frame(c=4, h=3, w=4, seed=3)
    base = decode_frame(encode_frame(fr, feature_codec="q16z"))
    assert base.features.shape == (4, 3, 4)
    for payload, needle in ((zlib.compress(b"\0" * (200 << 20), 9), "inflates"), (b"\x00garbage" * 10, "zlib")):
        body = dict(decode_message(encode_frame(fr, feature_codec="q16z"))[2])
        body["features"] = {"codec": "q8z", "shape": [4, 3, 4], "scale": np.ones(4, "<f4"),
                            "data": np.frombuffer(payload, np.uint8)}
        with pytest.raises(WireError, match=needle):
            decode_frame(encode_message(FRAME_SCHEMA, 2, body))


def test_640x480_label_frames_under_100kb_and_the_map_answers_the_same():
    """Demo-like frames (synthetic world, label encoder at the patch grid, PCA-100): every
    640×480 q16z frame (JPEG 80, as the edge sends) is <= 100 KB; maps built from the q16z and float16 features give max
    |Δcos| <= 0.01 on the demo's queries and the same top-1 class on every voxel."""
    from apps.demo import DEFAULT_QUERIES
    from common.feature_space import FeatureSpace
    from common.pca import OnlinePCAFitter
    from edge.encoding import compress_features
    from edge.sources import SourceConfig, open_source
    from encoders import EncoderConfig, make_encoder
    from encoders.text import MiniLMText
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap

    src = open_source(SourceConfig(kind="synthetic", n_frames=10, resolution="480x640", depth_limit=20.0))
    frames = list(src)
    enc = make_encoder(EncoderConfig(kind="label", label_stride=16), class_names=src.class_names)
    feats = [enc.encode(f.rgb, f.labels) for f in frames]
    fit = OnlinePCAFitter(100, 8)
    for x in feats[:8]:
        fit.add(x)
    pca = fit.fit()
    fs = FeatureSpace("label", "t", 384, pca=pca)
    cfg = map_config("throughput", {"vox_size": 0.5, "depth_limit": 20.0})
    maps = {k: RayFrontsMap(cfg, 100, fs.id) for k in ("f16", "q16z")}
    sizes = []
    import dataclasses

    for f, x in zip(frames, feats, strict=True):
        out = dataclasses.replace(f, features=compress_features(pca, x), feature_space=fs.id)
        for k, m in maps.items():
            data = encode_frame(out, feature_codec=k, jpeg_quality=80)  # as the edge sends (q16z default)
            if k == "q16z":
                sizes.append(len(data))
            d = decode_frame(data)
            m.integrate(d.pose, d.intrinsics, d.depth, np.array(d.rgb), np.array(d.features))
    for m in maps.values():
        m.flush()
    assert max(sizes) <= 100_000, sizes
    va, vb = maps["f16"].voxels(), maps["q16z"].voxels()
    assert torch.equal(torch.as_tensor(va.xyz), torch.as_tensor(vb.xyz)) and len(va.xyz) > 1000
    text = MiniLMText()
    q = text.encode(list(DEFAULT_QUERIES)).float()
    sa, sb = fs.similarity(va.features, q), fs.similarity(vb.features, q)
    assert float((sa - sb).abs().max()) <= 0.01
    cls = text.encode(list(src.class_names)).float()
    ta, tb = fs.similarity(va.features, cls).argmax(0), fs.similarity(vb.features, cls).argmax(0)
    assert torch.equal(ta, tb), int((ta != tb).sum())
