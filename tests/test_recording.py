"""Recording directories: write real recordings to tmp dirs, read them back, break them."""
from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
import yaml

from common.frame import Frame
from common.recording import RecordingError, RecordingReader, RecordingWriter
from common.wire import decode_frame, encode_frame


def frame(i: int, robot: str = "rover", fs: str = "space-A", h: int = 12, w: int = 16) -> Frame:
    rng = np.random.default_rng(i)
    pose = np.eye(4)
    pose[:3, 3] = [i, 2.0 * i, 0.5]
    depth = rng.uniform(0.5, 10, (h, w)).astype(np.float32)
    depth[0, 0], depth[0, 1] = np.nan, np.inf
    return Frame(
        robot=robot, seq=i, stamp=1000.0 + 0.1 * i, pose=pose,
        intrinsics=np.array([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]]),
        depth=depth, rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        features=rng.standard_normal((4, 3, 4)).astype(np.float16), feature_space=fs,
        labels=rng.integers(0, 50, (h, w)).astype(np.int32), meta={"index": i},
    )


def write(path, n: int, **kw) -> list[Frame]:
    frames = [frame(i) for i in range(n)]
    with RecordingWriter(path, robot="rover", source={"kind": "test", "n": n}, rgb_codec="raw", **kw) as w:
        for f in frames:
            p = w.write(f)
            assert p.name == f"{f.seq:06d}.rff" and p.is_file()
    return frames


def test_write_and_read_back(tmp_path):
    rec = tmp_path / "rec"
    frames = write(rec, 5)
    r = RecordingReader(rec)
    assert len(r) == 5
    info = r.info
    assert info["format"] == "rayfronts.recording" and info["version"] == 1
    assert info["robot"] == "rover" and info["frames"] == 5 and info["feature_space"] == "space-A"
    assert info["source"] == {"kind": "test", "n": 5}
    assert info["encoding"] == {"rgb_codec": "raw"}
    assert info["first_stamp"] == 1000.0 and info["last_stamp"] == pytest.approx(1000.4)
    assert dt.datetime.fromisoformat(info["created"]).tzinfo is not None
    got = list(r)
    assert [g.seq for g in got] == [0, 1, 2, 3, 4]
    for a, b in zip(frames, got, strict=True):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.features, b.features)
        np.testing.assert_array_equal(a.labels, b.labels)
        assert np.array_equal(np.isnan(a.depth), np.isnan(b.depth))
        assert np.array_equal(np.isposinf(a.depth), np.isposinf(b.depth))
        fin = np.isfinite(a.depth)
        assert np.abs(a.depth[fin] - b.depth[fin]).max() <= 5e-4
    assert r[-1].seq == 4 and r[2].seq == 2
    with pytest.raises(IndexError):
        r[5]
    # the files hold exactly the encode_frame bytes
    assert r.read_bytes(3) == encode_frame(frames[3], rgb_codec="raw")
    assert decode_frame((rec / "frames" / "000003.rff").read_bytes()).seq == 3


def test_empty_recording(tmp_path):
    with RecordingWriter(tmp_path / "e", robot="r1"):
        pass
    r = RecordingReader(tmp_path / "e")
    assert len(r) == 0 and list(r) == [] and r.info["frames"] == 0


def test_source_conversions(tmp_path):
    with RecordingWriter(tmp_path / "a", robot="r", source="replica"):
        pass
    assert RecordingReader(tmp_path / "a").info["source"] == {"kind": "replica"}
    src = {"res": (480, 640), "k": np.float32(0.5), "arr": np.arange(3), "path": tmp_path / "x"}
    with RecordingWriter(tmp_path / "b", robot="r", source=src):
        pass
    assert RecordingReader(tmp_path / "b").info["source"] == {
        "res": [480, 640], "k": 0.5, "arr": [0, 1, 2], "path": str(tmp_path / "x")}


def test_overwrite(tmp_path):
    rec = tmp_path / "rec"
    write(rec, 4)
    with pytest.raises(RecordingError, match="already holds a recording") as ei:
        RecordingWriter(rec, robot="rover")
    assert str(rec) in str(ei.value)
    (rec / "notes.txt").write_text("keep me")
    write(rec, 2, overwrite=True)
    r = RecordingReader(rec)
    assert len(r) == 2 and r.info["frames"] == 2
    assert (rec / "notes.txt").read_text() == "keep me"


