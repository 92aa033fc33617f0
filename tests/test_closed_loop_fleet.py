"""Two and three robots in the closed loop (apps/closed_loop/fleet_episode.py, issue 44 item 3):
a fleet on one shared map finds a far car in fewer steps than one robot, the coordinated fleet
duplicates less coverage than the uncoordinated one, a fleet of one is the single-robot loop,
and ``rayfronts eval search --robots N`` writes the fleet's rows."""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math

import numpy as np
import pytest

#: the car mission's image size (px): the unit tests' edge chain size (a three-robot episode ~15 s)
RES = 96


@pytest.fixture(scope="module")
def car():
    """World 3 and the car of mission draw 1: ≥ 15 m from the start, out of sight behind the
    town's blocks (one robot needs 20+ steps); the single robot's episode and a cache of
    fleet episodes shared by the tests."""
    from apps.closed_loop.episode import LoopSettings, run_episode
    from apps.closed_loop.missions import make_mission, xy_box_distance
    from apps.closed_loop.robot import Platform
    from apps.closed_loop.sensing import EdgeChain, SensorConfig
    from synthetic_world import World

    w = World.generate(3)
    robot = Platform.make("ground")
    m = make_mission(w, robot, "object", "car", np.random.default_rng(1), budget_steps=40)
    assert min(xy_box_distance(m.start, i.aabb_min, i.aabb_max) for i in m.instances) >= 15.0
    chain = EdgeChain(w, SensorConfig(resolution=RES, label_stride=4), fit_at=m.start)
    single = run_episode(w, m, "rayfronts", LoopSettings(), chain=chain)
    return w, chain, m, single, {}


def _fleet(car, policy: str, n: int) -> tuple[dict, list, list]:
    from apps.closed_loop.episode import LoopSettings
    from apps.closed_loop.fleet_episode import FleetSettings, run_fleet_episode

    w, chain, m, _, cache = car
    if (policy, n) not in cache:
        trace: list = []
        routes: list = []
        cache[policy, n] = (run_fleet_episode(w, m, policy, LoopSettings(), FleetSettings(n), chain, trace=trace,
                                              routes=routes), trace, routes)
    return cache[policy, n]


def _check_fleet_row(car, row: dict, trace: list, n: int, routes: list) -> None:
    """The fleet episode found the true car without collision or false find: every robot's
    swept body re-checked against the exact geometry along every leg it drove, the paths
    summed from those legs, each step's position among them."""
    from apps.closed_loop.robot import Platform

    w, _, m, _, _ = car
    robot = Platform.make("ground")
    pos = np.stack(trace)                                           # (steps + 1, n, 3)
    assert pos.shape[1] == n and row["robots"] == n and len(row["paths_m"]) == n and len(routes) == n
    for i in range(n):
        legs = routes[i]
        assert np.allclose(legs[0], pos[0, i]) and np.allclose(legs[-1], pos[-1, i])
        assert all(np.isclose(legs, p).all(1).any() for p in pos[:, i])
        assert not any(robot.collides(w, a, b, spacing=0.03) for a, b in zip(legs[:-1], legs[1:], strict=True))
        assert row["paths_m"][i] == pytest.approx(float(np.linalg.norm(np.diff(legs, axis=0), axis=1).sum()))
    assert row["path_m"] == pytest.approx(sum(row["paths_m"]))
    assert row["success"] and row["found"] == 1 and row["false_finds"] == 0 and not row["collided"], row
    (d,) = [d for d in row["declarations"] if d["verdict"] == "find"]
    assert d["robot"] == row["finder"] and d["nearest_id"] in {int(i.id) for i in m.instances}
    fi = ["sim", "sim1", "sim2"].index(row["finder"])
    assert row["spl"] == pytest.approx(min(1.0, m.shortest_m / row["paths_m"][fi]))


def test_two_robots_find_the_far_car_in_fewer_steps_than_one(car):
    _, _, m, single, _ = car
    assert single["success"] and single["steps"] >= 20, single      # one robot searches a while
    row, trace, routes = _fleet(car, "coordinated", 2)
    _check_fleet_row(car, row, trace, 2, routes)
    assert row["steps"] < single["steps"]


