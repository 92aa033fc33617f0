"""Every ``rayfronts eval search`` JSON says where it came from: the commit (checked against
git itself), the command line, the machine, the load before and after, and the seeds with
the development / held-out lists they belong to (apps/closed_loop/seeds.py)."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_eval_json_records_commit_command_machine_load_and_seeds(tmp_path, monkeypatch):
    """(The run's missions are left out — provenance does not depend on them — so the test
    needs no episode.)"""
    import json

    import apps.closed_loop.evaluate as ev
    from apps.closed_loop.evaluate import SearchEvalConfig, run_search_eval, write_outputs
    from apps.closed_loop.seeds import DEVELOPMENT_SEEDS, HELD_OUT_SEEDS

    assert not set(DEVELOPMENT_SEEDS["synthetic"]) & set(HELD_OUT_SEEDS["synthetic"])
    assert not set(DEVELOPMENT_SEEDS["pybullet"]) & set(HELD_OUT_SEEDS["pybullet"])
    argv = ["rayfronts", "eval", "search", "--policies", "oracle", "--missions", "object", "--json", "x.json"]
    cfg = SearchEvalConfig(policies=["oracle"], missions=["object"], resolution=32, seeds=[0])
    monkeypatch.setattr(ev, "seed_missions", lambda *a: [])
    doc = run_search_eval(cfg, argv=argv)
    p = tmp_path / "x.json"
    write_outputs(doc, p)
    back = json.loads(p.read_text())
    meta = back["meta"]
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    assert meta["commit"] == head and isinstance(meta["dirty"], bool)
    assert meta["argv"] == argv
    assert meta["machine"]["logical_cores"] == os.cpu_count() and meta["machine"]["cpu_model"]
    assert len(meta["load_before"]) == 3 and len(meta["load_after"]) == 3
    assert meta["utc"].endswith("Z") and meta["process"]["wall_s"] > 0
    assert back["seeds"] == {"run": [0], "set": "development", "development": DEVELOPMENT_SEEDS["synthetic"],
                             "held_out": HELD_OUT_SEEDS["synthetic"]}
    assert back["episodes"] == [] and back["settings"]["world"] == "synthetic"
    assert back["settings"]["background_phrases"] == ["ground", "road", "grass", "wall", "building", "tree", "sky"]


def test_seed_sets_name_the_set():
    from apps.closed_loop.seeds import seed_sets

    assert seed_sets("pybullet", [100, 101])["set"] == "held-out"
    assert seed_sets("pybullet", [1, 100])["set"] == "mixed"
    assert seed_sets("synthetic", [500])["set"] == "other"


def test_a_run_writes_its_finished_episodes_as_it_goes(tmp_path, monkeypatch):
    """With ``partial_path`` every finished episode is on disk before the next one starts (a
    run cut off keeps them, marked ``partial`` with the commit and command line), and the
    partial file is gone once the run has ended. The commit recorded is the one the run
    started with, even if HEAD moves during the run (here: every later look at git reads
    another commit). The world, missions and episodes are stand-ins: what is checked is the
    bookkeeping around them."""
    import itertools
    import json
    from types import SimpleNamespace

    import apps.bench.meta as bench_meta
    import apps.closed_loop.evaluate as ev
    from apps.closed_loop.evaluate import SearchEvalConfig, run_search_eval

    missions = [(k, 0, SimpleNamespace(target=t, start=(0.0, 0.0, 1.5))) for k, t in
                (("object", "car"), ("landmark", "water tower"))]
    monkeypatch.setattr(ev, "make_world", lambda world, seed: object())
    monkeypatch.setattr(ev, "seed_missions", lambda *a: missions)
    monkeypatch.setattr(ev, "EdgeChain", lambda *a, **k: None)
    part = tmp_path / "x.partial.json"
    seen: list = []

    def episode(cfg, world, seed, mission, policy, settings, chain, trace):
        seen.append(json.loads(part.read_text()) if part.exists() else None)
        return {"policy": policy, "success": True, "spl": 0.5 + 0.1 * len(seen), "path_m": 10.0 * len(seen),
                "false_finds": 0, "steps": 5, "cpu_ms_per_step": 1.0, "collided": False, "kind": mission.target}

    monkeypatch.setattr(ev, "_episode", episode)
    heads = itertools.count()
    monkeypatch.setattr(bench_meta, "git_commit", lambda: {"commit": f"c{next(heads)}", "dirty": False})
    argv = ["rayfronts", "eval", "search", "--json", "x.json"]
    cfg = SearchEvalConfig(policies=["frontier", "rayfronts"], seeds=[100, 101], resolution=32)
    doc = run_search_eval(cfg, argv=argv, partial_path=part)
    assert len(seen) == 8 and seen[0] is None and not part.exists()
    for i, got in enumerate(seen[1:], start=1):       # before episode i+1: the first i episodes, as run
        assert got["partial"] is True and got["meta"]["argv"] == argv and got["meta"]["commit"] == "c0"
        assert [r["path_m"] for r in got["episodes"]] == [10.0 * j for j in range(1, i + 1)]
        assert [(r["seed"], r["policy"]) for r in got["episodes"]] == \
            [(r["seed"], r["policy"]) for r in doc["episodes"][:i]]
        assert got["seeds"]["set"] == "held-out"
    assert len(doc["episodes"]) == 8 and "partial" not in doc
    assert doc["meta"]["commit"] in ("c0", "c1")      # the eval's start or run_meta's, both before episode 1
    assert next(heads) == 2                          # ... and git was read at no other time
