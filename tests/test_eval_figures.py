"""Evaluation pictures: one figure per depth limit comparing the methods (class-mean SCVR over
time, legend outside the data), the Table-I table as CSV, and ``eval report`` on one page.
The inputs are hand-written run directories, so every expected number is computed by hand."""
from __future__ import annotations

import csv
import io
import json
import math

import pytest

from apps.evaluation.figures import class_mean_curves, figure_for_depth, table_csv, write_figures


def _row(d, m, step, cls, scvr):
    return {"depth_limit": d, "method": m, "step": step, "class_id": cls, "class_name": f"c{cls}", "scvr": scvr}


ROWS = [
    _row(0.0, "rayfronts", 8, 1, 0.2), _row(0.0, "rayfronts", 8, 2, 0.4),
    _row(0.0, "rayfronts", 16, 1, 0.6), _row(0.0, "rayfronts", 16, 2, float("nan")),  # class 2 stopped
    _row(0.0, "semantic_poses", 8, 1, 0.1), _row(0.0, "semantic_poses", 16, 1, 0.05),
    _row(10.0, "rayfronts", 8, 1, 0.5), _row(10.0, "semantic_voxels", 8, 1, 0.25),
]
SUMMARY = {
    "0m": {"rayfronts": {"miou_auc": 0.1, "scv_auc": 0.2, "recall_auc": 0.3, "scvr_auc": 0.4},
           "semantic_poses": {"miou_auc": 0.0, "scv_auc": 0.5, "recall_auc": 0.25, "scvr_auc": 0.125},
           "semantic_voxels": None},
    "10m": {"rayfronts": {"miou_auc": 0.5, "scv_auc": 0.6, "recall_auc": 0.7, "scvr_auc": 0.8},
            "semantic_poses": None,
            "semantic_voxels": {"miou_auc": 0.1, "scv_auc": 0.1, "recall_auc": 0.1, "scvr_auc": float("nan")}},
}
METHODS = ["rayfronts", "semantic_poses", "semantic_voxels"]


def _run_dir(tmp_path):
    run = tmp_path / "sv"
    run.mkdir()
    (run / "steps.json").write_text(json.dumps([{k: (None if isinstance(v, float) and math.isnan(v) else v)
                                                 for k, v in r.items()} for r in ROWS]))
    (run / "summary.json").write_text(json.dumps(
        {dk: {m: (None if s is None else {k: (None if math.isnan(v) else v) for k, v in s.items()})
              for m, s in per.items()} for dk, per in SUMMARY.items()}))
    info = {"kind": "srchvol", "source": "synthetic", "frames": 16, "resolution": [48, 48], "fov_deg": [90, 90],
            "encoder": "label", "encoder_version": "1", "text_model": "minilm", "cone_half_angle_deg": 45.0,
            "scene_volume_voxels": 10, "classes_evaluated": ["c1", "c2"], "timings_s": {"total": 1.0},
            "config": {"vox": 1.0, "preset": "offline", "map": {}, "every": 8, "cone_shape": "cone",
                       "srchvol_thresh": 0.5, "temperature": 1.0, "denoise": False, "pred_thresh": 0.5,
                       "scene_volume": "gt", "gt_range": 25.0, "methods": METHODS}}
    (run / "run_info.json").write_text(json.dumps(info))
    (run / "table.md").write_text("| Method | x |\n|---|---:|\n| RayFronts | 1 |\n")
    return run


def test_class_mean_skips_stopped_classes():
    c = class_mean_curves(ROWS)
    assert c[0.0]["rayfronts"] == [(8, pytest.approx(0.3)), (16, pytest.approx(0.6))]
    assert c[0.0]["semantic_poses"] == [(8, pytest.approx(0.1)), (16, pytest.approx(0.05))]
    assert set(c) == {0.0, 10.0} and set(c[10.0]) == {"rayfronts", "semantic_voxels"}


def test_one_figure_per_depth_with_every_method_and_the_legend_outside():
    c = class_mean_curves(ROWS)
    fig = figure_for_depth(0.0, c[0.0])
    ax = fig.axes[0]
    assert len(ax.lines) == 2
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["RayFronts", "Sem Poses"]
    assert list(ax.lines[0].get_ydata()) == pytest.approx([30.0, 60.0])
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    leg = ax.get_legend().get_window_extent(r)
    box = ax.get_window_extent(r)
    assert leg.x0 >= box.x1, (leg, box)  # the legend covers no data


def test_table_csv_matches_summary():
    rows = list(csv.reader(io.StringIO(table_csv(SUMMARY, METHODS))))
    assert rows[0] == ["method"] + [f"{d} {n} (%)" for d in ("0m", "10m") for n in ("mIoU", "SCV", "Recall", "SCVR")]
    by = {r[0]: r[1:] for r in rows[1:]}
    assert len(by) == 3
    rf = by["RayFronts"]
    assert rf == ["10.00", "20.00", "30.00", "40.00", "50.00", "60.00", "70.00", "80.00"]
    poses = by["Sem Poses"]
    assert poses[:4] == ["0.00", "50.00", "25.00", "12.50"] and poses[4:] == [""] * 4  # not applicable at 10 m
    vox = by["Sem Voxels"]
    assert vox[:4] == [""] * 4 and vox[7] == ""  # NaN -> empty


def test_write_figures_and_report_page(tmp_path):
    from apps.evaluation.report import write_report

    run = _run_dir(tmp_path)
    paths = write_figures(run)
    assert [p.name for p in paths] == ["compare_scvr_0m.png", "compare_scvr_10m.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    assert (run / "table.csv").read_text().startswith("method,")
    page = write_report([run], tmp_path / "page" / "report.md")
    text = page.read_text()
    assert "](../sv/plots/compare_scvr_0m.png)" in text and "](../sv/plots/compare_scvr_10m.png)" in text
    assert "](../sv/table.csv)" in text and "| RayFronts | 1 |" in text