def test_yaml_stays_valid_if_writer_dies(tmp_path):
    """No close(): the yaml was written on open and every flush_every frames."""
    rec = tmp_path / "crash"
    w = RecordingWriter(rec, robot="rover", flush_every=3)
    assert RecordingReader(rec).info["frames"] == 0
    for i in range(7):
        w.write(frame(i))
    # simulate death: the writer object is abandoned without close()
    info = yaml.safe_load((rec / "recording.yaml").read_text())
    assert info["frames"] == 6  # last flush at frame 6
    r = RecordingReader(rec)
    assert len(r) == 7  # the files on disk are the truth
    assert [f.seq for f in r] == list(range(7))
    assert not list(rec.glob("**/*.tmp"))


def test_write_encoded_keeps_exact_bytes(tmp_path):
    data = encode_frame(frame(0), depth_codec="f32")
    with RecordingWriter(tmp_path / "x", robot="rover") as w:
        w.write_encoded(data)
        with pytest.raises(RecordingError, match="not a valid frame"):
            w.write_encoded(data[:-10])
    r = RecordingReader(tmp_path / "x")
    assert len(r) == 1 and r.read_bytes(0) == data


def test_writer_refuses(tmp_path):
    with pytest.raises(RecordingError, match="robot"):
        RecordingWriter(tmp_path / "a", robot="bad robot")
    with pytest.raises(TypeError, match="unknown encode options"):
        RecordingWriter(tmp_path / "b", robot="r", jpeg_qualty=3)
    with pytest.raises(RecordingError, match="YAML"):
        RecordingWriter(tmp_path / "c", robot="r", source={"x": object()})
    (tmp_path / "file").write_text("x")
    with pytest.raises(RecordingError, match="not a directory"):
        RecordingWriter(tmp_path / "file", robot="r")
    with RecordingWriter(tmp_path / "d", robot="rover") as w:
        w.write(frame(0))
        with pytest.raises(RecordingError, match="robot 'other'"):
            w.write(frame(1, robot="other"))
        with pytest.raises(RecordingError, match="feature space"):
            w.write(frame(1, fs="space-B"))
        bad = frame(1)
        bad.pose = np.diag([2.0, 2, 2, 1])
        with pytest.raises(RecordingError, match="pose"):
            w.write(bad)
        w.write(frame(1))
    with pytest.raises(RecordingError, match="closed"):
        w.write(frame(2))
    assert len(RecordingReader(tmp_path / "d")) == 2


def test_reader_errors_name_the_path(tmp_path):
    missing = tmp_path / "nope"
    with pytest.raises(RecordingError, match="does not exist") as ei:
        RecordingReader(missing)
    assert str(missing) in str(ei.value)

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RecordingError, match="recording.yaml: missing"):
        RecordingReader(empty)

    rec = tmp_path / "rec"
    write(rec, 3)
    yml = rec / "recording.yaml"
    good = yml.read_text()

    yml.write_text("format: [unclosed")
    with pytest.raises(RecordingError, match="YAML") as ei:
        RecordingReader(rec)
    assert str(yml) in str(ei.value)

    yml.write_text("- a list")
    with pytest.raises(RecordingError, match="mapping"):
        RecordingReader(rec)

    info = yaml.safe_load(good)
    for key, value, word in [("version", 2, "unsupported version 2"), ("format", "other", "format"),
                             ("frames", -1, "frames"), ("frames", "3", "frames"), ("robot", None, "robot")]:
        yml.write_text(yaml.safe_dump({**info, key: value}))
        with pytest.raises(RecordingError, match=word) as ei:
            RecordingReader(rec)
        assert str(yml) in str(ei.value)

    yml.write_text(good)
    (rec / "frames" / "000001.rff").unlink()
    with pytest.raises(RecordingError, match="000001.rff: missing"):
        RecordingReader(rec)


def test_reader_corrupt_frame_includes_wire_error(tmp_path):
    rec = tmp_path / "rec"
    write(rec, 3)
    p = rec / "frames" / "000002.rff"
    p.write_bytes(p.read_bytes()[:50])
    r = RecordingReader(rec)
    assert r[1].seq == 1
    with pytest.raises(RecordingError) as ei:
        r[2]
    msg = str(ei.value)
    assert str(p) in msg and "corrupt frame" in msg and "header" in msg
    with pytest.raises(RecordingError):
        list(r)
