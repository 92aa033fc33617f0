"""Benchmark metadata (apps.bench.meta via the dispatcher), `bench all`, the README table."""
import json
import os
import subprocess
import sys
import time

import pytest

from apps.bench import meta, report
from apps.cli import main


def _burn(seconds: float) -> None:
    t = time.thread_time()
    while time.thread_time() - t < seconds:
        pass


def test_section_separates_cpu_from_wall():
    """A CPU-bound section shows its CPU time; a sleeping one shows wall time but ~no CPU."""
    meta.reset()
    with meta.timed("burn", frames=4) as a:
        _burn(0.2)
    with meta.timed("sleep", frames=4) as b:
        time.sleep(0.25)
    assert a.result["cpu_s"] >= 0.18 and a.result["calling_thread_cpu_s"] >= 0.18
    assert abs(a.result["cpu_ms_per_frame"] - 1e3 * a.result["cpu_s"] / 4) < 1e-6
    assert b.result["wall_s"] >= 0.24 and b.result["cpu_s"] < 0.1
    assert b.result["cpu_ms_per_frame"] < 25 and b.result["wall_ms_per_frame"] >= 60
    assert [s["name"] for s in meta.sections()] == ["burn", "sleep"]
    assert len(a.result["load_before"]) == 3 and len(a.result["load_after"]) == 3


def test_attach_picks_main_section_and_whole_run_fallback():
    m = {"process": {"cpu_s": 2.0}, "sections": [{"name": "x", "frames": 10, "cpu_ms_per_frame": 5.0,
                                                  "frames_per_s": 50.0},
                                                 {"name": "y", "frames": 10, "cpu_ms_per_frame": 9.0,
                                                  "frames_per_s": 20.0}]}
    r = meta.attach({"frames": 10, "main_section": "y"}, m)
    assert r["cpu_ms_per_frame"] == 9.0 and r["frames_per_s"] == 20.0 and r["meta"] is m
    assert "cpu_ms_per_frame" not in meta.attach({"frames": 10}, m)  # two sections, no main: none chosen
    r = meta.attach({"frames": 4}, {"process": {"cpu_s": 2.0}, "sections": []})
    assert r["cpu_ms_per_frame_whole_run"] == 500.0
    assert meta.attach({"frames": 4, "cpu_ms_per_frame": {"edge": 1}}, m)["cpu_ms_per_frame"] == {"edge": 1}


