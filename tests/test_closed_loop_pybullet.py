"""The closed loop in a world this project did not write: a short ``rayfronts`` episode in a
pybullet scene, with the evaluation's default conditions (realistic depth sensor, simulated
ViT-like encoder, PCA basis from the robot's first views, generic background phrases),
finds the object it is sent for — checked against the scene's true instances — without a
false find or a collision (true collisions from pybullet's collision shapes)."""
from __future__ import annotations

import math

import numpy as np


def test_short_episode_in_a_pybullet_scene_finds_an_object():
    from apps.closed_loop.episode import LoopSettings, run_episode
    from apps.closed_loop.evaluate import SearchEvalConfig
    from apps.closed_loop.missions import DISTANCES, Mission, oracle_tour, truth_grid
    from apps.closed_loop.robot import Platform
    from apps.closed_loop.sensing import EdgeChain
    from synthetic_world.pybullet_world import PybulletWorld

    w = PybulletWorld.generate(0)
    robot = Platform.make("ground")
    target = "teddy bear"
    insts = w.instances_of(w.class_id(target))
    assert len(insts) == 2
    c = insts[0].center
    tg = truth_grid(w, robot, c[:2] - 12.0, c[:2] + 12.0, 0.5)
    reach, declare = DISTANCES["object"]
    for k in range(8):                            # a free start 7 m from the bear with a true path to it
        start = np.r_[c[:2] + 7.0 * np.array([math.cos(k * math.pi / 4), math.sin(k * math.pi / 4)]), robot.cruise_z]
        if tg.ok[tg.cell_of(start)]:
            length, pts, _ = oracle_tour(tg, start, insts, 1, reach)
            if math.isfinite(length):
                break
    else:
        raise AssertionError("no free start near the teddy bear")
    mission = Mission("object", target, insts, 1, start, reach, declare, 8, length,
                      np.c_[pts, np.full(len(pts), robot.cruise_z)])
    cfg = SearchEvalConfig(world="pybullet", resolution=96)
    assert (cfg.sensor, cfg.encoder, cfg.pca_fit, cfg.background) == ("realistic", "sim", "first_views", "generic")
    chain = EdgeChain(w, cfg.sensor_config(0), fit_at=start)
    row = run_episode(w, mission, "rayfronts", LoopSettings(background=cfg.background, depth_limit_m=10.0),
                      chain=chain)
    assert row["success"] and row["found"] == 1, row
    assert row["false_finds"] == 0 and not row["collided"]
    assert [d["verdict"] for d in row["declarations"]] == ["find"]
    assert 0.0 < row["spl"] <= 1.0 and row["steps"] <= 8
    w.close()
