"""Semantic Poses (``sem-poses``, the paper's image-level baseline) does not collapse into
frontier exploration: in a constructed world whose target — a large water tower 22 m away,
beyond the 10 m depth limit — is seen from afar, it turns toward the camera pose whose
image-level feature stands out for the target, while frontier exploration, on the same
views (same sensor and encoder draws), keeps to its information-gain goal."""
from __future__ import annotations

import math

import numpy as np

TOWER_XY = np.array([28.0, 0.0])


def _bearing_deg(a: np.ndarray, b: np.ndarray) -> float:
    d = np.asarray(b[:2], np.float64) - np.asarray(a[:2], np.float64)
    return math.degrees(math.atan2(d[1], d[0]))


def test_sem_poses_heads_for_a_target_seen_from_afar_where_frontier_does_not():
    from apps.closed_loop.episode import LoopSettings, Trace, run_episode
    from apps.closed_loop.evaluate import SearchEvalConfig
    from apps.closed_loop.missions import Mission
    from apps.closed_loop.sensing import EdgeChain
    from synthetic_world import Box, Part, World

    parts = [Part(Box((0, 0, -0.5), (120, 120, 0.5)), "ground", "ground"),
             Part(Box((*TOWER_XY, 15.0), (6, 6, 15)), "water tower", "tower"),
             Part(Box((-8, 6, 2), (1.5, 1.5, 2)), "building", "b0"),
             Part(Box((-8, -6, 2), (1.5, 1.5, 2)), "building", "b1")]
    w = World.from_primitives(parts)
    tower = w.instances_of(w.class_id("water tower"))
    start = np.array([0.0, 0.0, 1.5])
    mission = Mission("landmark", "water tower", tower, 1, start, 10.0, 5.0, 8, 12.0)
    cfg = SearchEvalConfig(resolution=96)            # the evaluation's defaults: sim encoder, realistic sensor
    chain = EdgeChain(w, cfg.sensor_config(0), fit_at=start)
    settings = LoopSettings(background=cfg.background, depth_limit_m=10.0)
    runs = {}
    for policy in ("frontier", "sem-poses"):
        trace = Trace()
        row = run_episode(w, mission, policy, settings, chain=chain, trace=trace)
        assert not row["collided"] and row["steps"] >= 6
        runs[policy] = trace
    fr, sp = runs["frontier"], runs["sem-poses"]
    assert not any(why.startswith("pose") for why in fr.why)
    pose_steps = [i for i, why in enumerate(sp.why) if why.startswith("pose")]
    assert pose_steps, sp.why                                    # the poses' evidence led somewhere
    for i in pose_steps:                                         # ... toward the tower
        at, goal = sp.positions[i], sp.goals[i]
        off = abs((_bearing_deg(at, goal) - _bearing_deg(at, TOWER_XY) + 180.0) % 360.0 - 180.0)
        assert off < 45.0, (i, at, goal, off)
        assert np.linalg.norm(goal - fr.goals[i]) > 2.0         # not the frontier's goal
    # same views until the first pose decision (same draws), different paths after it
    first = pose_steps[0]
    assert all(np.allclose(a, b) for a, b in zip(fr.positions[:first + 1], sp.positions[:first + 1], strict=True))
    assert np.linalg.norm(fr.positions[-1][:2] - sp.positions[-1][:2]) > 1.0
    assert np.linalg.norm(sp.positions[-1][:2] - TOWER_XY) < np.linalg.norm(fr.positions[-1][:2] - TOWER_XY)


def test_pose_goal_takes_probability_then_margin_outliers():
    """``_pose_goal``: a pose whose probability reaches ``min_score`` leads; else the pose with
    the highest margin z-score if it reaches the cut; else nothing (frontier exploration)."""
    from apps.closed_loop.policies import _pose_goal
    from apps.closed_loop.world_model import Observation

    goals = [({"position": [10.0, 0.0, 0.0]}, np.array([20, 0]), 10.0),
             ({"position": [0.0, 10.0, 0.0]}, np.array([0, 20]), 10.0)]
    east, north = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    o = np.zeros(3)

    def obs(poses):
        return Observation([], [], np.zeros((1, 1)), np.zeros(2), 0.5, poses)

    d = _pose_goal(obs([(o, east, 0.5, 0.0), (o, north, 0.1, 9.0)]), goals, 0.3, 3.5)
    assert d is not None and list(d.goal_xy) == [10.0, 0.0] and d.why.startswith("pose 0.50")
    d = _pose_goal(obs([(o, east, 0.1, 1.0), (o, north, 0.1, 4.0)]), goals, 0.3, 3.5)
    assert d is not None and list(d.goal_xy) == [0.0, 10.0] and d.why == "pose z 4.0"
    assert _pose_goal(obs([(o, east, 0.1, 1.0), (o, north, 0.1, 3.0)]), goals, 0.3, 3.5) is None
