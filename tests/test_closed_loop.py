"""Closed-loop search: planner paths against an independent brute-force shortest path, the
robot against the true world, every policy, the eval command's outputs."""
import argparse
import math

import numpy as np
import pytest
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
    assert length == pytest.approx(_brute(states, start, goal) * 0.5, rel=1e-9)   # the shortest, by brute force
    assert spl(True, length, length) == 1.0 and spl(False, length, length) == 0.0
    assert spl(True, length, 1.25 * length) == pytest.approx(0.8) and spl(True, length, 0.5 * length) == 1.0


# ----------------------------------------------------------------- the closed loop itself
@pytest.fixture(scope="module")
def loop():
    """World 3, its edge chain at 96 px, one car mission (shared by the episode tests)."""
    from apps.closed_loop.missions import make_mission
    from apps.closed_loop.robot import Platform
    from apps.closed_loop.sensing import EdgeChain, SensorConfig
    from synthetic_world import World

    w = World.generate(3)
    chain = EdgeChain(w, SensorConfig(resolution=96, label_stride=4))
    mission = make_mission(w, Platform.make("ground"), "object", "car", np.random.default_rng(3), budget_steps=8)
    return w, chain, mission


def test_edge_chain_basis_keeps_every_class_apart(loop):
    """The closed loop's PCA basis (fitted per world) keeps each of the world's classes: a cell
    showing one class, compressed and decompressed, reads as that class and no other (cosine
    to its own name ~1, brute force over all names). A basis fitted on views alone leaves
    unseen classes to arbitrary directions (world 3: at 96 px its rock read as road, at 224 px
    its water tower as the radio tower)."""
    import torch

    from edge.runtime import compress_features

    w, chain, _ = loop
    names = chain.encoder.table.float()                                   # (K, C) unit rows
    cells = chain.class_cells().float()
    assert cells.shape == names.shape
    y = np.asarray(compress_features(chain.pca, cells.T.reshape(cells.shape[1], -1, 1).numpy()))
    back = torch.as_tensor(np.asarray(chain.pca.decompress(y.reshape(y.shape[0], -1).T)), dtype=torch.float32)
    cos = torch.nn.functional.normalize(back, dim=1) @ names.T
    for k, name in enumerate(w.classes):
        assert int(cos[k].argmax()) == k, (name, w.classes[int(cos[k].argmax())])
        assert float(cos[k, k]) > 0.999, name


def test_navfield_paths_stay_in_traversable_known_free_cells():
    """Paths only cross cells that are FREE with no occupied/unknown cell within the body's
    clearance (checked cell by cell here, against the states directly), and lengths equal an
    independent Dijkstra."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.planner import path_to

    rng = np.random.default_rng(5)
    states = np.where(rng.random((40, 40)) < 0.04, OCCUPIED, FREE).astype(np.int8)
    states[:, 30:] = UNKNOWN
    states[18:22, 18:22] = FREE
    nav = NavField(states, np.zeros(2), 0.5, np.array([10.0, 10.0, 1.5]), 0.4)
    reach = np.argwhere(np.isfinite(nav.dist_m))
    assert len(reach) > 100
    for c in reach[rng.choice(len(reach), 30, replace=False)]:
        for cell in path_to(nav.pred, tuple(c))[1:]:
            i, j = cell
            near = states[max(0, i - 1):i + 2, max(0, j - 1):j + 2]      # clearance 0.9 m = the 3x3 block
            assert states[cell] == FREE and (near == FREE).all(), cell
        assert math.isclose(nav.dist_m[tuple(c)], _brute(np.where(nav.ok, FREE, OCCUPIED).astype(np.int8),
                                                          nav.start, tuple(c)) * 0.5, rel_tol=1e-9)
    cell, _, _ = nav.nearest_reachable(np.array([17.0, 10.0]))            # into the unknown: stops before it
    assert states[tuple(cell)] == FREE and cell[1] < 30


def test_ray_policies_follow_an_outlier_ray_when_probabilities_are_zero():
    """A far target: every goal's probability ~0. The ray policies head for the goal whose
    ray stands out (ray_z >= MIN_RAY_Z), even past a nearer goal with more unknown volume;
    below the bar, and for frontier exploration, the gain per path decides. A held goal
    chosen without evidence is dropped once evidence appears."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import MIN_RAY_Z, PolicyState, explore
    from apps.closed_loop.world_model import Observation

    states = np.full((60, 60), FREE, np.int8)
    at = np.array([5.0, 5.0, 1.5])

    def goal(x, y, gain, z):
        return dict(position=[x, y, 1.5], score=1e-12, gain_m3=gain, ray_z=z, target="water tower")

    near, far = goal(12.0, 5.0, 30.0, 0.0), goal(5.0, 25.0, 2.0, MIN_RAY_Z + 1.0)
    nav = NavField(states, np.zeros(2), 0.5, at, 0.4)
    obs = Observation([], [near, far], states, np.zeros(2), 0.5)
    for name, want in [("rayfronts", far), ("unidirectional", far), ("spherical", far), ("frontier", near)]:
        d = explore(name, obs, nav, PolicyState())
        assert np.allclose(d.goal_xy, want["position"][:2]), name
    weak = dict(far, ray_z=MIN_RAY_Z - 0.5)
    d = explore("rayfronts", Observation([], [near, weak], states, np.zeros(2), 0.5), nav, PolicyState())
    assert np.allclose(d.goal_xy, near["position"][:2]) and d.why.startswith("frontier")
    state = PolicyState()
    explore("rayfronts", Observation([], [near, weak], states, np.zeros(2), 0.5), nav, state)   # holds `near`
    d = explore("rayfronts", obs, nav, state)                                                    # evidence appears
    assert np.allclose(d.goal_xy, far["position"][:2]) and d.why.startswith("ray z")


def test_ray_policy_leaves_evidence_it_has_passed_for_the_fresh_outlier_ahead():
    """Close to a tall landmark the camera loses its top: the frontier that kept the strong
    rays (probability 1) lies behind the robot, which stands on along those rays. RayFronts
    follows the fresh, weaker evidence next to it (an outlier ray, probability ~0) rather
    than the shortest-path goal somewhere ahead along the spent rays, and holds that goal
    the next step (the spent goal's score does not count as a better goal)."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import MIN_RAY_Z, PolicyState, explore
    from apps.closed_loop.world_model import Observation

    states = np.full((140, 60), FREE, np.int8)
    at = np.array([40.0, 5.0, 1.5])

    def goal(x, y, score, z, gain=1.0):
        return dict(position=[x, y, 1.5], score=score, gain_m3=gain, ray_z=z, heading_rad=0.0, target="water tower")

    spent = goal(5.0, 5.0, 1.0, 1e6)                 # 35 m behind, its rays point at the robot's way
    fresh = goal(55.0, 4.0, 1e-9, MIN_RAY_Z + 2.0)   # 15 m ahead
    side = goal(42.0, 17.0, 1e-9, 0.0, gain=50.0)    # 12 m away, also ahead along the spent rays
    nav = NavField(states, np.zeros(2), 0.5, at, 0.4)
    obs = Observation([], [spent, fresh, side], states, np.zeros(2), 0.5)
    state = PolicyState()
    d = explore("rayfronts", obs, nav, state)
    assert np.allclose(d.goal_xy, fresh["position"][:2]) and d.why.startswith("ray z"), d
    d = explore("rayfronts", obs, nav, state)
    assert np.allclose(d.goal_xy, fresh["position"][:2]) and d.why == "held goal", d
    # not passed (the robot stands beside the spent goal's rays, not on along them): it still leads
    at2 = np.array([8.0, 25.0, 1.5])
    nav2 = NavField(states, np.zeros(2), 0.5, at2, 0.4)
    d = explore("rayfronts", obs, nav2, PolicyState())
    assert d.why.startswith("rays 1.00") or d.why == "beyond rays", d


def _open_field(at: np.ndarray) -> tuple:
    """A 70 m × 70 m field of free 0.5 m cells (origin 0) and the robot's NavField at ``at``."""
    from apps.closed_loop.navigation import NavField

    states = np.full((140, 140), FREE, np.int8)
    return states, NavField(states, np.zeros(2), 0.5, at, 0.4)


