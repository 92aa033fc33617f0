"""`rayfronts world` end to end and `rayfronts bench world`."""
from __future__ import annotations

import argparse

import numpy as np
import pytest

from apps.cli import main
from synthetic_world import World


def test_rayfronts_world_writes_recording_and_rrd(tmp_path, capsys):
    import rerun as rr

    from common.recording import RecordingReader

    out = tmp_path / "w"
    rc = main(["world", "--out", str(out), "--frames", "4", "--resolution", "48x64", "--seed", "3",
               "--depth-limit", "20", "--robot", "rover_1"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert str(out / "recording") in printed and str(out / "world.rrd") in printed

    # The recording holds what the world renders, with the depth limit applied.
    world = World.generate(3)
    poses = world.trajectory("ground", 4, seed=3)
    K = world.camera((48, 64), 90.0)
    rec = RecordingReader(out / "recording")
    assert len(rec) == 4 and rec.info["robot"] == "rover_1"
    for i, f in enumerate(rec):
        ref = world.render(poses[i], K, (48, 64))
        assert f.robot == "rover_1" and f.seq == i and f.stamp == pytest.approx(0.1 * i)
        np.testing.assert_allclose(f.pose, poses[i], atol=1e-9)
        np.testing.assert_allclose(f.intrinsics, K)
        np.testing.assert_array_equal(f.labels, ref.labels)
        assert f.features is None and f.feature_space == ""
        near = np.isfinite(ref.depth) & (ref.depth <= 19.9)
        np.testing.assert_allclose(f.depth[near], ref.depth[near], atol=2e-3)
        assert np.all(np.isinf(f.depth[ref.depth > 20.1]))
        assert np.abs(f.rgb.astype(int) - ref.rgb).mean() < 8  # JPEG on the wire

    # The rerun file has the expected entities.
    reader = rr.chunk.RrdReader(str(out / "world.rrd"))
    summary = reader.store().summary()
    cam = "/world/robots/rover_1/camera"                 # docs/conventions.md#rerun-entity-paths
    for entity, col in [("/world/truth/instances", "Boxes3D:centers"), (cam, "Transform3D:translation"),
                        (f"{cam}/image", "Pinhole:image_from_camera"),
                        (f"{cam}/image/rgb", "EncodedImage:blob"),
                        (f"{cam}/image/depth", "DepthImage:buffer"),
                        (f"{cam}/image/labels", "SegmentationImage:buffer"),
                        ("/world/robots/rover_1/trajectory", "LineStrips3D:strips"),
                        ("/world", "AnnotationContext:context")]:
        assert any(line.startswith(entity + " ") and col in line for line in summary.splitlines()), entity
    labels = []
    for chunk in reader.stream().to_chunks():
        rb = chunk.to_record_batch()
        if "Boxes3D:labels" in rb.schema.names:
            labels = rb.column("Boxes3D:labels")[0].as_py()
    assert len(labels) == len(world.instances)
    assert any(lab.startswith("radio tower") for lab in labels)


def test_rayfronts_world_rejects_bad_options(tmp_path, capsys):
    assert main(["world", "--out", str(tmp_path), "--frames", "0"]) == 2
    assert "--frames" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["world", "--resolution", "big"])


def test_bench_world_reports_fps():
    from apps.bench import world as bench

    res = bench.run(argparse.Namespace(frames=2, seed=0, preset="ground", hfov=90.0))
    assert res["fps_224x224"] > 0 and res["fps_640x480"] > 0
    assert res["n_primitives"] == World.generate(0).n_primitives
