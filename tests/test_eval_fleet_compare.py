"""``rayfronts eval fleet-compare``: fleets against one robot on the same missions.

Constructed documents with round numbers: every ratio, bound and verdict below is worked out
by hand in the test from the rows it builds, not read back from the code under test.
"""
from __future__ import annotations

import copy
import json
import math

import pytest

from apps.closed_loop.fleet_compare import bound_steps, compare_fleets, compare_markdown

SETTINGS = {"platform": "ground", "depth_limits": [20.0], "world": "pybullet", "step_m": 2.0, "budget_scale": 1.0}


def _one(rows: list[tuple[int, bool, int, float]]) -> dict:
    """The one-robot run: (seed, found, steps, path_m) per seed, policy rayfronts."""
    eps = [{"seed": s, "kind": "landmark", "episode": 0, "depth_limit_m": 20.0, "policy": "rayfronts",
            "success": f, "steps": n, "path_m": p, "shortest_m": 30.0, "start": [0.0, 0.0, 1.5], "budget_steps": 120}
           for s, f, n, p in rows]
    return {"settings": {**SETTINGS, "seeds": [r[0] for r in rows], "policies": ["rayfronts"]}, "episodes": eps}


def _fleet(n: int, rows: list[tuple[int, str, bool, int, float, float]], start: str = "together") -> dict:
    """A fleet run: (seed, policy, found, steps, total path_m, duplicated coverage); robot k starts
    1.5·k m east of the mission start, the mission's shortest path 30 m."""
    eps = [{"seed": s, "kind": "landmark", "episode": 0, "depth_limit_m": 20.0, "policy": pol, "robots": n,
            "success": f, "steps": k, "path_m": p, "duplicated_coverage": c, "shortest_m": 30.0,
            "start": [0.0, 0.0, 1.5], "starts": [[1.5 * i, 0.0, 1.5] for i in range(n)], "budget_steps": 120,
            "collided": not f and k < 120}
           for s, pol, f, k, p, c in rows]
    return {"settings": {**SETTINGS, "seeds": sorted({r[0] for r in rows}),
                         "policies": sorted({r[1] for r in rows}), "robots": n, "start": start, "footprint_m": 8.0},
            "episodes": eps}


def test_bound_is_the_shortest_path_less_the_farthest_start_in_steps():
    assert bound_steps(30.0, [[0, 0, 0]], [0, 0, 0], 2.0) == 15          # 30 m / 2 m exactly: not 16
    assert bound_steps(30.0, [[0, 0, 0], [3, 4, 0]], [0, 0, 0], 2.0) == 13   # 25 m left -> 12.5 -> 13
    assert bound_steps(3.0, [[0, 0, 0], [0, 5, 0]], [0, 0, 0], 2.0) == 0     # a robot starts in reach


def test_ratios_sums_and_the_aim_against_hand_worked_numbers():
    one = _one([(100, True, 20, 40.0), (101, False, 120, 200.0)])
    three = _fleet(3, [(100, "coordinated", True, 10, 55.0, 0.2), (101, "coordinated", True, 40, 240.0, 0.3),
                       (100, "uncoordinated", True, 12, 70.0, 0.6), (101, "uncoordinated", False, 120, 700.0, 0.7)])
    doc = compare_fleets([one, three])
    m = {(r["seed"], r["policy"]): r for r in doc["missions"]}
    assert m[(100, "coordinated")]["steps_ratio"] == pytest.approx(10 / 20)
    assert m[(101, "coordinated")]["path_ratio"] == pytest.approx(240 / 200)
    assert m[(101, "coordinated")]["one_found"] is False
    # robots start 0, 1.5, 3 m out: ceil((30 - 3) / 2) = 14 steps at least
    assert m[(100, "coordinated")]["bound_steps"] == 14
    assert m[(100, "coordinated")]["bound_ratio"] == pytest.approx(14 / 20)
    s = {r["policy"]: r for r in doc["summary"]}
    assert s["coordinated"]["steps_ratio"] == pytest.approx((10 + 40) / (20 + 120))
    assert s["coordinated"]["path_ratio"] == pytest.approx((55 + 240) / (40 + 200))
    assert s["coordinated"]["duplicated_coverage"] == pytest.approx(0.25)
    assert s["coordinated"]["found"] == 2 and s["uncoordinated"]["found"] == 1
    assert s["coordinated"]["vs_uncoordinated"] == {"fewer": 2, "same": 0, "more": 0, "steps": 50,
                                                     "uncoordinated_steps": 132}
    # 50/140 = 0.36 <= 0.5 and 295/240 = 1.23 <= 1.5 and ahead: met
    assert doc["aim"]["robots"] == 3 and doc["aim"]["met"] is True
    worse = copy.deepcopy(three)
    worse["episodes"][0]["path_m"] = 200.0                  # (200 + 240) / 240 = 1.83 > 1.5
    aim = compare_fleets([one, worse])["aim"]
    assert aim["checks"]["path_ratio"] is False and aim["checks"]["steps_ratio"] is True and aim["met"] is False
    md = compare_markdown(doc)
    assert "| 100 | 3 | coordinated | yes | 10 (20) | 0.50 | 0.70 | 55 (40) | 1.38 | 0.20 |" in md
    assert "| 101 | 3 | uncoordinated | no (ended at 120) | 120 (120, not found) | 1.00 |" in md


