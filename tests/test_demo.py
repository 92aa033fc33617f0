"""``rayfronts demo`` end to end: router, mapper and edge processes, results.json, demo.rrd."""
import json

import pytest

from apps.demo import DemoConfig, done_criteria, run_demo, summary_table

MAIN = ("water tower", "vehicle", "chimney", "radio tower", "tree")


@pytest.mark.timeout(400)
def test_demo_results_and_recording(tmp_path):
    cfg = DemoConfig(out=tmp_path, frames=80)
    res = run_demo(cfg, progress=False)
    data = json.loads((tmp_path / "results.json").read_text())
    assert 72 <= data["frames"] <= 80  # the edge's one-slot queue may replace a frame or two
    assert set(data) >= {"queries", "frames", "seconds", "settings"}
    st = data["settings"]
    assert st["frames"] == 80 and st["depth_limit_m"] == cfg.depth_limit and st["vox_size_m"] == cfg.vox_size
    assert st["queries"] == list(cfg.queries) and st["router_endpoint"].startswith("tcp/127.0.0.1:")
    for q in data["queries"]:
        assert set(q) >= {"query", "class", "in_range", "best_voxel", "best_ray", "judged_by", "search_volume_m3"}
        assert q["judged_by"] == ("best_voxel" if q["in_range"] else "best_ray")
        assert set(q["best_voxel"]) == {"xyz", "score", "error_m"}
        assert set(q["best_ray"]) == {"origin", "direction", "score", "miss_m"}
    by = {q["query"]: q for q in data["queries"]}
    assert by["vehicle"]["class"] == "car" and by["water tower"]["class"] == "water tower"
    assert not by["water tower"]["in_range"] and by["vehicle"]["in_range"]
    assert by["radio tower"]["class"] == "radio tower" and not by["radio tower"]["in_range"]
    assert by["chimney"]["in_range"] and by["tree"]["in_range"]
    main = {"queries": [by[q] for q in MAIN], "frames": data["frames"], "seconds": data["seconds"]}
    assert done_criteria(main, cfg.vox_size) == [], summary_table(data, cfg.vox_size)
    assert all(v == 0 for v in res["exit_codes"].values()), res["exit_codes"]
    # the mapper's rerun recording reads back with the layers
    import rerun as rr

    reader = rr.chunk.RrdReader(str(tmp_path / "demo.rrd"))
    paths = {str(c.entity_path) for c in reader.stream().to_chunks()}
    text = "\n".join(sorted(paths))
    for needle in ("/camera", "/camera/image/rgb", "/camera/image/depth", "world/map/voxels",
                   "world/map/frontiers", "world/map/rays", "world/queries/"):
        assert needle in text, f"{needle} not in recording entities:\n{text}"


def test_progress_line_has_no_carriage_return_off_a_terminal():
    import io

    from apps.demo import Progress

    buf = io.StringIO()  # not a TTY
    p = Progress(buf, every_s=3600.0)
    p.update("frames 1")
    p.update("frames 2")           # within the interval: not printed
    p.update("frames 3 done", force=True)
    p.end()
    out = buf.getvalue()
    assert "\r" not in out
    assert out.splitlines() == ["frames 1", "frames 3 done"]

    class Tty(io.StringIO):
        def isatty(self):
            return True

    t = Tty()
    p = Progress(t)
    p.update("a")
    p.update("b")
    p.end()
    assert t.getvalue().count("\r") == 2 and t.getvalue().endswith("\n")
