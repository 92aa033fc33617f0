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


def _tower_case():
    """(world, mission, edge chain, loop settings) of the constructed case (module docstring)."""
    from apps.closed_loop.episode import LoopSettings
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
    return w, mission, chain, LoopSettings(background=cfg.background, depth_limit_m=10.0)


def test_sem_poses_heads_for_a_target_seen_from_afar_where_frontier_does_not():
    from apps.closed_loop.episode import Trace, run_episode

    w, mission, chain, settings = _tower_case()
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
    # the z-scores where the cut decides are recorded: the best pose by z heads toward a goal
    seen: list = []
    assert _pose_goal(obs([(o, east, 0.1, 1.0), (o, north, 0.1, 3.0)]), goals, 0.3, 3.5, seen) is None
    assert _pose_goal(obs([(o, east, 0.1, 1.0), (o, -east, 0.1, 7.0)]), goals, 0.3, 3.5, seen) is None  # none west
    assert _pose_goal(obs([(o, east, 0.5, 0.0), (o, north, 0.1, 9.0)]), goals, 0.3, 3.5, seen) is not None
    assert _pose_goal(obs([(o, east, 0.1, 4.0)]), goals, 0.3, 3.5, seen) is not None
    assert seen == [3.0, 4.0]           # not the westward 7.0, not the probability branch's pose


#: what an episode row says of the run itself (the rest is timing)
_RUN_FIELDS = ("success", "spl", "path_m", "steps", "false_finds", "finds", "declarations", "end", "pose_z")


def test_a_cut_no_recorded_z_separates_replays_the_episode_and_one_that_does_not_is_run():
    """The tuning's shortcut (:func:`apps.closed_loop.tuning.same_episodes`) against running:
    at a cut that no z-score of the cut-5 episode separates from 5 the episode is the same,
    field for field; at a cut below a recorded z-score (which the shortcut refuses to copy)
    the episode really differs — the poses lead earlier."""
    import dataclasses

    from apps.closed_loop.episode import run_episode
    from apps.closed_loop.tuning import reusable_cut, same_episodes

    w, mission, chain, settings = _tower_case()

    def run(cut: float) -> dict:
        return run_episode(w, mission, "sem-poses", dataclasses.replace(settings, sem_poses_min_z=cut), chain=chain)

    at5 = run(5.0)
    zs = at5["pose_z"]
    above, below = [z for z in zs if z >= 5.0 + 1e-4], [z for z in zs if z < 5.0 - 1e-4]
    assert above and below, zs                    # the poses stood out past 5 and short of it
    quiet = 5.0 + (min(above) - 5.0) / 2          # between 5 and the next recorded z: no z separates them
    loud = max(below) - 0.05                      # the strongest z short of 5 now passes the cut
    assert same_episodes([at5], 5.0, quiet) and not same_episodes([at5], 5.0, loud)
    assert reusable_cut({5.0: [at5]}, quiet) == 5.0 and reusable_cut({5.0: [at5]}, loud) is None
    same, other = run(quiet), run(loud)
    assert {k: same[k] for k in _RUN_FIELDS} == {k: at5[k] for k in _RUN_FIELDS}
    assert (other["path_m"], other["end"]) != (at5["path_m"], at5["end"])


def test_same_episodes_reads_every_row_and_refuses_rows_without_a_record():
    from apps.closed_loop.tuning import reusable_cut, same_episodes

    rows = [{"pose_z": [1.0, 4.2]}, {"pose_z": [2.7]}]
    assert same_episodes(rows, 5.0, 4.5) and same_episodes(rows, 3.0, 4.0)
    assert not same_episodes(rows, 5.0, 4.0)           # 4.2 lies between
    assert not same_episodes(rows, 2.5, 3.0)           # 2.7, in the second row
    assert not same_episodes(rows, 3.0, 2.7)           # a z at a cut counts as between
    assert not same_episodes([{}], 5.0, 4.5) and same_episodes([{}], 5.0, 5.0)
    # the nearest cut run that gives the same episodes
    assert reusable_cut({5.0: rows, 3.0: rows}, 4.5) == 5.0
    assert reusable_cut({5.0: rows, 3.5: rows}, 4.0) == 3.5 and reusable_cut({5.0: rows}, 4.0) is None
    assert reusable_cut({5.0: rows, 3.0: rows}, 3.5) == 3.0