def _far_target_goal(x: float, y: float, z: float, heading: float | None = None) -> dict:
    """A look-next goal for a far water tower at (x, y): probability ~0, ``ray_z`` ``z``, its
    rays' yaw ``heading`` (None: no rays)."""
    return dict(position=[x, y, 1.5], score=1e-12, gain_m3=1.0, ray_z=z, heading_rad=heading,
                target="water tower")


def test_ray_policy_keeps_the_strongest_bearing_against_weaker_outliers_elsewhere():
    """A far target's rays keep their bearing and grow stronger; noise outliers jump and stay
    weak. Once strong rays pointed +x, a weaker outlier pointing elsewhere is not followed:
    an outlier agreeing with +x is, else the nearest goal ahead along +x. A stronger ray
    anywhere is followed (and becomes the bearing); a declaration forgets the bearing."""
    from apps.closed_loop.policies import MIN_RAY_Z, PolicyState, confirm, explore
    from apps.closed_loop.world_model import Observation

    at = np.array([20.0, 20.0, 1.5])
    states, nav = _open_field(at)
    goal = _far_target_goal

    def obs(*goals):
        return Observation([], list(goals), states, np.zeros(2), 0.5)

    strong = goal(60.0, 21.0, 1e3, 0.0)                     # 40 m along +x
    noise = goal(20.0, 40.0, MIN_RAY_Z + 10.0, np.pi / 2)  # 20 m along +y, nearer
    ahead = goal(45.0, 18.0, 0.0)                           # 25 m along +x, no rays
    state = PolicyState()
    assert np.allclose(explore("rayfronts", obs(strong, ahead), nav, state).goal_xy, strong["position"][:2])
    state.goal = None                                       # the strong goal was explored: it is gone
    d = explore("rayfronts", obs(noise, ahead), nav, state)
    assert np.allclose(d.goal_xy, ahead["position"][:2]) and d.why.startswith("bearing"), d
    d = explore("rayfronts", obs(noise, ahead), nav, PolicyState())      # no memory: the outlier leads
    assert np.allclose(d.goal_xy, noise["position"][:2]) and d.why.startswith("ray z"), d
    agreeing = goal(40.0, 30.0, MIN_RAY_Z + 1.0, 0.4)        # weaker still, but 23° from +x
    state.goal = None
    d = explore("rayfronts", obs(noise, agreeing, ahead), nav, state)
    assert np.allclose(d.goal_xy, agreeing["position"][:2]) and d.why.startswith("ray z"), d
    stronger = dict(noise, ray_z=2e3)
    state.goal = None
    d = explore("rayfronts", obs(stronger, ahead), nav, state)
    assert np.allclose(d.goal_xy, stronger["position"][:2]) and state.bearing == (np.pi / 2, 2e3), d
    car = dict(id=1, target="car", box_min=[20.5, 20.5, 0.0], box_max=[21.0, 21.0, 1.5])
    d = confirm(Observation([car], [], states, np.zeros(2), 0.5), nav, at, state, reach_m=3.0)
    assert d is not None and d.declare is car and state.bearing is None


def test_ray_policy_goes_on_past_its_bearing_rather_than_after_a_weaker_outlier_elsewhere():
    """The robot has passed every goal whose strong rays set the bearing (+x), and no goal
    lies ahead of it along +x; a weak outlier pointing elsewhere is left. It drives on past
    the passed evidence (a goal ahead along those rays), not after the outlier (development
    seed 21: 200 m back toward a weak ray of the radio tower's, the budget spent)."""
    from apps.closed_loop.policies import MIN_RAY_Z, PolicyState, explore
    from apps.closed_loop.world_model import Observation

    states, nav = _open_field(np.array([20.0, 20.0, 1.5]))
    goal = _far_target_goal

    spent = goal(10.0, 20.0, 1e3, 0.0)                      # 10 m behind the robot, rays along +x
    noise = goal(20.0, 40.0, MIN_RAY_Z + 10.0, np.pi / 2)  # weak, along +y
    side = goal(26.0, 29.0, 0.0)          # 56° off +x from the robot, 29° off it from the spent goal
    for name in ("rayfronts", "unidirectional", "spherical"):
        state = PolicyState()
        d = explore(name, Observation([], [spent, noise, side], states, np.zeros(2), 0.5), nav, state)
        assert state.bearing == (0.0, 1e3)                 # remembered from the passed goal's rays
        assert np.allclose(d.goal_xy, side["position"][:2]) and d.why.startswith("beyond bearing"), (name, d)


def test_every_episode_gets_the_runs_sem_poses_cut():
    """``LoopSettings.policy_state`` (the one place single-robot and fleet episodes build a
    policy's memory) carries the run's ``--sem-poses-min-z``, else the module default."""
    from apps.closed_loop.evaluate import SearchEvalConfig
    from apps.closed_loop.policies import SEM_POSES_MIN_Z

    assert SearchEvalConfig(sem_poses_min_z=2.5).loop_settings().policy_state().pose_min_z == 2.5
    assert SearchEvalConfig().loop_settings().policy_state().pose_min_z == SEM_POSES_MIN_Z != 2.5


