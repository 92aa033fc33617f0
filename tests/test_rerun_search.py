"""Search answers in the mapper's rerun recording: the found instances as boxes whose class
ids are the instances' stable ids, read back by rerun's own CLI (``rerun rrd stats``)."""
from __future__ import annotations

import subprocess

import numpy as np

from common.search_messages import SearchReply


def test_search_instances_logged_as_boxes_with_ids(tmp_path):
    from mapper.outputs.rerun import RerunLogger, search_boxes
    from mapper.outputs.rerun_view import rerun_binary

    rep = SearchReply(found=[{"id": 7, "target": "car", "box_min": [1.0, 2.0, 0.0], "box_max": [3.0, 3.0, 1.5],
                              "centroid": [2.0, 2.5, 0.7], "confidence": 0.91},
                             {"id": 12, "target": "car", "box_min": [-4.0, 0.0, 0.0], "box_max": [-3.0, 2.0, 1.0],
                              "centroid": [-3.5, 1.0, 0.5], "confidence": 0.6}],
                      look_next=[{"position": [0.0, 1.0, 1.0], "score": 0.4, "heading_rad": 0.0}])
    b = search_boxes(rep)
    np.testing.assert_allclose(b["centers"], [[2.0, 2.5, 0.75], [-3.5, 1.0, 0.5]])
    np.testing.assert_allclose(b["half_sizes"], [[1.0, 0.5, 0.75], [0.5, 1.0, 0.5]])
    assert b["ids"].tolist() == [7, 12] and b["labels"] == ["car #7 0.91", "car #12 0.60"]
    path = tmp_path / "s.rrd"
    lg = RerunLogger("rayfronts_test", file=str(path))
    lg.log_search(["car"], rep, 3)
    lg.log_search(["bench"], SearchReply(), 4)          # nothing found: cleared, no error
    lg.close()
    out = subprocess.run([rerun_binary(), "rrd", "stats", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for ent in ("/world/searches/car/instances", "/world/searches/car/goals", "/world/searches/bench/instances"):
        assert ent in out.stdout, f"{ent} not in the recording:\n{out.stdout[:3000]}"