def test_tune_sem_poses_copies_a_seed_no_z_separates_and_chooses_the_higher_cut_on_a_tie(tmp_path):
    """``tune_sem_poses`` end to end on one development seed (a short object mission): cut 60
    lies above every margin z-score, so cut 50's episodes are copied from it (one run, not
    two), the two cuts' summaries are equal and the tie goes to the higher cut; held-out
    seeds are refused; runs split by seed merge into one tuning."""
    import copy
    import dataclasses
    import json

    import pytest

    from apps.cli import main
    from apps.closed_loop.evaluate import SearchEvalConfig
    from apps.closed_loop.seeds import HELD_OUT_SEEDS
    from apps.closed_loop.tuning import merge_tunings, tune_sem_poses

    cfg = SearchEvalConfig(seeds=[0], missions=["object"], budget_scale=0.1, resolution=64, depth_limits=[10.0])
    partial = tmp_path / "tune.partial.json"
    doc = tune_sem_poses(cfg, [60.0, 50.0], partial_path=str(partial))
    assert not partial.exists()
    first, copied = doc["episodes"]
    assert first["pose_z"] and max(first["pose_z"]) < 50.0      # z-scores were compared, all below both cuts
    assert (doc["episodes_run"], doc["episodes_reused"]) == (1, 1)
    assert (first["cut"], copied["cut"], copied["reused_from_cut"]) == (60.0, 50.0, 60.0)
    assert {k: copied[k] for k in _RUN_FIELDS} == {k: first[k] for k in _RUN_FIELDS}
    assert doc["cuts"]["60.0"]["spl"] == doc["cuts"]["50.0"]["spl"] and doc["chosen"] == 60.0
    assert doc["seeds"]["set"] == "development" and doc["seeds_complete"] == [0] and doc["meta"]["commit"]
    with pytest.raises(ValueError, match="held-out"):
        tune_sem_poses(SearchEvalConfig(seeds=[HELD_OUT_SEEDS["synthetic"][0]]), [5.0])
    # runs split by seed join into one tuning (seed 1 here: seed 0's rows relabelled)
    other = copy.deepcopy(doc)
    for r in other["episodes"]:
        r["seed"] = 1
    both = merge_tunings([doc, other])
    assert both["seeds_complete"] == [0, 1] and (both["episodes_run"], both["episodes_reused"]) == (2, 2)
    assert {c: s["spl"] for c, s in both["cuts"].items()} == {c: s["spl"] for c, s in doc["cuts"].items()}
    assert [s["episodes"] for s in both["cuts"].values()] == [2, 2] and both["chosen"] == 60.0
    assert [p["seeds"] for p in both["merged_from"]] == [[0], [1]] and both["settings"]["seeds"] == [0, 1]
    # a seed run again (a cut-off run's seed) is kept once when it reproduces, refused when not
    again = merge_tunings([doc, both])
    assert again["seeds_complete"] == [0, 1] and again["episodes"] == both["episodes"]
    assert again["reproduced"] == [{"seed": 0, "cut": 60.0, "part": 2}, {"seed": 0, "cut": 50.0, "part": 2}]
    assert again["cuts"] == both["cuts"]
    moved = copy.deepcopy(doc)
    moved["episodes"][1]["path_m"] += 1.0
    with pytest.raises(ValueError, match=r"seed 0 at cut 50 is in an earlier part with another outcome \(path_m\)"):
        merge_tunings([doc, moved])
    # ... and so does `rayfronts eval merge` given tune-sem-poses files
    parts = [tmp_path / "a.json", tmp_path / "b.json"]
    for f, d in zip(parts, (doc, other), strict=True):
        f.write_text(json.dumps(d, default=float))
    assert main(["eval", "merge", *map(str, parts), "--json", str(tmp_path / "both.json")]) == 0
    assert json.loads((tmp_path / "both.json").read_text())["cuts"] == json.loads(json.dumps(both["cuts"]))
    other["settings"]["resolution"] = 96
    with pytest.raises(ValueError, match="resolution"):
        merge_tunings([doc, other])
    # a run cut off after seed 0's first cut goes on with --resume: cut 50 is copied from the
    # resumed cut 60 (no episode run), and the result is the uncut run's
    cut_off = json.loads(json.dumps({**doc, "episodes": doc["episodes"][:1], "episodes_reused": 0, "seeds_complete": [],
                                     "partial": True},
                                    default=float))
    resumed = tune_sem_poses(cfg, [60.0, 50.0], resume=cut_off)
    assert resumed["episodes"] == json.loads(json.dumps(doc["episodes"], default=float))
    assert (resumed["episodes_run"], resumed["episodes_reused"], resumed["cpu_s"]) == (1, 1, cut_off["cpu_s"])
    assert resumed["cuts"] == json.loads(json.dumps(doc["cuts"])) and resumed["chosen"] == 60.0
    assert resumed["resumed_from"] == {"meta": cut_off["meta"], "seeds_complete": [], "episodes": 1}
    with pytest.raises(ValueError, match="settings differ in resolution"):
        tune_sem_poses(dataclasses.replace(cfg, resolution=96), [60.0, 50.0], resume=cut_off)
    with pytest.raises(ValueError, match="cut 60, not in --cuts"):
        tune_sem_poses(cfg, [50.0], resume=cut_off)
    with pytest.raises(ValueError, match="seed 0 lacks a cut before its last one"):
        tune_sem_poses(cfg, [70.0, 60.0], resume=cut_off)
    # ... from the command line, the partial file as the run left it
    (tmp_path / "cut_off.partial.json").write_text(json.dumps(cut_off))
    assert main(["eval", "tune-sem-poses", "--seeds", "0", "--missions", "object", "--budget-scale", "0.1",
                 "--resolution", "64", "--depth-limit", "10", "--cuts", "60,50",
                 "--resume", str(tmp_path / "cut_off.partial.json"), "--json", str(tmp_path / "resumed.json")]) == 0
    assert json.loads((tmp_path / "resumed.json").read_text())["episodes"] == resumed["episodes"]
    (tmp_path / "bad.json").write_text("{")
    assert main(["eval", "tune-sem-poses", "--seeds", "0", "--resume", str(tmp_path / "bad.json"),
                 "--json", str(tmp_path / "x.json")]) == 2
