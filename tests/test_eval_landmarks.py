"""``rayfronts eval landmarks``: landmark episodes' starts and ends against the world's landmarks.

Checked against the world's own geometry: in the town, a start placed next to the radio tower
(the water tower's look-alike) must come out with the look-alike nearer, the distances equal
to the instances' box centres; in a pybullet site, pybullet's own ray test along each reported
bearing must hit the landmark's box no farther than the reported distance.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from apps.closed_loop.landmark_report import landmark_report, report_markdown
from apps.closed_loop.missions import TARGETS

ROOT = Path(__file__).resolve().parents[1]
DRONE = ROOT / "benchmarks" / "eval_search_pybullet_drone_20m_vocabulary_seeds100-105.json"


def _episode(policy: str, start, end, success: bool, seed: int = 0, target: str = "water tower") -> dict:
    return {"policy": policy, "kind": "landmark", "target": target, "seed": seed, "episode": 0,
            "depth_limit_m": 20.0, "platform": "ground", "start": [*start, 1.5], "end": [*end, 1.5],
            "success": success, "spl": 0.5 if success else 0.0, "path_m": 100.0, "false_finds": 0}


@pytest.fixture(scope="module")
def town():
    from synthetic_world import World

    return World.generate(0)


def test_town_start_by_the_look_alike(town):
    radio = town.instances_of(town.classes.index("radio tower"))[0]
    water = town.instances_of(town.classes.index("water tower"))[0]
    start = np.asarray(radio.center[:2]) + [6.0, 0.0]
    doc = {"settings": {"world": "synthetic"}, "meta": {"commit": "abc", "argv": ["rayfronts"]}, "episodes": [
        _episode("rayfronts", start, radio.center[:2] + [10.0, 10.0], False),
        _episode("spherical", start, water.center[:2], True),
        _episode("frontier", start, start + [200.0, 0.0], False),
        {**_episode("object-only", start, start, False), "kind": "object"}]}
    rep = landmark_report([doc], near_m=30.0, make=lambda w, s: town)
    (row,) = rep["episodes"]
    assert row["target_nearer"] is False
    d = {m["class"]: m for m in row["landmarks"] if m["id"] in (radio.id, water.id)}
    for inst, name in ((radio, "radio tower"), (water, "water tower")):
        dx, dy = inst.center[0] - start[0], inst.center[1] - start[1]
        assert d[name]["distance_m"] == pytest.approx(math.hypot(dx, dy), abs=1e-6)
        back = start + d[name]["distance_m"] * np.array([math.cos(math.radians(d[name]["bearing_deg"])),
                                                         math.sin(math.radians(d[name]["bearing_deg"]))])
        assert np.allclose(back, inst.center[:2], atol=1e-6)
    assert [m["distance_m"] for m in row["landmarks"]] == sorted(m["distance_m"] for m in row["landmarks"])
    by = {p["policy"]: p for p in row["policies"]}
    assert by["rayfronts"]["by_look_alike"] and by["rayfronts"]["end_m"]["radio tower"] <= math.hypot(10, 10) + 1e-6
    assert not by["spherical"]["by_look_alike"] and by["spherical"]["end_m"]["water tower"] < 1e-6
    assert not by["frontier"]["by_look_alike"]
    assert "object-only" not in by
    s = rep["summary"]
    assert s["rayfronts"]["look_alike_nearer"] == {"episodes": 1, "found": 0, "by_look_alike": 1}
    assert s["spherical"]["look_alike_nearer"]["found"] == 1 and s["spherical"]["target_nearer"]["episodes"] == 0
    md = report_markdown(rep)
    assert "water tower (look-alike nearer)" in md and "| rayfronts | 0/0 | 0/1 | 1 |" in md
    # with traces: the steps whose strongest ray points at each tower (within 15°)
    import tempfile

    from apps.closed_loop.evaluate import trace_name

    def ray_at(frm, to, turn_deg=0.0):
        h = math.degrees(math.atan2(to[1] - frm[1], to[0] - frm[0])) + turn_deg
        return {"position": [float(frm[0]), float(frm[1])], "heading_deg": h, "ray_z": 9.0}

    p0 = np.asarray(start, np.float64) + [0.0, 30.0]
    steps = [{"rays": [ray_at(p0, water.center)]}, {"rays": [ray_at(p0, water.center, 14.0)]},
             {"rays": [ray_at(p0, radio.center), ray_at(p0, water.center)]}, {"rays": [ray_at(p0, water.center, 40.0)]},
             {"rays": []}]
    with tempfile.TemporaryDirectory() as tdir:
        ep = doc["episodes"][0]
        (Path(tdir) / trace_name({**ep, "kind": "landmark"})).write_text(json.dumps({"trace": steps}))
        rep3 = landmark_report([doc], near_m=30.0, make=lambda w, s: town, traces=tdir)
    by3 = {p["policy"]: p for p in rep3["episodes"][0]["policies"]}
    assert by3["rayfronts"]["traced_steps"] == 5
    assert len(town.instances_of(town.classes.index("water tower"))) == 1     # one of each in town 0
    assert len(town.instances_of(town.classes.index("radio tower"))) == 1
    # at the water tower: steps 0 and 1 (14° off); at the radio tower: step 2 (its first ray)
    assert by3["rayfronts"]["rays_at"] == {"water tower": 2, "radio tower": 1}
    assert "rays_at" not in by3["spherical"]           # no trace file for it
    assert "strongest ray at water tower" in report_markdown(rep3)
    # the same start with the water tower as target one metre away: the target is nearer
    near_water = np.asarray(water.center[:2]) + [1.0, 0.0]
    rep2 = landmark_report([{"settings": {"world": "synthetic"}, "episodes": [
        _episode("rayfronts", near_water, near_water, True)]}], make=lambda w, s: town)
    assert rep2["episodes"][0]["target_nearer"] is True


def test_pybullet_bearings_hit_the_landmark():
    """The committed drone run: pybullet's ray test from each start along each bearing hits the
    landmark's box, and no farther than the reported centre distance."""
    import pybullet as p

    from synthetic_world.pybullet_world import PybulletWorld

    doc = json.loads(DRONE.read_text())
    doc["episodes"] = [e for e in doc["episodes"] if e["seed"] in (100, 103)]
    worlds: dict[int, PybulletWorld] = {}

    def make(family: str, seed: int):
        assert family == "pybullet"
        worlds[seed] = PybulletWorld.generate(seed)
        return worlds[seed]

    rep = landmark_report([doc], make=make)
    checked = 0
    for row in rep["episodes"]:
        w = PybulletWorld.generate(row["seed"])
        try:
            for m in row["landmarks"]:
                inst = next(i for i in w.instances if i.id == m["id"])
                z = float(inst.aabb_min[2] + inst.aabb_max[2]) / 2.0
                a = math.radians(m["bearing_deg"])
                u = np.array([math.cos(a), math.sin(a), 0.0])
                o = np.array([row["start"][0], row["start"][1], z])
                travelled, hit_xyz = 0.0, None
                for _ in range(50):             # step past whatever stands in between (trees, walls)
                    far = m["distance_m"] + 60.0 - travelled
                    hit = p.rayTest(o.tolist(), (o + far * u).tolist(), physicsClientId=w.cid)[0]
                    assert hit[0] >= 0, (row["seed"], m)
                    xyz = np.asarray(hit[3])
                    travelled += hit[2] * far
                    if np.all(xyz[:2] >= inst.aabb_min[:2] - 0.5) and np.all(xyz[:2] <= inst.aabb_max[:2] + 0.5):
                        hit_xyz = xyz
                        break
                    o = xyz + 0.01 * u
                    travelled += 0.01
                assert hit_xyz is not None, (row["seed"], m)
                assert travelled <= m["distance_m"] + 1e-6
                checked += 1
        finally:
            w.close()
    assert checked == 2 * len(TARGETS["pybullet"]["landmark"])
    by_seed = {r["seed"]: r for r in rep["episodes"]}
    assert by_seed[100]["target_nearer"] and not by_seed[103]["target_nearer"]
    for w in worlds.values():
        assert w.cid == -1                 # the report closed the worlds it built


def test_cli_refuses_a_run_without_landmarks(tmp_path, capsys):
    from apps.cli import main

    f = tmp_path / "objects.json"
    f.write_text(json.dumps({"settings": {"world": "synthetic"}, "episodes": [
        {**_episode("rayfronts", (0, 0), (0, 0), False), "kind": "object"}]}))
    capsys.readouterr()
    assert main(["eval", "landmarks", str(f)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no single-robot landmark episodes" in err[0]
    assert main(["eval", "landmarks", str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot read" in err[0]