def test_an_approach_that_stalled_is_not_driven_back_to():
    """A found instance behind a wall: the approach leads to the wall's foot (B), where the
    robot gets no nearer. Sent elsewhere and back, it does not drive to B again (before, a
    robot shuttled between B and the exploration goal it took there for 70 steps), but an
    approach that leads somewhere new is still taken."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import PolicyState, confirm
    from apps.closed_loop.world_model import Observation

    states = np.full((60, 60), FREE, np.int8)
    states[30:32, :] = OCCUPIED                                   # a wall across x = 15-16 m
    inst = dict(id=7, target="car", box_min=[20.0, 10.0, 0.0], box_max=[21.0, 11.0, 1.5])
    obs = Observation([inst], [], states, np.zeros(2), 0.5)
    state = PolicyState()

    def at_(x, y):
        at = np.array([x, y, 1.5])
        return at, NavField(states, np.zeros(2), 0.5, at, 0.4)

    a, nav_a = at_(10.25, 10.25)
    d = confirm(obs, nav_a, a, state, reach_m=3.0)
    assert d is not None and d.why.startswith("approach"), d
    b = nav_a.origin + (np.asarray(d.goal_cell) + 0.5) * nav_a.cell
    assert 13.0 < b[0] < 15.0, b                                  # the wall's foot
    b, nav_b = at_(*b)
    assert confirm(obs, nav_b, b, state, reach_m=3.0) is None     # no nearer from there
    assert confirm(obs, nav_a, a, state, reach_m=3.0) is None     # and not sent back to it
    wall = states.copy()
    states[30, :] = FREE                                          # the wall's near face flickers free:
    a, nav_a = at_(10.25, 10.25)                                  # its foot one cell (0.5 m) nearer is
    assert confirm(Observation([inst], [], states, np.zeros(2), 0.5), nav_a, a, state, reach_m=3.0) is None
    states[:] = wall                                              # the same spot (no back and forth)
    states[30:32, 18:24] = FREE                                   # a gate opens in the wall
    a, nav_a = at_(10.25, 10.25)
    d = confirm(Observation([inst], [], states, np.zeros(2), 0.5), nav_a, a, state, reach_m=3.0)
    assert d is not None and d.why.startswith("approach"), d
    assert np.linalg.norm(nav_a.origin + (np.asarray(d.goal_cell) + 0.5) * nav_a.cell - b[:2]) > 1.0


def test_a_found_object_the_robot_can_get_no_nearer_is_declared_from_there():
    """A large object whose named part lies behind its own near side: the robot stands at the
    wall's foot, as near as the map lets it. Within STALL_DECLARE reaches of the mapped box it
    declares from there; farther, it does not (and remembers the stall)."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import STALL_DECLARE, PolicyState, confirm
    from apps.closed_loop.world_model import Observation

    states = np.full((60, 60), FREE, np.int8)
    states[30:32, :] = OCCUPIED                                   # the near side across x = 15-16 m
    at = np.array([14.75, 10.25, 1.5])                            # its foot: no reachable cell nearer
    nav = NavField(states, np.zeros(2), 0.5, at, 0.4)
    reach = 3.0
    for box_x, declared in ((14.75 + STALL_DECLARE * reach - 0.1, True), (14.75 + STALL_DECLARE * reach + 0.1, False)):
        inst = dict(id=7, target="statue", box_min=[box_x, 9.0, 0.0], box_max=[box_x + 4.0, 12.0, 6.0])
        state = PolicyState()
        d = confirm(Observation([inst], [], states, np.zeros(2), 0.5), nav, at, state, reach_m=reach)
        if declared:
            assert d is not None and d.declare is inst and "no nearer" in d.why, d
        else:
            assert d is None and len(state.stalled[7]) == 1, (d, state.stalled)


