"""Synthetic-world and recording sources, and the shared selection / resampling rules."""
from __future__ import annotations

import numpy as np
import pytest

import synthetic_world as world_mod
from common.geometry import camera_rays, intrinsics_from_fov
from edge.sources import SourceConfig, SourceError, open_source, select_indices


@pytest.fixture(scope="module")
def world():
    return world_mod.World.generate(0, "default")


def _cfg(**kw):
    base = dict(kind="synthetic", seed=0, preset="default", trajectory="ground", n_frames=6,
                resolution="48x64", hfov=90.0)
    base.update(kw)
    return SourceConfig(**base)


def test_select_indices():
    assert select_indices(range(10), 0, None) == list(range(10))
    assert select_indices(range(10), 2, None) == [0, 3, 6, 9]
    assert select_indices([0, 1, 3, 4, 6, 7], 1, 2) == [0, 4]  # the rule is on the source index
    with pytest.raises(SourceError):
        select_indices(range(3), -1, None)


def test_synthetic_frames_match_world_geometry(world):
    src = open_source(_cfg())
    assert len(src) == 6 and src.class_names == world.classes and src.class_names[0] == "sky"
    K = intrinsics_from_fov(90.0, 48, 64)
    np.testing.assert_allclose(src.intrinsics, K)
    poses = world.trajectory("ground", 6)
    frames = list(src)
    assert [f.seq for f in frames] == list(range(6))
    n_checked = n_agree = 0
    for i, f in enumerate(frames):
        np.testing.assert_allclose(f.pose, poses[i])
        assert f.depth.shape == (48, 64) and f.rgb.shape == (48, 64, 3) and f.labels.dtype == np.int32
        assert f.stamp == pytest.approx(i / 10.0)
        d = f.depth
        assert not np.any(d <= 0) and not np.any(np.isneginf(d))
        # Sky: +inf depth exactly where the label is 0.
        np.testing.assert_array_equal(np.isinf(d), f.labels == 0)
        # Geometry: a point 1 cm beyond each finite depth pixel lies inside a solid of the pixel's class.
        rays = camera_rays(f.intrinsics, 48, 64)
        fin = np.isfinite(d)
        pc = rays[fin] * d[fin][:, None]
        pc += 0.01 * rays[fin] / np.linalg.norm(rays[fin], axis=1, keepdims=True)
        pw = pc @ f.pose[:3, :3].T + f.pose[:3, 3]
        lab = world.labels_at(pw)
        n_checked += lab.size
        n_agree += int(np.sum(lab == f.labels[fin]))
    assert n_checked > 1000
    assert n_agree / n_checked > 0.97


def test_synthetic_skip_max_limit(world):
    full = list(open_source(_cfg()))
    src = open_source(_cfg(frame_skip=2, max_frames=1, depth_limit=5.0, robot="rover"))
    frames = list(src)
    assert len(src) == 1 and len(frames) == 1 and frames[0].meta["index"] == 0 and frames[0].robot == "rover"
    d0, d = full[0].depth, frames[0].depth
    assert np.all(d[np.isfinite(d)] <= 5.0)
    np.testing.assert_array_equal(d[d0 <= 5.0], d0[d0 <= 5.0])
    assert np.all(np.isinf(d[d0 > 5.0]))
    src = open_source(_cfg(frame_skip=2))
    assert [f.meta["index"] for f in src] == [0, 3]


def test_synthetic_resolution_rescales_intrinsics(world):
    a = open_source(_cfg(resolution="24x32"))
    b = open_source(_cfg(resolution="48x64"))
    np.testing.assert_allclose(a.intrinsics[:2], b.intrinsics[:2] / 2)
    fa = next(iter(a))
    assert fa.depth.shape == (24, 32) and fa.labels.shape == (24, 32) and fa.rgb.shape == (24, 32, 3)


def test_synthetic_bad_config():
    with pytest.raises(SourceError, match="preset"):
        open_source(_cfg(preset="moon"))
    with pytest.raises(SourceError, match="trajectory"):
        open_source(_cfg(trajectory="submarine"))


# --------------------------------------------------------------------------- recording

def test_recording_roundtrip(tmp_path, world):
    import common.recording as rec
    frames = list(open_source(_cfg(n_frames=5)))
    path = tmp_path / "rec"
    with rec.RecordingWriter(path, robot="robot1", source={"type": "synthetic_world", "classes": world.classes,
                                                            "frame_dt": 0.1}) as w:
        for f in frames:
            w.write(f)
    src = open_source(SourceConfig(kind="recording", path=str(path), frame_skip=1, resolution="24x32",
                                   depth_limit=4.0))
    out = list(src)
    assert [f.meta["index"] for f in out] == [0, 2, 4] and len(src) == 3
    assert src.class_names == world.classes and "synthetic" in src.world_frame
    np.testing.assert_allclose(src.intrinsics, frames[0].intrinsics * [[0.5], [0.5], [1]])
    for f in out:
        g = frames[f.meta["index"]]
        np.testing.assert_allclose(f.pose, g.pose)
        np.testing.assert_allclose(f.intrinsics, g.intrinsics * [[0.5], [0.5], [1]])
        exp = g.depth[1::2, 1::2].copy()
        exp[np.isfinite(exp) & (exp > 4.0)] = np.inf
        np.testing.assert_allclose(f.depth, exp, atol=1e-3)
        assert f.rgb.shape == (24, 32, 3) and f.stamp == pytest.approx(g.stamp)
        np.testing.assert_array_equal(f.labels, g.labels[1::2, 1::2])


def test_recording_missing(tmp_path):
    with pytest.raises(SourceError, match="no_such_rec"):
        open_source(SourceConfig(kind="recording", path=str(tmp_path / "no_such_rec")))
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="recording.yaml"):
        open_source(SourceConfig(kind="recording", path=str(tmp_path / "empty")))