def test_a_fleet_that_failed_early_counts_the_whole_budget():
    """A collision at step 4 is no faster find: it counts the mission's 120 steps."""
    one = _one([(105, True, 22, 38.0)])
    three = _fleet(3, [(105, "uncoordinated", False, 4, 15.0, 0.6), (105, "coordinated", True, 22, 113.0, 0.6)])
    doc = compare_fleets([one, three])
    m = {r["policy"]: r for r in doc["missions"]}
    assert m["uncoordinated"]["steps"] == 120 and m["uncoordinated"]["ended_at"] == 4
    assert m["uncoordinated"]["steps_ratio"] == pytest.approx(120 / 22) and m["uncoordinated"]["collided"]
    assert doc["summary"][0]["vs_uncoordinated"]["fewer"] == 1
    assert "| 105 | 3 | uncoordinated | collided (ended at 4) |" in compare_markdown(doc)


def test_the_aim_is_judged_on_the_largest_fleet():
    one = _one([(100, True, 20, 40.0)])
    two = _fleet(2, [(100, "coordinated", True, 8, 40.0, 0.1), (100, "uncoordinated", True, 9, 40.0, 0.2)])
    three = _fleet(3, [(100, "coordinated", True, 15, 90.0, 0.4), (100, "uncoordinated", True, 14, 80.0, 0.5)])
    doc = compare_fleets([three, one, two])
    assert doc["aim"]["robots"] == 3
    assert doc["aim"]["steps_ratio"] == pytest.approx(15 / 20)
    assert doc["aim"]["checks"]["ahead_of_uncoordinated"] is False
    assert [(r["robots"], r["policy"]) for r in doc["summary"]] == [
        (2, "coordinated"), (2, "uncoordinated"), (3, "coordinated"), (3, "uncoordinated")]


def test_refusals_name_what_is_wrong():
    one = _one([(100, True, 20, 40.0)])
    three = _fleet(3, [(100, "coordinated", True, 10, 55.0, 0.2)])
    other = copy.deepcopy(three)
    other["settings"]["depth_limits"] = [10.0]
    with pytest.raises(ValueError, match="depth_limits"):
        compare_fleets([one, other])
    with pytest.raises(ValueError, match="no one-robot rayfronts"):
        compare_fleets([three])
    with pytest.raises(ValueError, match="more than one document"):
        compare_fleets([one, three, copy.deepcopy(three)])
    spread = _fleet(2, [(100, "coordinated", True, 10, 55.0, 0.2)], start="spread")
    with pytest.raises(ValueError, match="start"):
        compare_fleets([one, three, spread])
    with pytest.raises(ValueError, match="nothing to compare"):
        compare_fleets([])
    with pytest.raises(ValueError, match="not an eval search document"):
        compare_fleets([one, {"episodes": []}])


def test_cli_writes_the_comparison_and_refuses_in_one_line(tmp_path, capsys):
    from apps.cli import main

    a, b = tmp_path / "one.json", tmp_path / "three.json"
    a.write_text(json.dumps(_one([(100, True, 20, 40.0)])))
    b.write_text(json.dumps(_fleet(3, [(100, "coordinated", True, 10, 55.0, 0.2)])))
    out = tmp_path / "cmp.json"
    assert main(["eval", "fleet-compare", str(a), str(b), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert math.isclose(doc["summary"][0]["steps_ratio"], 0.5)
    assert out.with_suffix(".md").read_text().startswith("| seed | robots | policy |")
    capsys.readouterr()
    assert main(["eval", "fleet-compare", str(b), "--json", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no one-robot rayfronts" in err[0]
    assert not (tmp_path / "x.json").exists()