def test_a_found_instance_is_declared_only_once_found_at_enough_map_updates():
    """Within reach of a found instance, the robot stays (its own cell, no path) and looks
    again until the instance was found at MIN_OBSERVATIONS map updates, then declares it; a
    look-alike found at one update whose fused views then drop it is never declared; beyond
    reach, one found once is approached as before; an instance without the field (an older
    mapper) is trusted."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import MIN_OBSERVATIONS, PolicyState, confirm
    from apps.closed_loop.world_model import Observation

    assert MIN_OBSERVATIONS >= 2
    states = np.full((80, 80), FREE, np.int8)
    at = np.array([10.25, 10.25, 1.5])
    nav = NavField(states, np.zeros(2), 0.5, at, 0.4)

    def inst(x: float, seen: int | None) -> dict:
        d = dict(id=4, target="statue", box_min=[x, 10.0, 0.0], box_max=[x + 0.5, 10.5, 0.5])
        return d if seen is None else d | {"observations": seen}

    state = PolicyState()
    for seen in range(1, MIN_OBSERVATIONS + 1):
        d = confirm(Observation([inst(13.0, seen)], [], states, np.zeros(2), 0.5), nav, at, state, reach_m=5.0)
        assert d is not None
        if seen < MIN_OBSERVATIONS:
            assert d.declare is None and tuple(d.goal_cell) == nav.start and d.why.startswith("look again"), d
        else:
            assert d.declare is not None and d.declare["id"] == 4, d
    assert confirm(Observation([], [], states, np.zeros(2), 0.5), nav, at, PolicyState(), reach_m=5.0) is None
    d = confirm(Observation([inst(30.0, 1)], [], states, np.zeros(2), 0.5), nav, at, PolicyState(), reach_m=5.0)
    assert d is not None and d.why.startswith("approach") and tuple(d.goal_cell) != nav.start, d
    d = confirm(Observation([inst(13.0, None)], [], states, np.zeros(2), 0.5), nav, at, PolicyState(), reach_m=5.0)
    assert d is not None and d.declare is not None, d


def test_ray_policy_does_not_follow_a_ray_crossing_back_behind_it():
    """Rays cast close together and nearly parallel cross near where they were cast: such an
    estimate behind the robot (along its evidence's heading) is not driven back to; one
    ahead is."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import PolicyState, explore
    from apps.closed_loop.world_model import Observation

    states = np.full((140, 60), FREE, np.int8)
    at = np.array([40.0, 5.0, 1.5])
    nav = NavField(states, np.zeros(2), 0.5, at, 0.4)

    def goal(x, y, score, heading=None):
        return dict(position=[x, y, 1.5], score=score, gain_m3=1.0, ray_z=0.0, heading_rad=heading,
                    target="water tower")

    goals = [goal(30.0, 5.0, 1.0, 0.0), goal(20.0, 5.0, 0.0), goal(38.0, 20.0, 0.0)]   # evidence passed, +x
    for est, want in [((25.0, 5.0), None), ((60.0, 20.0), (38.0, 20.0))]:
        obs = Observation([], goals, states, np.zeros(2), 0.5,
                          estimates=[dict(position=[*est, 20.0], score=1.0, target="water tower")])
        d = explore("rayfronts", obs, nav, PolicyState())
        if want is None:
            assert d.why != "toward estimate", d
        else:
            assert d.why == "toward estimate" and np.allclose(d.goal_xy, want), d


def test_ray_policy_counts_the_unknown_gap_to_a_goal():
    """Of two goals with the same evidence, the one behind unknown space — a short path to
    the reachable cell nearest it, then a long gap — is farther than a reachable one with a
    longer path (the robot would stop at the gap's edge and set it aside)."""
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.policies import PolicyState, explore
    from apps.closed_loop.world_model import Observation

    states = np.full((100, 60), FREE, np.int8)
    states[24:, :30] = UNKNOWN                         # x > 12 m, y < 15 m: not mapped yet
    at = np.array([5.0, 5.0, 1.5])
    nav = NavField(states, np.zeros(2), 0.5, at, 0.4)

    def goal(x, y):
        return dict(position=[x, y, 1.5], score=1.0, gain_m3=1.0, ray_z=0.0, target="water tower")

    behind, open_ = goal(20.0, 5.0), goal(5.0, 17.0)
    _, path_b, gap_b = nav.nearest_reachable(np.array(behind["position"][:2]))
    _, path_o, gap_o = nav.nearest_reachable(np.array(open_["position"][:2]))
    assert path_b < path_o and gap_o < 0.5 and path_b + gap_b > path_o + gap_o   # the premise
    d = explore("rayfronts", Observation([], [behind, open_], states, np.zeros(2), 0.5), nav, PolicyState())
    assert np.allclose(d.goal_xy, open_["position"][:2]), d


def _shifted(a: np.ndarray, di: int, dj: int) -> np.ndarray:
    """``out[i, j] = a[i + di, j + dj]`` (False outside ``a``)."""
    out = np.zeros_like(a)
    nx, ny = a.shape
    out[max(0, -di):nx - max(0, di), max(0, -dj):ny - max(0, dj)] = \
        a[max(0, di):nx - max(0, -di), max(0, dj):ny - max(0, -dj)]
    return out


#: 16-neighbour moves (one per undirected pair) -> the cells each sweeps besides its two ends
_MOVES16 = {(1, 0): [], (0, 1): [], (1, 1): [(1, 0), (0, 1)], (1, -1): [(1, 0), (0, -1)],
            (2, 1): [(1, 0), (1, 1)], (1, 2): [(0, 1), (1, 1)], (2, -1): [(1, 0), (1, -1)],
            (1, -2): [(0, -1), (1, -1)]}
#: a 16-neighbour lattice path is at most 1/cos(26.57°/2) longer than the straight line
#: (the widest gap between its directions); an 8-neighbour one 1/cos(22.5°)
_STRETCH16, _STRETCH8 = 1.0 / math.cos(math.atan(0.5) / 2), 1.0 / math.cos(math.pi / 8)


def _true_shortest_m(world, robot, mission, clearances: tuple, cell: float = 0.25) -> list[float]:
    """Shortest distances (m) from the mission's start to within ``reach_m`` (xy) of one of
    its instances, computed here from the world's exact geometry and nothing of the planner:
    a ``cell`` m grid whose cells are solid when any of 11 heights from the body's ground
    clearance to the camera is inside a solid (``labels_at``), each free cell's distance to
    the nearest solid cell (scipy's exact Euclidean distance transform), then scipy's
    Dijkstra over 16-neighbour moves between cells with more than each of ``clearances`` (m)."""
    from scipy.ndimage import distance_transform_edt
    from scipy.sparse import coo_matrix

    from apps.closed_loop.robot import GROUND_CLEARANCE_M

    start = np.asarray(mission.start[:2], np.float64)
    lo = np.minimum(start, np.min([i.aabb_min[:2] for i in mission.instances], 0)) - 10.0
    hi = np.maximum(start, np.max([i.aabb_max[:2] for i in mission.instances], 0)) + 10.0
    n = np.ceil((hi - lo) / cell).astype(int)
    xs, ys = (lo[k] + (np.arange(n[k]) + 0.5) * cell for k in range(2))
    pts = np.stack(np.meshgrid(xs, ys, np.linspace(GROUND_CLEARANCE_M, robot.cruise_z, 11), indexing="ij"), -1)
    solid = (world.labels_at(pts.reshape(-1, 3)) != 0).reshape(pts.shape[:3]).any(2)
    clear = distance_transform_edt(~solid) * cell
    goal = np.zeros(solid.shape, bool)
    for inst in mission.instances:
        dx = np.maximum(np.maximum(inst.aabb_min[0] - xs, 0.0), xs - inst.aabb_max[0])
        dy = np.maximum(np.maximum(inst.aabb_min[1] - ys, 0.0), ys - inst.aabb_max[1])
        goal |= np.hypot(dx[:, None], dy[None, :]) <= mission.reach_m
    s = tuple(np.floor((start - lo) / cell).astype(int))
    idx = np.arange(solid.size).reshape(solid.shape)
    out = []
    for c in clearances:
        ok = clear > c
        ok[s] = True                                       # the robot stands there
        rows, cols, lengths = [], [], []
        for (di, dj), via in _MOVES16.items():
            valid = ok & _shifted(ok, di, dj)
            for vi, vj in via:
                valid &= _shifted(ok, vi, vj)
            rows.append(idx[valid])
            cols.append(idx[valid] + di * solid.shape[1] + dj)
            lengths.append(np.full(int(valid.sum()), math.hypot(di, dj) * cell))
        g = coo_matrix((np.concatenate(lengths), (np.concatenate(rows), np.concatenate(cols))), shape=(idx.size,) * 2)
        d = dijkstra(g.tocsr(), directed=False, indices=idx[s]).reshape(solid.shape)
        out.append(float(d[goal & ok].min()))
    return out


def test_oracle_drives_the_true_shortest_path(loop):
    """The oracle's driven path and the mission's ``shortest_m`` (SPL's reference for every
    policy) against a shortest path computed independently of the oracle's planner
    (:func:`_true_shortest_m`). Bounds: below, the path through every cell with more than the
    body's radius less one cell of clearance (all the body can stand in), over the
    16-neighbour lattice's stretch, less 0.5 m (start and goal cells); above, the oracle's
    8-neighbour path on its 0.5 m cells is at most 1/cos(22.5°) longer than the path through
    cells with more than the oracle's inflated body (radius + 0.375 m) plus one cell of
    clearance, plus 1 m (its goal lies 0.5 m inside ``reach_m``, start and goal cells)."""
    import dataclasses

    from apps.closed_loop.episode import LoopSettings, run_episode
    from apps.closed_loop.robot import Platform

    w, chain, mission = loop
    robot = Platform.make("ground")
    mission = dataclasses.replace(mission, budget_steps=200)
    r = run_episode(w, mission, "oracle", LoopSettings())
    assert r["success"] and not r["collided"] and r["spl"] == pytest.approx(1.0, abs=1e-9)
    lo, hi = _true_shortest_m(w, robot, mission, (robot.radius - 0.25, robot.radius + 0.375 + 0.25))
    assert lo > 10.0 and math.isfinite(hi), (lo, hi)
    for what, m in (("driven path", r["path_m"]), ("mission.shortest_m", mission.shortest_m)):
        assert lo / _STRETCH16 - 0.5 <= m <= _STRETCH8 * hi + 1.0, (what, m, lo, hi)


def test_declarations_name_the_true_object_a_false_find_was(loop):
    """A declaration's row: 'find' at a true target from within reach, 'false' at another
    class's instance, with the world's nearest object (its class, id, distance to its box)
    checked against every instance by brute force; the eval table lists the false one."""
    from apps.closed_loop.episode import _check_declaration, _declaration_row, _Run
    from apps.closed_loop.evaluate import table_markdown
    from apps.closed_loop.missions import box_distance

    w, _, mission = loop
    car = mission.instances[0]
    other = next(i for i in w.instances if w.classes[i.class_id] not in ("car", "ground", "road"))
    run = _Run(np.asarray(car.center, np.float64))
    rows = []
    for inst in (car, other):
        at = np.asarray(inst.center, np.float64)
        d = {"id": inst.id, "centroid": [float(v) for v in inst.center]}
        verdict = _check_declaration(d, mission, at, run.counted, 0.5)
        rows.append(_declaration_row(w, d, verdict, run))
    assert [r["verdict"] for r in rows] == ["find", "false"]
    for r in rows:
        dist = [box_distance(np.asarray(r["centroid"]), i.aabb_min, i.aabb_max) for i in w.instances]
        vol = [float(np.prod(np.asarray(i.aabb_max) - np.asarray(i.aabb_min))) for i in w.instances]
        best = w.instances[int(np.lexsort((vol, dist))[0])]
        assert r["nearest_m"] == pytest.approx(min(dist), abs=0.01) and r["nearest_id"] == best.id
        assert r["nearest_class"] == w.classes[best.class_id]
    assert rows[1]["nearest_m"] == 0.0          # the centre of its own box
    doc = {"policies": {}, "episodes": [{"seed": 3, "policy": "rayfronts", "target": "car", "declarations": rows}]}
    md = table_markdown(doc)
    assert "False finds" in md and f"{w.classes[other.class_id]} #{other.id}" in md
    assert f"car #{car.id}" not in md


def test_a_false_find_inside_a_site_names_the_object_not_the_site():
    """A declaration inside a small object's box that lies within a large one (a duck on the
    pybullet monastery's site, whose box spans ±60 m) names the object; outside every box,
    the nearest box."""
    from types import SimpleNamespace

    from apps.closed_loop.episode import _declaration_row, _Run

    site = SimpleNamespace(id=1, class_id=1, aabb_min=np.array([-60.0, -60, 0]), aabb_max=np.array([60.0, 60, 30]))
    duck = SimpleNamespace(id=7, class_id=2, aabb_min=np.array([35.5, 38.5, 0]), aabb_max=np.array([36.5, 39.5, 1]))
    far = SimpleNamespace(id=9, class_id=3, aabb_min=np.array([100.0, 0, 0]), aabb_max=np.array([101.0, 1, 5]))
    w = SimpleNamespace(instances=[site, duck, far], classes=["sky", "monastery", "duck", "tower"])
    run = _Run(np.zeros(3))
    r = _declaration_row(w, {"centroid": [36.0, 39.0, 0.5]}, "false", run)
    assert (r["nearest_class"], r["nearest_id"], r["nearest_m"]) == ("duck", 7, 0.0)
    r = _declaration_row(w, {"centroid": [70.0, 0.5, 1.0]}, "false", run)
    assert (r["nearest_class"], r["nearest_id"], r["nearest_m"]) == ("monastery", 1, 10.0)
    assert "confidence" not in r and "extent_m" not in r       # a bare centroid carries no more
    inst = {"centroid": [36.0, 39.0, 0.5], "box_min": [35.5, 38.5, 0.0], "box_max": [36.5, 39.75, 1.0],
            "confidence": 0.71234, "voxels": 12, "observations": 3}
    r = _declaration_row(w, inst, "false", run)
    assert (r["confidence"], r["voxels"], r["observations"], r["extent_m"]) == (0.7123, 12, 3, [1.0, 1.25, 1.0])


def test_every_policy_runs_without_collision_and_deterministically(loop, tmp_path):
    """Each policy over a short budget (4 steps): no collision (re-checked against the exact
    geometry with a finer sweep), the row's fields, and, run again, the same path, decisions
    and outcome — every policy; the rayfronts episode's rerun recording read back by rerun's
    own CLI."""
    import dataclasses
    import subprocess

    from apps.closed_loop.episode import LoopSettings, Trace, run_episode
    from apps.closed_loop.policies import POLICIES
    from apps.closed_loop.recording import record_episode
    from apps.closed_loop.robot import Platform
    from mapper.outputs.rerun_view import rerun_binary

    w, chain, mission = loop
    mission = dataclasses.replace(mission, budget_steps=4)   # twice 4 steps: the time one 8-step run took
    robot = Platform.make("ground")
    outcome = ("success", "spl", "path_m", "steps", "false_finds", "finds", "declarations", "collided", "end")
    differ = {}
    for p in POLICIES:
        tr = Trace()
        r = run_episode(w, mission, p, LoopSettings(), chain=chain, trace=tr)
        assert not r["collided"] and 1 <= r["steps"] <= mission.budget_steps, (p, r)
        assert set(r) >= {"success", "spl", "path_m", "false_finds", "steps", "cpu_ms_per_step"}
        pos, legs = np.asarray(tr.positions), np.asarray(tr.driven)
        assert all(np.isclose(legs, q).all(1).any() for q in pos), p          # each step's end was driven
        assert not any(robot.collides(w, a, b, spacing=0.03) for a, b in zip(legs[:-1], legs[1:], strict=True)), p
        assert r["path_m"] == pytest.approx(float(np.linalg.norm(np.diff(legs, axis=0), axis=1).sum())), p
        assert r["path_m"] > 1.0, (p, r)
        again = Trace()
        r2 = run_episode(w, mission, p, LoopSettings(), chain=chain, trace=again)
        if not (np.array_equal(pos, np.asarray(again.positions)) and tr.why == again.why
                and {k: r[k] for k in outcome} == {k: r2[k] for k in outcome}):
            differ[p] = (tr.why, again.why, {k: (r[k], r2[k]) for k in outcome if r[k] != r2[k]})
        if p == "rayfronts":
            assert r["step_ms_p50"]["step"] > 0
            st = r["step_ms_p50"]                 # the simulated camera's share, and the rest
            assert 0 < st["render"] < st["sense"] and 0 < st["robot_step"] < st["step"]
            rrd = tmp_path / "ep.rrd"
            record_episode(str(rrd), w, mission, tr, r)
            out = subprocess.run([rerun_binary(), "rrd", "stats", str(rrd)], capture_output=True, text=True,
                                 timeout=60)
            assert out.returncode == 0, out.stderr
            for ent in ("/world/robots/robot/trajectory", "/world/robots/robot/position", "/world/map/voxels",
                        "/world/truth/targets", "/summary"):   # docs/conventions.md#rerun-entity-paths
                assert ent in out.stdout, f"{ent} not in the recording:\n{out.stdout[:2000]}"
    assert not differ, f"not deterministic: {sorted(differ)}: {differ}"


def test_drone_flies_a_car_mission_without_collision_and_clears_only_its_own_body(loop):
    """The drone: its costmap marks UNKNOWN cells within its body's reach free (never an
    OCCUPIED one, never a cell farther away), and a car episode with the rayfronts policy
    moves every step (not stuck at the start), flies at its cruise height and touches no
    solid of the exact world (re-checked with a fine sweep)."""
    from apps.closed_loop.episode import LoopSettings, Trace, run_episode
    from apps.closed_loop.missions import make_mission
    from apps.closed_loop.robot import Platform

    drone = Platform.make("drone")
    states = np.full((20, 20), UNKNOWN, np.int8)
    states[10, 11] = OCCUPIED
    out = drone.with_own_body_free(states, np.zeros(2), 0.5, np.array([5.1, 5.1, 5.5]))
    centres = (np.indices(states.shape).transpose(1, 2, 0) + 0.5) * 0.5
    near = np.linalg.norm(centres - [5.1, 5.1], axis=2) <= drone.radius + 0.5
    assert (out[near & (states == UNKNOWN)] == FREE).all() and out[10, 11] == OCCUPIED
    assert (out[~near] == states[~near]).all() and near.sum() >= 9
    assert Platform.make("ground").with_own_body_free(states, np.zeros(2), 0.5, np.array([5.1, 5.1, 1.5])) is states

    w, chain, _ = loop
    mission = make_mission(w, drone, "object", "car", np.random.default_rng(3), budget_steps=6)
    tr = Trace()
    r = run_episode(w, mission, "rayfronts", LoopSettings(platform="drone"), chain=chain, trace=tr)
    pos = np.asarray(tr.positions)
    assert not r["collided"] and r["path_m"] > 0.5 * 2.0 * min(r["steps"], 3), r
    assert np.allclose(pos[:, 2], drone.cruise_z)
    assert not any(drone.collides(w, a, b, spacing=0.03) for a, b in zip(pos[:-1], pos[1:], strict=True))


@pytest.mark.timeout(400)
def test_live_loop_over_zenoh_finds_the_car_on_the_in_process_map(loop, tmp_path):
    """``--distributed`` in small: real mapper and edge processes over loopback Zenoh, the
    edge rendering the poses the simulator puts (``source.kind=sim_camera``), the planner on
    Client.search / occupancy_slice. The robot finds the car within its budget, and the live
    mapper's map equals the in-process map of the same views (voxel for voxel, scores within
    the query tolerance). A malformed sim-views message is counted by the edge, which keeps
    serving."""
    from apps.closed_loop.distributed import LiveMapper
    from apps.closed_loop.episode import LoopSettings, Trace, run_episode
    from apps.closed_loop.missions import make_mission
    from apps.closed_loop.robot import Platform
    from apps.closed_loop.world_model import LocalMapper, mapper_config
    from common.messages import QueryRequest
    from mapper.query_answer import answer_snapshot
    from semantic_map.query_copy import SCORE_ATOL

    w, chain, _ = loop
    robot, s = Platform.make("ground"), LoopSettings()
    mission = make_mission(w, robot, "object", "car", np.random.default_rng(0), budget_steps=12)
    cfg = mapper_config("rayfronts", s.depth_limit_m, s.vox_m, chain.cfg.resolution, s.preset, s.background_phrases(w))
    with LiveMapper(3, "default", chain, cfg, robot.costmap_band(s.vox_m), s.window_m, tmp_path) as live:
        live._views.put(b"not a sim-views message")
        trace = Trace()
        r = run_episode(w, mission, "rayfronts", s, chain=chain, mapper=live, trace=trace)
        assert live.mapped() == live.sent == chain.cfg.views * r["steps"]
        got = live.client.query("car", top_k=100_000, timeout=60.0)
    assert r["success"] and r["found"] == 1 and not r["collided"], r
    local = LocalMapper(chain.space, cfg, robot.costmap_band(s.vox_m), s.window_m)
    for pos in trace.positions[:r["steps"]]:
        local.integrate([chain.frame(p) for p in chain.view_poses(robot, pos)])
    local.snap.reserve(local.map)
    local.snap.sync(local.map, local.frames, local.frames)
    ref = answer_snapshot(local.snap, chain.space, QueryRequest(text="car", top_k=100_000), cfg.query)
    mine = dict(zip(map(tuple, np.round(ref.voxel_xyz, 3)), ref.voxel_score, strict=True))
    theirs = dict(zip(map(tuple, np.round(got.voxel_xyz, 3)), got.voxel_score, strict=True))
    assert len(theirs) == len(mine) == local.map.n_voxels() > 100 and set(theirs) == set(mine)
    assert max(abs(mine[k] - theirs[k]) for k in mine) <= SCORE_ATOL
    assert "sim_camera: ignoring a message" in (tmp_path / "edge.log").read_text()


def test_the_first_steps_outlier_rays_are_the_wires_rounding_and_read_zero():
    """Development seed 21 (the water tower ~280 m away, out of sight): after the first step's
    views the rays whose distinct cosine stands out do so by the wire's float16 rounding
    (within 1e-4 of the median). Without ``search.ray_cosine_resolution`` some look-next goal
    reads ``ray_z`` >= MIN_RAY_Z and the ray policies would follow it; with the default
    (2^-11) no goal's ``ray_z`` is above 0, so they explore by geometry (the same goals)."""
    import dataclasses

    from apps.closed_loop.episode import LoopSettings
    from apps.closed_loop.evaluate import SearchEvalConfig, seed_missions
    from apps.closed_loop.policies import MIN_RAY_Z
    from apps.closed_loop.robot import Platform
    from apps.closed_loop.sensing import EdgeChain, SensorConfig
    from apps.closed_loop.world_model import LocalMapper, mapper_config
    from synthetic_world import World

    w, robot, s = World.generate(21), Platform.make("ground"), LoopSettings()
    (_, _, mission), = seed_missions(SearchEvalConfig(missions=["landmark"], seeds=[21]), w, robot, 21)
    assert mission.target == "water tower"
    chain = EdgeChain(w, SensorConfig(resolution=224))
    cfg = mapper_config("rayfronts", s.depth_limit_m, s.vox_m, 224, s.preset, s.background_phrases(w))
    assert cfg.search.ray_cosine_resolution == 2.0 ** -11
    local = LocalMapper(chain.space, cfg, robot.costmap_band(s.vox_m), s.window_m)
    local.integrate([chain.frame(p) for p in chain.view_poses(robot, mission.start)])
    band = robot.goal_band
    z_default = [g["ray_z"] for g in local.observe([mission.target], mission.start, z_band=band).look_next]
    local.cfg = dataclasses.replace(cfg, search=dataclasses.replace(cfg.search, ray_cosine_resolution=0.0))
    z_plain = [g["ray_z"] for g in local.observe([mission.target], mission.start, z_band=band).look_next]
    assert len(z_default) == len(z_plain) > 5
    assert max(z_plain) >= MIN_RAY_Z and max(z_default) < MIN_RAY_Z
    assert not any(z_default)


def test_landmark_budget_is_three_oracle_tours():
    """A landmark's budget: 120 steps, at least three times the oracle's steps; objects keep theirs."""
    from apps.closed_loop.evaluate import budget_steps

    assert budget_steps("landmark", 210.0, 2.0) == 315
    assert budget_steps("landmark", 30.0, 2.0) == 120
    assert budget_steps("landmark", 210.0, 2.0, 0.5) == 158
    assert budget_steps("object", 210.0, 2.0) == 40 and budget_steps("all", 500.0, 2.0) == 60


def test_fewer_missions_replay_the_same_episodes(loop):
    """Missions are drawn per seed in one fixed order, so ``--missions landmark`` (or the two
    kinds in the other order) gives the landmark episode of ``--missions object,landmark``:
    same start, target instance and budget; and the car of ``object`` alone is that run's car."""
    from apps.closed_loop.evaluate import SearchEvalConfig, seed_missions
    from apps.closed_loop.robot import Platform

    w = loop[0]
    robot = Platform.make("ground")
    both = seed_missions(SearchEvalConfig(missions=["object", "landmark"]), w, robot, 3)
    assert [k for k, _, _ in both] == ["object", "landmark"]
    for asked, kind in ((["landmark"], "landmark"), (["landmark", "object"], "landmark"), (["object"], "object")):
        got = {k: m for k, _, m in seed_missions(SearchEvalConfig(missions=asked), w, robot, 3)}
        ref = next(m for k, _, m in both if k == kind)
        assert set(got) == set(asked)
        assert np.allclose(got[kind].start, ref.start) and got[kind].budget_steps == ref.budget_steps
        assert [i.id for i in got[kind].instances] == [i.id for i in ref.instances]
    # the generator is shared: a landmark drawn first (a fresh generator) starts elsewhere
    from apps.closed_loop.evaluate import MISSIONS
    from apps.closed_loop.missions import make_mission

    lm = next(m for k, _, m in both if k == "landmark")
    first = make_mission(w, robot, "landmark", lm.target, np.random.default_rng(3), MISSIONS["landmark"][1])
    assert not np.allclose(first.start, lm.start)


def test_eval_search_outputs(tmp_path):
    """``rayfronts eval search`` on one tiny run: the JSON's exact top-level shape, the table,
    the CSV rows (one per episode) and the plots."""
    import csv
    import json

    from apps.evaluation import cli

    p = argparse.ArgumentParser()
    cli.add_arguments(p)
    out = tmp_path / "es.json"
    args = p.parse_args(["search", "--seeds", "3", "--missions", "object", "--policies", "oracle,frontier",
                         "--budget-scale", "0.1", "--resolution", "64", "--json", str(out)])
    assert cli.run(args) == 0
    doc = json.loads(out.read_text())
    assert set(doc["policies"]) == {"oracle", "frontier"}
    for s in doc["policies"].values():
        assert {"success", "spl", "path_m", "false_finds", "episodes"} <= set(s) and s["episodes"] == 1
        assert isinstance(s["false_finds"], int)
    assert doc["settings"]["platform"] == "ground" and len(doc["episodes"]) == 2
    assert doc["policies"]["oracle"]["spl"] == pytest.approx(
        doc["episodes"][[r["policy"] for r in doc["episodes"]].index("oracle")]["spl"])
    rows = list(csv.DictReader(out.with_suffix(".csv").open()))
    assert [r["policy"] for r in rows] == [r["policy"] for r in doc["episodes"]]
    assert "| oracle |" in out.with_suffix(".md").read_text()
    assert (tmp_path / "es_spl.png").stat().st_size > 1000
    bad = p.parse_args(["search", "--depth-limit", "0", "--json", str(out)])
    assert cli.run(bad) == 2


def test_eval_search_trace_files(tmp_path):
    """``--trace DIR``: one file per map-based episode (none for the oracle), a step per step
    the row counts, starting at the row's start, each step's move no longer than the step
    length, the strongest rays first, and a "ray z" decision never stronger than the
    strongest ray the trace kept."""
    import json
    import re

    from apps.evaluation import cli

    p = argparse.ArgumentParser()
    cli.add_arguments(p)
    out, tr = tmp_path / "es.json", tmp_path / "trace"
    args = p.parse_args(["search", "--seeds", "3", "--missions", "object", "--policies", "oracle,rayfronts",
                         "--budget-scale", "0.1", "--resolution", "64", "--json", str(out), "--trace", str(tr)])
    assert cli.run(args) == 0
    rows = {r["policy"]: r for r in json.loads(out.read_text())["episodes"]}
    assert sorted(f.name for f in tr.iterdir()) == ["s3_object0_d20_rayfronts.json"]
    doc = json.loads((tr / "s3_object0_d20_rayfronts.json").read_text())
    row = rows["rayfronts"]
    assert (doc["policy"], doc["seed"], doc["steps"], doc["end"]) == ("rayfronts", 3, row["steps"], row["end"])
    steps = doc["trace"]
    assert [s["step"] for s in steps] == list(range(row["steps"]))
    assert np.allclose(steps[0]["position"], row["start"], atol=1e-3)
    pos = np.array([s["position"] for s in steps] + [row["end"]])
    assert np.all(np.linalg.norm(np.diff(pos, axis=0), axis=1) <= 2.0 + 1e-3)
    assert any(s["rays"] for s in steps)
    for s in steps:
        z = [r["ray_z"] for r in s["rays"]]
        assert z == sorted(z, reverse=True) and len(z) <= 5
        assert all(-180.0 <= r["heading_deg"] <= 180.0 for r in s["rays"])
        m = re.match(r"ray z (-?[0-9.]+)", s["why"])
        if m:
            assert float(m.group(1)) <= max(z) + 0.06, s
    # a ray goal the policy set aside is marked so (within 1.5 m of a set-aside goal)
    from apps.closed_loop.episode import strongest_rays
    from apps.closed_loop.policies import PolicyState

    state = PolicyState(set_aside=[np.array([10.0, 0.0])])
    rays = strongest_rays([dict(position=[10.5, 0.5, 1.5], heading_rad=0.0, ray_z=5.0, score=0.1),
                           dict(position=[30.0, 0.0, 1.5], heading_rad=np.pi, ray_z=9.0, score=0.2),
                           dict(position=[0.0, 0.0, 1.5], heading_rad=None, ray_z=99.0)], state)
    assert [(r["ray_z"], r["heading_deg"], r["set_aside"]) for r in rays] == [(9.0, 180.0, False), (5.0, 0.0, True)]


def test_rayfronts_finds_the_far_water_tower_where_frontier_exploration_does_not(loop):
    """The far-landmark regression, small: world 3's water tower, the robot starting 40 m from
    its centre on the town's side (36 m from its box), beyond the 15 m depth limit, at the
    shared chain's 96 px; the budget is three oracle tours (the eval's landmark rule without
    its 120-step floor). RayFronts finds the tower with no false find; frontier exploration,
    given as many steps as RayFronts needed, does not: a change that loses the far evidence
    (ray_z, the onward goals, the rays' crossing) fails here. Success is judged against the
    world's true instance."""
    import dataclasses

    from apps.closed_loop.episode import LoopSettings, run_episode
    from apps.closed_loop.evaluate import BUDGET_VS_ORACLE
    from apps.closed_loop.missions import DISTANCES, Mission, oracle_tour, truth_grid, xy_box_distance
    from apps.closed_loop.robot import Platform

    w, chain, _ = loop
    robot, s = Platform.make("ground"), LoopSettings(depth_limit_m=15.0)
    (tower,) = w.instances_of(w.class_id("water tower"))
    c = np.asarray(tower.center[:2], np.float64)
    start = np.r_[c - 40.0 * c / np.linalg.norm(c), robot.cruise_z]
    tg = truth_grid(w, robot, np.minimum(start[:2], tower.aabb_min[:2]) - 15.0,
                    np.maximum(start[:2], tower.aabb_max[:2]) + 15.0)
    assert tg.ok[tg.cell_of(start)], "the start is free ground"
    reach, declare = DISTANCES["landmark"]
    length, pts, _ = oracle_tour(tg, start, [tower], 1, reach)
    budget = int(math.ceil(BUDGET_VS_ORACLE["landmark"] * length / s.step_m))
    m = Mission("landmark", "water tower", [tower], 1, start, reach, declare, budget, length,
                np.c_[pts, np.full(len(pts), robot.cruise_z)])
    assert xy_box_distance(start, tower.aabb_min, tower.aabb_max) > 2 * s.depth_limit_m and length > 20.0
    rf = run_episode(w, m, "rayfronts", s, chain=chain)
    assert rf["success"] and rf["false_finds"] == 0 and not rf["collided"], rf
    assert 0 < rf["spl"] <= 1.0 and rf["path_m"] >= m.shortest_m
    fr = run_episode(w, dataclasses.replace(m, budget_steps=rf["steps"]), "frontier", s, chain=chain)
    assert not fr["success"] and not fr["collided"] and fr["steps"] == rf["steps"], fr


def test_a_step_drives_its_route_not_the_chord():
    """A step's route (``NavField.route_toward``) keeps to traversable cells around a corner,
    while the straight line from the robot to the point reached cuts through cells the
    clearance rule rejected; ``_Run.move`` drives the route leg by leg, so a body that the
    chord would drive into the obstacle misses it, and the path counts the route's length
    (the fault that made frontier exploration collide on pybullet seeds 100 and 105)."""
    from types import SimpleNamespace

    from apps.closed_loop.episode import _Run
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.planner import OCCUPIED

    cell, radius = 0.5, 0.3
    states = np.zeros((20, 20), np.int8)
    states[6:, :8] = OCCUPIED                         # x ≥ 3 m, y < 4 m: a block with its corner at (3, 4)
    at = np.array([1.25, 1.25, 0.5])
    nav = NavField(states, np.zeros(2), cell, at, radius)
    pts = nav.route_toward(np.array([16, 14]), 10.0, at)
    legs = np.vstack([at[:2], pts])
    assert len(pts) >= 3

    def cells_on(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        s = np.linspace(0.0, 1.0, 200)[:, None]
        return np.floor((a + (b - a) * s) / cell).astype(int)

    on_route = np.vstack([cells_on(a, b) for a, b in zip(legs[:-1], legs[1:], strict=True)])
    assert nav.ok[on_route[:, 0], on_route[:, 1]].all()
    chord = cells_on(at[:2], pts[-1])
    assert not nav.ok[chord[:, 0], chord[:, 1]].all()          # the chord crosses a rejected cell

    def collides(_world, a: np.ndarray, b: np.ndarray) -> bool:   # a disc of the body's radius
        p = a[None, :2] + (b - a)[None, :2] * np.linspace(0.0, 1.0, 400)[:, None]
        near = np.clip(p, [3.0, -np.inf], [np.inf, 4.0])           # nearest point of the block
        return bool((np.linalg.norm(p - near, axis=1) < radius).any())

    body = SimpleNamespace(collides=collides)
    route3 = np.c_[pts, np.full(len(pts), at[2])]
    run = _Run(at.copy())
    assert run.move(body, None, route3) and not run.collided
    assert np.allclose(run.pos, route3[-1])
    assert run.path_m == pytest.approx(float(np.linalg.norm(np.diff(legs, axis=0), axis=1).sum()))
    straight = _Run(at.copy())
    assert not straight.move(body, None, route3[-1]) and straight.collided and np.allclose(straight.pos, at)


def test_finer_ray_bins_keep_a_narrow_far_target_from_the_sky_around_it():
    """``--angle-bin``: a far tower 1.6° wide and 8° tall in a 30° × 30° field of sky rays is
    ~1 % of the one 30° bin its rays share; in 3° bins its best bin is half tower. The
    binned features' cosines to the tower feature are checked against the shares counted here
    by angle arithmetic alone (a 3° bin spans [3k − 1.5, 3k + 1.5) in azimuth, [3k, 3k + 3) in
    polar angle)."""
    import torch

    from semantic_map.ray_frontiers import bin_rays

    az, el = np.meshgrid(np.arange(-14.75, 15.0, 0.5), np.arange(0.25, 30.0, 0.5), indexing="ij")
    az, el = az.ravel(), el.ravel()
    tower = (az > 0.0) & (az < 1.6) & (el < 8.0)
    a, e = np.radians(az), np.radians(el)
    dirs = torch.as_tensor(np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1))
    sky_f, tower_f = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 1.0])
    feats = torch.where(torch.as_tensor(tower)[:, None], tower_f, sky_f)
    keys = torch.zeros(len(az), dtype=torch.int64)
    best = {}
    for psi in (30.0, 3.0):
        _, sw, sf, _ = bin_rays(keys, keys[:1], dirs, feats, torch.ones(len(az)), psi)
        mean = sf / sw[:, None]
        best[psi] = float(torch.nn.functional.cosine_similarity(mean, tower_f[None], dim=1).max())
    share30 = tower.sum() / len(az)
    in_bin = (az >= -1.5) & (az < 1.5) & (90.0 - el >= 84.0)            # the 3° bin holding the tower's base
    share3 = (tower & in_bin).sum() / in_bin.sum()
    cos = [s / math.hypot(s, 1.0 - s) for s in (share30, share3)]     # cosine of (1 - s, s) to (0, 1)
    assert share30 < 0.02 < 0.4 < share3
    assert best[30.0] == pytest.approx(cos[0], abs=1e-5)
    assert best[3.0] == pytest.approx(cos[1], abs=1e-5)


def test_the_angle_bin_option_sets_the_ray_maps_bins_and_the_json_says_so():
    from apps.closed_loop.episode import LoopSettings
    from apps.closed_loop.evaluate import SearchEvalConfig, _settings_fields
    from apps.evaluation.cli import _search_config, add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    cfg = _search_config(parser.parse_args(["search", "--json", "x.json", "--angle-bin", "5"]))
    assert cfg.angle_bin_deg == 5.0 and _settings_fields(cfg)["angle_bin_deg"] == 5.0
    assert "angle_bin_deg" not in _settings_fields(SearchEvalConfig())     # older runs' settings, unchanged
    s = cfg.loop_settings()                                            # what every episode of the run gets
    assert s.angle_bin_deg == 5.0 and s.background == "generic"
    assert s.map_config("rayfronts", None, 224).map.angle_bin_size == 5.0
    assert s.map_config("spherical_semfronts", None, 224).map.angle_bin_size == 360.0   # one bin per frontier
    assert LoopSettings(background="generic").map_config("rayfronts", None, 224).map.angle_bin_size == 30.0
    with pytest.raises(ValueError, match="--angle-bin"):
        SearchEvalConfig(angle_bin_deg=0.0).validate()