def test_interleaved_alternates():
    calls = []
    out = meta.interleaved({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, reps=3, warmup=1)
    assert calls == ["a", "b"] * 4
    assert sorted(out) == ["a", "b"] and all(len(v) == 3 for v in out.values())


def test_dispatcher_wraps_every_target(tmp_path, capsys):
    f = tmp_path / "w.json"
    assert main(["bench", "world", "--frames", "2", "--json", str(f)]) == 0
    d = json.loads(f.read_text())
    assert json.loads(capsys.readouterr().out) == d
    m = d["meta"]
    assert m["machine"]["logical_cores"] == os.cpu_count() and m["machine"]["cpu_model"]
    assert len(m["load_before"]) == 3 and len(m["load_after"]) == 3
    assert m["process"]["cpu_s"] > 0 and m["process"]["wall_s"] > 0
    assert m["argv"][:3] == ["rayfronts", "bench", "world"] and "--frames" in m["argv"]
    names = [s["name"] for s in m["sections"]]
    assert names == ["render_224x224", "render_640x480"]
    assert d["cpu_ms_per_frame_224x224"] == m["sections"][0]["cpu_ms_per_frame"] > 0
    assert d["fps_224x224"] > 0


def test_bench_all_quick_and_table(tmp_path, monkeypatch):
    """`bench all --quick` on two runs writes their JSONs, all.json and table.md; `bench
    table --readme` puts the table between the markers and is idempotent."""
    monkeypatch.chdir(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = tmp_path / "b"
    assert main(["bench", "all", "--quick", "--only", "world,mapper_kernels_vs_torch", "--json", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["all.json", "mapper_kernels_vs_torch.json", "table.md",
                                                     "world.json"]
    mk = json.loads((out / "mapper_kernels_vs_torch.json").read_text())
    assert mk["maps_identical"] is True and set(mk["sides"]) == {"kernels", "torch"}
    assert mk["meta"]["argv"][:3] == ["rayfronts", "bench", "mapper"]
    assert mk["sides"]["kernels"]["frames"] == mk["sides"]["torch"]["frames"] == 10
    table = (out / "table.md").read_text()
    assert table.startswith("Machine: ") and "QUICK" in table
    rows = [r for r in table.splitlines() if r.startswith("| ") and not r.startswith("| run ")]
    assert [r.split(" | ")[0] for r in rows] == ["| mapper_kernels_vs_torch", "| world"]
    assert "`rayfronts bench world --frames 2`" in rows[1] and " → " in rows[1]
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\ntext\n")
    assert main(["bench", "table", str(out), "--readme", str(readme)]) == 0
    once = readme.read_text()
    assert main(["bench", "table", str(out), "--readme", str(readme)]) == 0
    assert readme.read_text() == once and once.count(report.BEGIN) == 1 and table in once
    assert main(["bench", "all", "--only", "nope", "--json", str(out)]) == 2
    assert main(["bench", "table", str(tmp_path / "missing")]) == 2


def test_bench_all_lists_every_readme_figure():
    """Each README run names an existing target and a different JSON."""
    from apps.bench import ALL, TARGETS
    names = [n for n, _, _ in ALL]
    assert len(set(names)) == len(names)
    for _, full, quick in ALL:
        assert full[0] in TARGETS and quick[0] == full[0]
    assert sys.modules["apps.bench"].run_all is not None


def test_bench_search_quick(tmp_path):
    """`bench search` on a small map: every stage timed, look-next goals from the frames'
    frontiers, the three occupancy queries measured; the JSON carries the meta block."""
    f = tmp_path / "s.json"
    assert main(["bench", "search", "--voxels", "5k", "--queries", "2", "--rays", "50", "--frames", "2",
                 "--standing-rounds", "1", "--json", str(f)]) == 0
    d = json.loads(f.read_text())
    row = d["sizes"]["5k"]
    assert row["voxels"] >= 5000 and row["frontiers"] > 0 and row["look_next"] > 0
    assert {"encode", "similarity", "instances", "look_next", "beyond", "total"} <= set(row["stage_p50_ms"])
    assert row["search_ms"]["n"] == 2 and row["search_ms"]["p50"] > 0
    assert set(row["occupancy_ms"]) == {"box_40x40x6m", "slice_80x80m", "points_1000_r1m", "points_1000_r1m_first"}
    sm = row["standing_ms"]
    assert sm["one"]["n"] == sm["three"]["n"] == 1 and sm["ratio"] == pytest.approx(
        sm["three"]["p50"] / sm["one"]["p50"])
    head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    assert d["meta"]["commit"].split("+")[0] == head
    assert d["meta"]["process"]["cpu_s"] > 0 and "search_5k" in [s["name"] for s in d["meta"]["sections"]]


def test_bench_mapper_growing_control_is_the_last_frames_on_an_empty_map(tmp_path):
    """``bench mapper --growing``: windows tile the frames, and ``growth_control`` is the last
    window's frames fed to an empty map — its voxel count equals a map built here from those
    frames alone (same renders and features, drawn in frame order), and its ratios are the
    quotients of the reported CPU figures."""
    import argparse

    from apps.bench import mapper as bench_mapper
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap

    f = tmp_path / "g.json"
    assert main(["bench", "mapper", "--preset", "throughput", "--frames", "24", "--growing", "--window", "8",
                 "--json", str(f)]) == 0
    d = json.loads(f.read_text())
    w, c = d["windows"], d["growth_control"]
    assert [x["frames"] for x in w] == [[0, 8], [8, 16], [16, 24]] and c["frames"] == [16, 24]
    assert c["content_ratio"] == round(c["fresh_map_cpu_ms_per_frame"] / w[0]["cpu_ms_per_frame"], 3)
    assert c["map_size_ratio"] == round(w[-1]["cpu_ms_per_frame"] / c["fresh_map_cpu_ms_per_frame"], 3)
    assert d["growth_cpu_ratio"] == round(w[-1]["cpu_ms_per_frame"] / w[0]["cpu_ms_per_frame"], 3)
    assert d["growth_cpu_ratio_from_second"] == round(w[-1]["cpu_ms_per_frame"] / w[1]["cpu_ms_per_frame"], 3)
    assert set(c["stage_ms_per_frame"]) >= {"frontiers", "fuse", "total"}
    p = argparse.ArgumentParser()
    bench_mapper.add_arguments(p)
    args = p.parse_args(["--preset", "throughput", "--frames", "24"])
    frames, K, _ = bench_mapper._render_frames(args, (224, 224))
    m = RayFrontsMap(map_config("throughput", {"depth_limit": args.depth_limit}), args.feature_dim, "bench")
    for pose, depth, rgb, feat in frames[16:24]:
        m.integrate(pose, K, depth, rgb, feat)
    m.flush()
    assert c["n_voxels"] == m.n_voxels() > 0 and c["n_voxels"] < w[-1]["n_voxels"]
