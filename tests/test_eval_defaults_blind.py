"""No default of ``rayfronts eval search`` reads the world's class list or its true labels
on the robot's side: the command line's defaults are the realistic conditions (sensor,
simulated encoder, PCA basis from the robot's first views, generic background phrases), the
searches' background phrases are the same fixed list for every world (a world whose class
list cannot be read gets them too), the PCA basis is fitted on nothing but encoder outputs
of views rendered at the start (no class table), and the frames the map receives carry no
labels. (The simulated encoder itself turns the rendered scene into features: it stands in
for camera + ViT, so the rendered label image is its input the way pixels are a ViT's.)"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest


def _cli_config(*extra: str):
    from apps.evaluation.cli import _search_config, add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return _search_config(parser.parse_args(["search", "--json", "x.json", *extra]))


def _strings(obj) -> list[str]:
    """Every string in a nested dict / list / tuple."""
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for k, v in obj.items() for s in _strings(k) + _strings(v)]
    if isinstance(obj, (list, tuple)):
        return [s for v in obj for s in _strings(v)]
    return []


class Blind:
    """A world whose class list and labels cannot be read."""

    @property
    def classes(self):
        raise AssertionError("the world's class list was read")


def test_command_line_defaults_are_the_realistic_conditions():
    from apps.closed_loop.episode import GENERIC_BACKGROUND, LoopSettings
    from apps.closed_loop.evaluate import SearchEvalConfig
    from synthetic_world import CLASS_NAMES
    from synthetic_world.pybullet_assets import CLASS_NAMES as PB_NAMES

    cfg = _cli_config()
    assert cfg == SearchEvalConfig(policies=cfg.policies)
    assert (cfg.sensor, cfg.encoder, cfg.pca_fit, cfg.background, cfg.world) == \
        ("realistic", "sim", "first_views", "generic", "synthetic")
    sensor = cfg.sensor_config()
    assert (sensor.sensor, sensor.encoder, sensor.pca_fit) == ("realistic", "sim", "first_views")
    # nothing in the run's settings names a class of either world beyond the generic phrases
    named = set(_strings(dataclasses.asdict(cfg))) | set(_strings(dataclasses.asdict(sensor)))
    assert not named & ((set(CLASS_NAMES) | set(PB_NAMES)) - set(GENERIC_BACKGROUND) - {"sky"})
    phrases = LoopSettings(background=cfg.background).background_phrases(Blind())
    assert phrases == list(GENERIC_BACKGROUND)
    with pytest.raises(AssertionError, match="class list was read"):     # the ablation does read it
        LoopSettings(background="world").background_phrases(Blind())
    ablation = _cli_config("--sensor", "exact", "--encoder", "label", "--pca-fit", "classes", "--background", "world")
    assert (ablation.sensor, ablation.encoder, ablation.pca_fit, ablation.background) == \
        ("exact", "label", "classes", "world")


def test_default_basis_and_frames_use_only_the_robots_own_views(monkeypatch):
    """The default edge chain fits its PCA basis on the encoder's output for views rendered at
    the start (each encoder call's input is exactly such a render; no class table), and a
    frame sent to the map carries depth, features and pose, no labels."""
    from apps.closed_loop.evaluate import SearchEvalConfig
    from apps.closed_loop.robot import camera_pose
    from apps.closed_loop.sensing import EdgeChain
    from synthetic_world import World

    def no_class_cells(self, *a, **k):
        raise AssertionError("the PCA basis read the world's class table")

    monkeypatch.setattr(EdgeChain, "class_cells", no_class_cells)
    seen: list[tuple[np.ndarray, np.ndarray]] = []
    import encoders.sim as sim

    orig = sim.SimEncoder.encode_with_global

    def spy(self, rgb, labels=None, global_space="language"):
        seen.append((np.array(rgb), np.array(labels)))
        return orig(self, rgb, labels, global_space)

    monkeypatch.setattr(sim.SimEncoder, "encode_with_global", spy)
    w = World.generate(1)
    start = np.array([3.0, -2.0, 1.5])
    cfg = SearchEvalConfig(resolution=32)
    chain = EdgeChain(w, cfg.sensor_config(0), fit_at=start)
    assert len(seen) == 8
    for k, (rgb, lab) in enumerate(seen):
        r = w.render(camera_pose(start, 2 * np.pi * k / 8, 0.3 * (k % 2)), chain.K, chain.hw)
        assert np.array_equal(rgb, r.rgb) and np.array_equal(lab, r.labels)
    f = chain.frame(camera_pose(start, 0.0, 0.4))
    assert f.labels is None and f.features is not None and f.depth.shape == (32, 32)
