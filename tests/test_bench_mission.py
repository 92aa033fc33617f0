"""``rayfronts bench mission``: the per-window records against a map built directly from the
same frames, and the mission route against the no-revisit claim of
:mod:`synthetic_world.mission`."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch

from apps.bench import mission
from common.geometry import intrinsics_from_fov
from semantic_map.config import map_config
from semantic_map.map import RayFrontsMap
from synthetic_world.mission import MissionCity


def _args(tmp_path, *extra: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    mission.add_arguments(p)
    return p.parse_args(["--frames", "45", "--window", "15", "--chunk", "20", "--resolution", "64x64",
                         "--queries", "1", "--query-source", "random", "--plot", str(tmp_path / "m.png"), *extra])


def test_mission_windows_match_a_directly_built_map(tmp_path):
    res = mission.run(_args(tmp_path))
    # independent: the same frames (route poses, renders, features in frame order) integrated sequentially
    city, hw = MissionCity(0), (64, 64)
    K = intrinsics_from_fov(90.0, *hw)
    g = torch.Generator().manual_seed(0)
    m = RayFrontsMap(map_config("throughput", {"depth_limit": 20.0}), 100, "bench")
    at_window_end = []
    for i, p in enumerate(city.poses(0, 45, 0.15)):
        r = city.render(p, K, hw)
        m.integrate(p, K, r.depth.astype(np.float32), r.rgb, torch.randn(100, 4, 4, generator=g).to(torch.float16))
        if (i + 1) % 15 == 0:
            st = m.stats()
            at_window_end.append((st["n_voxels"], st["n_frontiers"], st["n_rays"]))
    m.flush()
    st = m.stats()
    w = res["windows"]
    assert [x["frames"] for x in w] == [[0, 15], [15, 30], [30, 45]]
    assert [(x["n_voxels"], x["n_frontiers"], x["n_rays"]) for x in w] == at_window_end
    assert at_window_end[0][0] < at_window_end[-1][0]          # the map grows along the route
    assert (res["n_voxels"], res["n_frontiers"], res["n_rays"]) == (st["n_voxels"], st["n_frontiers"], st["n_rays"])
    assert abs(res["map_memory_mb"] * 2**20 - st["memory_bytes"]) <= 0.001 * 2**20
    assert res["bytes_per_voxel"] == round(st["memory_bytes"] / st["n_voxels"], 1)
    ratio = res["cpu_ms_per_frame_last_10pct"] / res["cpu_ms_per_frame_first_10pct"]   # of the rounded figures
    assert res["flat_cost_ratio"] == pytest.approx(ratio, rel=2e-3)
    for x in w:
        assert x["cpu_ms_per_frame"] > 0 and x["rss_mb"] > 0 and x["query_ms_p50"] > 0
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_mission_route_never_revisits_and_is_continuous():
    step, leg = 0.15, 100.0
    city = MissionCity(3, leg=leg)
    poses = city.poses(0, 1500, step)                           # the first two corners (225 m)
    xy = poses[:, :2, 3]
    d = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert np.allclose(d, step, atol=1e-6)                      # continuous at constant speed (arcs too)
    fwd = poses[:-1, :2, 2] / np.linalg.norm(poses[:-1, :2, 2], axis=1, keepdims=True)
    assert np.min(np.sum(fwd * np.diff(xy, axis=0) / d[:, None], axis=1)) > np.cos(np.deg2rad(20))  # looks ahead
    assert np.all(np.abs(poses[:, 2, 3] - 1.52) < 1e-9)         # eye 1.5 m above the road
    s = np.arange(0, 36000 * step, 3.0)                         # the hour-long route (5.4 km), every 3 m
    xy, _, _ = city.path(s)
    assert np.allclose(xy[:len(poses[::20])], poses[::20, :2, 3])
    assert np.allclose(np.linalg.norm(np.diff(xy, axis=0), axis=1), 3.0, atol=0.05)  # chords on arcs are shorter
    far_along = np.abs(s[:, None] - s[None, :]) >= 1.5 * leg
    gap = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=-1)
    assert gap[far_along].min() > 2 * 20.0                      # never back within two sensor ranges
