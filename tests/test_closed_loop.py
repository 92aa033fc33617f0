"""Closed-loop search planner: A* paths against an independent brute-force shortest path."""
import math

import numpy as np
from scipy.sparse import lil_matrix
from scipy.sparse.csgraph import dijkstra

from apps.closed_loop.planner import FREE, OCCUPIED, UNKNOWN, advance, astar, path_length


def _brute(states: np.ndarray, start, goal) -> float:
    """Dijkstra over all 8-neighbour moves whose cells (and cut corners) are free; goal may be unknown."""
    nx, ny = states.shape
    idx = np.arange(nx * ny).reshape(nx, ny)
    g = lil_matrix((nx * ny, nx * ny))
    ok = lambda c: 0 <= c[0] < nx and 0 <= c[1] < ny and (states[c] == FREE or (c == goal and states[c] == UNKNOWN))  # noqa: E731
    for i in range(nx):
        for j in range(ny):
            if states[i, j] != FREE:
                continue
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    n = (i + di, j + dj)
                    if (di or dj) and ok(n):
                        if di and dj and not (states[i + di, j] == FREE and states[i, j + dj] == FREE):
                            continue
                        g[idx[i, j], idx[n]] = math.hypot(di, dj)
    d = dijkstra(g.tocsr(), indices=idx[start])
    return float(d[idx[goal]])


def test_astar_matches_brute_force_and_stays_in_free_space():
    rng = np.random.default_rng(3)
    for _ in range(20):
        states = rng.choice([FREE, OCCUPIED, UNKNOWN], size=(14, 12), p=[0.7, 0.2, 0.1]).astype(np.int8)
        states[0, 0] = FREE
        goal = (13, 11)
        truth = _brute(states, (0, 0), goal)
        path = astar(states, (0, 0), goal)
        if math.isinf(truth):
            assert path is None
            continue
        assert path is not None and path[0] == (0, 0) and path[-1] == goal
        assert all(states[c] == FREE for c in path[:-1])
        assert math.isclose(path_length(path, 1.0), truth, rel_tol=1e-9)


def test_astar_refuses_occupied_goal_and_advance_clips_to_step():
    states = np.zeros((5, 5), np.int8)
    states[4, 4] = OCCUPIED
    assert astar(states, (0, 0), (4, 4)) is None
    path = astar(states, (0, 0), (0, 4))
    p = advance(path, np.zeros(2), 0.5, 1.0)
    assert np.allclose(p, [0.25, 1.25])


def test_robot_collision_and_pose_against_true_world():
    from apps.closed_loop.robot import Platform, camera_pose
    from synthetic_world import World

    w = World.generate(seed=0)
    car = w.instances_of(w.class_id("car"))[0]
    robot = Platform.make("ground")
    inside = np.array([car.center[0], car.center[1], 1.5])
    assert robot.collides(w, inside, inside)               # standing where the car is
    _, top = w.bounds
    sky = np.array([car.center[0], car.center[1], top[2] + 5.0])
    assert not Platform.make("drone").collides(w, sky, sky + [3.0, 0.0, 0.0])   # above every solid
    pose = camera_pose(np.array([0.0, 0.0, 1.5]), math.pi / 2)
    assert np.allclose(pose[:3, 2], [0, 1, 0], atol=1e-12) and np.isclose(np.linalg.det(pose[:3, :3]), 1.0)


def test_oracle_path_on_true_world_is_collision_free_and_spl_one():
    from apps.closed_loop.metrics import spl
    from apps.closed_loop.robot import Platform, true_free_grid
    from synthetic_world import World

    w = World.generate(seed=0)
    robot = Platform.make("ground")
    car = w.instances_of(w.class_id("car"))[0]
    c = np.asarray(car.center, float)[:2]
    states, origin = true_free_grid(w, robot, c - 12.0, c + 12.0, 0.5)
    free = np.argwhere(states == FREE)
    assert len(free) > 0 and (states == OCCUPIED).any()     # the car occupies cells
    start, goal = tuple(free[0]), tuple(free[-1])
    path = astar(states, start, goal)
    assert path is not None
    pts = [np.r_[origin + (np.asarray(p) + 0.5) * 0.5, 1.5] for p in path]
    assert not any(robot.collides(w, a, b) for a, b in zip(pts[:-1], pts[1:], strict=True))
    length = path_length(path, 0.5)
    assert spl(True, length, length) == 1.0 and spl(False, length, length) == 0.0


def test_frontier_episode_moves_without_touching_the_true_world():
    from apps.closed_loop.episode import frontier_episode
    from apps.closed_loop.robot import Platform
    from synthetic_world import World

    w = World.generate(3)
    start = w.trajectory("ground", 2, seed=3)[0][:3, 3]
    r = frontier_episode(w, start[:2], steps=10)
    assert not r["collided"] and r["path_m"] > 0.5
    robot = Platform.make("ground")
    # independent re-check of every move against the exact geometry, with a finer sweep
    assert not any(robot.collides(w, a, b, spacing=0.03) for a, b in r["moves"])
    r2 = frontier_episode(w, start[:2], steps=10)
    assert np.array_equal(r["path"], r2["path"])            # deterministic