def test_three_robots_find_the_far_car_in_fewer_steps_than_one(car):
    _, _, _, single, _ = car
    assert single["success"]
    row, trace, routes = _fleet(car, "coordinated", 3)
    _check_fleet_row(car, row, trace, 3, routes)
    assert row["steps"] < single["steps"]


def test_coordinated_fleet_duplicates_less_coverage_than_uncoordinated(car):
    co, _, _ = _fleet(car, "coordinated", 2)
    un, trace, routes = _fleet(car, "uncoordinated", 2)
    _check_fleet_row(car, un, trace, 2, routes)
    assert co["observed_voxels"] > 1000 and un["observed_voxels"] > 1000    # both saw a good part of the town
    assert 0.0 < co["duplicated_coverage"] < un["duplicated_coverage"]


def test_a_fleet_of_one_is_the_single_robot_loop(car):
    """``coordinated`` and ``uncoordinated`` with one robot replay the single-robot rayfronts
    episode step for step (same path, decisions, outcome); ``--robots 1`` keeps today's loop."""
    from apps.closed_loop.episode import LoopSettings, Trace, run_episode
    from apps.closed_loop.fleet_episode import FleetSettings, run_fleet_episode

    w, chain, m, _, _ = car
    m = dataclasses.replace(m, budget_steps=6)
    tr = Trace()
    ref = run_episode(w, m, "rayfronts", LoopSettings(), chain=chain, trace=tr)
    assert ref["path_m"] > 5.0
    for policy in ("coordinated", "uncoordinated"):
        trace: list = []
        r = run_fleet_episode(w, m, policy, LoopSettings(), FleetSettings(1), chain, trace=trace)
        assert np.array_equal(np.stack(trace)[:, 0], np.asarray(tr.positions)), policy
        for k in ("success", "spl", "path_m", "steps", "false_finds", "found", "finds"):
            assert r[k] == ref[k], (policy, k, r[k], ref[k])
        assert r["end"] == [ref["end"]] and r["duplicated_coverage"] == 0.0


def test_fleet_starts_together_and_spread(car):
    from apps.closed_loop.fleet_episode import fleet_starts
    from apps.closed_loop.robot import Platform

    w, _, m, _, _ = car
    robot = Platform.make("ground")
    for mode, lo, hi in (("together", 1.2, 6.0), ("spread", 1.2, 24.0)):
        s = fleet_starts(w, robot, m.start, 3, mode)
        assert np.array_equal(s[0], m.start) and len(s) == 3
        for a, b in itertools.combinations(s, 2):
            assert lo <= np.linalg.norm(a - b) <= hi, (mode, a, b)
        assert all(not robot.collides(w, p, p, spacing=0.03) and p[2] == m.start[2] for p in s)
    far = fleet_starts(w, robot, m.start, 3, "spread")
    assert max(np.linalg.norm(p - m.start) for p in far) > 3.0          # spread farther than together


def test_observed_voxels_and_duplicated_coverage_against_plain_geometry():
    from apps.closed_loop.fleet_episode import duplicated_coverage, observed_voxels
    from apps.closed_loop.robot import camera_pose
    from common.frame import Frame

    k = np.array([[20.0, 0, 20.0], [0, 20.0, 20.0], [0, 0, 1]])
    depth = np.full((40, 40), 5.0, np.float32)           # a wall 5 m ahead of a camera looking along +x
    depth[:, :8] = np.nan                                 # no return
    depth[:, 32:] = 30.0                                  # beyond the depth limit
    f = Frame("r", 0, 0.0, camera_pose(np.array([0.2, 0.1, 1.5]), 0.0), k, depth, np.zeros((40, 40, 3), np.uint8))
    got = observed_voxels(f, 0.5, 20.0, stride=1)
    # independent: the wall x = 5.2; y from 0.1 - (u - 20)/20·5, z from 1.5 - (v - 20)/20·5, u in 8..31
    u, v = np.meshgrid(np.arange(8, 32), np.arange(40))
    want = {(10, int(a), int(b)) for a, b in zip(np.floor((0.1 - (u - 20) / 20 * 5) / 0.5).ravel(),
                                                   np.floor((1.5 - (v - 20) / 20 * 5) / 0.5).ravel(), strict=True)}
    assert got == want and len(got) > 100
    a, b, c = {(0, 0, 0), (1, 0, 0)}, {(1, 0, 0), (2, 0, 0)}, {(3, 0, 0)}
    assert duplicated_coverage([a, b, c]) == (pytest.approx(1 / 4), 4)
    assert duplicated_coverage([a]) == (0.0, 2) and duplicated_coverage([set(), set()]) == (0.0, 0)


