"""``rayfronts eval merge``: runs split by seed or policy give back the one run's document.

The reference is a committed ``rayfronts eval search`` run over six seeds and two policies
(benchmarks/eval_search_ground_10m_seeds18-23.json, written by run_search_eval in one
process): split into parts by seed and by policy, merged in scrambled order, the rows come
back in the run's order and every per-policy summary equals the one the run computed.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from apps.closed_loop.merge import merge_documents

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "benchmarks" / "eval_search_ground_10m_seeds18-23.json"


def _run() -> dict:
    return json.loads(RUN.read_text())


def _part(doc: dict, seeds: list[int], policies: list[str]) -> dict:
    d = copy.deepcopy(doc)
    d["episodes"] = [r for r in d["episodes"] if r["seed"] in seeds and r["policy"] in policies]
    d["settings"]["seeds"] = list(seeds)
    d["settings"]["policies"] = list(policies)
    d["policies"] = {}                       # a part's own summary is not what the merge uses
    return d


def test_parts_by_seed_merge_back_into_the_run():
    run = _run()
    assert len(run["settings"]["seeds"]) == 6 and len(run["episodes"]) == 12
    pol = run["settings"]["policies"]
    parts = [_part(run, [22, 23, 18], pol), _part(run, [21, 19, 20], pol)]
    out = merge_documents(parts)
    assert out["episodes"] == run["episodes"]
    assert out["policies"] == run["policies"]
    assert out["settings"]["seeds"] == run["settings"]["seeds"]
    assert [p["seeds"] for p in out["merged_from"]] == [[22, 23, 18], [21, 19, 20]]
    assert out["seeds"]["set"] == "development" and "partial" not in out


def test_parts_by_policy_merge_back_into_the_run():
    run = _run()
    a, b = run["settings"]["policies"]
    out = merge_documents([_part(run, run["settings"]["seeds"], [b]), _part(run, run["settings"]["seeds"], [a])])
    assert out["episodes"] == run["episodes"]
    assert out["policies"] == run["policies"]
    assert out["settings"]["policies"] == [a, b]


def test_refusals_name_what_is_wrong():
    run = _run()
    one, two = _part(run, [18], ["rayfronts"]), _part(run, [19], ["rayfronts"])
    other = copy.deepcopy(two)
    other["settings"]["depth_limits"] = [20.0]
    with pytest.raises(ValueError, match="depth_limits"):
        merge_documents([one, other])
    finer = copy.deepcopy(two)
    finer["settings"]["angle_bin_deg"] = 3.0                 # --angle-bin 3 beside a run at the preset's bins
    with pytest.raises(ValueError, match="angle_bin_deg"):
        merge_documents([one, finer])
    with pytest.raises(ValueError, match="seed 18 .* more than one part"):
        merge_documents([one, copy.deepcopy(one)])
    half = dict(copy.deepcopy(two), partial=True)
    with pytest.raises(ValueError, match="partial"):
        merge_documents([one, half])
    cut = dict(_part(run, [19, 20], ["rayfronts"]), partial=True)
    cut["episodes"] = [r for r in cut["episodes"] if r["seed"] == 19]        # seed 20 never finished
    got = merge_documents([one, cut], allow_partial=True)
    assert got["partial"] is True and got["settings"]["seeds"] == [18, 19]
    assert [p["seeds"] for p in got["merged_from"]] == [[18], [19]]
    with pytest.raises(ValueError, match="nothing to merge"):
        merge_documents([])
    with pytest.raises(ValueError, match="not an eval search document"):
        merge_documents([one, {"policies": {}}])


def test_cli_writes_the_merged_table(tmp_path, capsys):
    from apps.cli import main

    run = _run()
    files = []
    for i, seeds in enumerate(([18, 19, 20], [21, 22, 23])):
        f = tmp_path / f"part{i}.json"
        f.write_text(json.dumps(_part(run, seeds, run["settings"]["policies"])))
        files.append(str(f))
    out = tmp_path / "merged.json"
    assert main(["eval", "merge", *files, "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["episodes"] == run["episodes"] and doc["policies"] == run["policies"]
    md = out.with_suffix(".md").read_text()
    assert md.splitlines()[2].startswith(f"| rayfronts | 6 | {run['policies']['rayfronts']['success']:.2f} |")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    capsys.readouterr()
    assert main(["eval", "merge", files[0], str(bad), "--json", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot read" in err[0] and "bad.json" in err[0]