def test_eval_search_with_robots_writes_the_fleet_rows(tmp_path):
    """``rayfronts eval search --robots 2`` on a tiny budget: the fleet policies by default, one
    row per policy with the fleet's fields, the provenance block, the fleet table; one-line
    errors for a single-robot policy with a fleet and for a fleet of none."""
    from apps.evaluation import cli

    p = argparse.ArgumentParser()
    cli.add_arguments(p)
    out = tmp_path / "fleet.json"
    args = p.parse_args(["search", "--robots", "2", "--seeds", "3", "--missions", "object", "--budget-scale", "0.05",
                         "--resolution", "48", "--json", str(out)])
    assert cli.run(args) == 0
    doc = json.loads(out.read_text())
    assert set(doc["policies"]) == {"coordinated", "uncoordinated", "frontier-only"}
    assert doc["settings"]["robots"] == 2 and doc["settings"]["start"] == "together"
    assert {"commit", "argv", "machine", "load_before"} <= set(doc["meta"]) and doc["machine"]["cores"] >= 1
    assert doc["seeds"]["set"] == "development" and len(doc["episodes"]) == 3
    for r in doc["episodes"]:
        assert r["robots"] == 2 and len(r["paths_m"]) == 2 and r["steps"] == 2
        assert r["path_m"] == pytest.approx(sum(r["paths_m"])) and 0.0 <= r["duplicated_coverage"] <= 1.0
    for s in doc["policies"].values():
        assert s["robots"] == [2] and math.isfinite(s["duplicated_coverage"])
    md = out.with_suffix(".md").read_text()
    assert "| duplicated coverage |" in md and "| 3 | coordinated | 2 | together |" in md
    for bad in (["--robots", "2", "--policies", "rayfronts"], ["--robots", "0"]):
        assert cli.run(p.parse_args(["search", *bad, "--json", str(tmp_path / "x.json")])) == 2


def test_single_robot_runs_keep_their_json_and_csv_columns():
    """``--robots 1`` with the single-robot policies: the JSON settings and CSV columns are
    those of before the fleet (no fleet keys), so its outputs stay byte for byte the same."""
    from apps.closed_loop.evaluate import FLEET_ROW_FIELDS, ROW_FIELDS, SearchEvalConfig, _settings_fields

    one = _settings_fields(SearchEvalConfig(policies=["rayfronts", "frontier"]).validate())
    assert not {"robots", "start", "footprint_m"} & set(one) and one["policies"] == ["rayfronts", "frontier"]
    two = _settings_fields(SearchEvalConfig(robots=2, policies=["coordinated"]).validate())
    assert two["robots"] == 2 and two["start"] == "together" and two["footprint_m"] == 8.0
    assert not set(FLEET_ROW_FIELDS) & set(ROW_FIELDS)
    with pytest.raises(ValueError, match="--robots 2: rayfronts drive one robot"):
        SearchEvalConfig(robots=2, policies=["rayfronts", "coordinated"]).validate()


def test_robots_side_by_side_declare_what_they_all_see_once(car):
    """Three robots start next to the car, each within reach: in the same step every one of
    them decides to declare it once it was found at ``MIN_OBSERVATIONS`` map updates (they
    stay and look until then). The fleet declares it once (the first robot's), not three
    times — a false instance would otherwise count three false finds."""
    from apps.closed_loop.episode import LoopSettings
    from apps.closed_loop.fleet_episode import FleetSettings, fleet_starts, run_fleet_episode
    from apps.closed_loop.missions import xy_box_distance
    from apps.closed_loop.robot import Platform

    w, chain, m, _, _ = car
    robot = Platform.make("ground")
    box = m.instances[0]
    near = None
    for r, a in itertools.product((1.5, 2.0, 2.5), np.arange(16) * math.pi / 8):
        c = np.clip(m.start[:2], box.aabb_min[:2], box.aabb_max[:2])   # the box side facing the start
        p = np.array([c[0] + r * math.cos(a), c[1] + r * math.sin(a), m.start[2]])
        if xy_box_distance(p, box.aabb_min, box.aabb_max) >= 1.0 and not robot.collides(w, p, p):
            try:
                starts = fleet_starts(w, robot, p, 3)
            except ValueError:
                continue
            if max(xy_box_distance(s, box.aabb_min, box.aabb_max) for s in starts) <= m.reach_m - 0.6:
                near = p
                break
    assert near is not None, "no start by the car where three robots fit within reach"
    mission = dataclasses.replace(m, start=near)
    from apps.closed_loop.policies import MIN_OBSERVATIONS

    row = run_fleet_episode(w, mission, "uncoordinated", LoopSettings(), FleetSettings(3), chain)
    assert row["success"] and row["steps"] == MIN_OBSERVATIONS and row["path_m"] == 0.0, row
    assert len(row["declarations"]) == 1 and row["declarations"][0]["verdict"] == "find", row["declarations"]


def test_a_cluster_of_bids_goes_to_the_robot_nearest_it():
    """Round 1 of the allocation on an open costmap: robots A (x = 0) and B (x = 10) bid goals
    4 m apart (one frontier region, footprint 8 m), A's own bid at x = 30 and B's at x = 26,
    both by evidence; robot C (x = -10) bids a region of its own. The region goes to the
    robot with the shortest path to any bid of it — B, to its own bid — even were A's bid
    the one kept; the loser A takes another region (round 2), C keeps its bid. Then with B's
    bid moved beyond A's (B at x = 10, bid x = 34; A's bid x = 30): B is nearest A's bid
    (20 m against A's 30 m), so B takes A's bid, holding it as its own goal."""
    from apps.closed_loop.fleet_episode import _allocate, _Fleet
    from apps.closed_loop.navigation import NavField
    from apps.closed_loop.planner import FREE
    from apps.closed_loop.policies import Decision, PolicyState
    from apps.closed_loop.world_model import Observation

    cell, origin = 0.5, np.array([-40.0, -40.0])
    states = np.full((160, 160), FREE, np.int8)
    look = [{"position": [x, y, 1.0], "score": 0.0, "gain_m3": 50.0, "distance_m": 0.0, "ray_z": 0.0,
             "target": None, "heading_rad": 0.0} for x, y in ((30.0, 0.0), (26.0, 0.0), (-30.0, 0.0), (0.0, 30.0))]

    def fleet(at_x: list[float]):
        runs = [argparse.Namespace(pos=np.array([x, 0.0, 1.0])) for x in at_x]
        navs = [NavField(states, origin, cell, r.pos, 0.3) for r in runs]
        obs = [Observation([], look, states, origin, cell) for _ in runs]
        return _Fleet(runs=runs, states=[PolicyState() for _ in runs], navs=navs, obs=obs)

    def bid(fl, i: int, x: float, y: float = 0.0, evidence: bool = True):
        c, _, _ = fl.navs[i].nearest_reachable(np.array([x, y]))
        fl.states[i].goal = (np.array([x, y]), 1.0, evidence)
        return Decision(goal_cell=c, goal_xy=np.array([x, y]), why="rays", score=1.0), evidence

    names = ["a", "b", "c"]
    fl = fleet([0.0, 10.0, -10.0])
    out = _allocate({0: bid(fl, 0, 30.0), 1: bid(fl, 1, 26.0), 2: bid(fl, 2, -30.0)}, fl, names, [0, 1, 2], 8.0)
    assert np.allclose(out[1].goal_xy, [26.0, 0.0]) and np.allclose(out[2].goal_xy, [-30.0, 0.0])
    assert out[0].why == "allocated" and np.linalg.norm(out[0].goal_xy - [26.0, 0.0]) >= 8.0
    assert fl.states[0].goal is None                 # its bid lost: it decides afresh

    fl = fleet([0.0, 10.0, -10.0])
    out = _allocate({0: bid(fl, 0, 30.0), 1: bid(fl, 1, 34.0), 2: bid(fl, 2, -30.0)}, fl, names, [0, 1, 2], 8.0)
    assert np.allclose(out[1].goal_xy, [30.0, 0.0]) and "(from a)" in out[1].why
    assert np.allclose(fl.states[1].goal[0], [30.0, 0.0]) and fl.states[1].goal[2] is True
    assert np.linalg.norm(out[0].goal_xy - [30.0, 0.0]) >= 8.0 and np.allclose(out[2].goal_xy, [-30.0, 0.0])
