"""Figures and tables of a ``rayfronts eval srchvol`` run, made from the run directory's files.

Everything here reads what the run wrote (``steps.json``, ``summary.json``, ``run_info.json``),
so ``rayfronts eval report`` can (re)draw them for any run directory, old or new:

* ``plots/compare_scvr_<depth>.png``: one figure per depth limit, one line per method, the
  class-mean SCVR (%) over frames (the paper's Fig. 4 style). Methods not applicable at that
  depth (Table I's ``--``) are absent. The legend sits outside the axes, right of the data.
* ``table.csv``: the Table-I layout (one row per method; mIoU, SCV, Recall, SCVR AUCs in %
  per depth limit; empty cell = not applicable), next to ``table.md``.

Class mean at a frame = the mean over the classes still counted at that frame (a class stops
counting once more than half of its ground-truth voxels are observed; rows of stopped classes
carry NaN and are skipped), as in the AUC of ``summary.json``.
"""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

if TYPE_CHECKING:
    import matplotlib.figure

METRICS = (("mIoU", "miou_auc"), ("SCV", "scv_auc"), ("Recall", "recall_auc"), ("SCVR", "scvr_auc"))
#: one colour and line style per method, the same in every figure
STYLE = {
    "rayfronts": ("#d62728", "-"),
    "semantic_poses": ("#1f77b4", "--"),
    "semantic_voxels": ("#2ca02c", "-."),
    "spherical_semfronts": ("#9467bd", ":"),
    "unidirectional_semfronts": ("#ff7f0e", (0, (5, 1, 1, 1))),
}


METHOD_TITLES = {
    "rayfronts": "RayFronts",
    "semantic_poses": "Sem Poses",
    "semantic_voxels": "Sem Voxels",
    "spherical_semfronts": "Spherical Sem Fronts",
    "unidirectional_semfronts": "Unidirectional Sem Fronts",
}
"""Display names of the search-volume methods (here, not in :mod:`apps.evaluation.srchvol`, which
imports this module: the figures need no evaluation imports)."""


def _titles() -> dict:
    return dict(METHOD_TITLES)


def _depth_key(d: float) -> str:
    return f"{float(d):g}m"


def load_run(run_dir: str | Path) -> tuple[list[dict], dict, dict]:
    """(rows of steps.json, summary keyed by depth, run_info) of a srchvol run directory."""
    run = Path(run_dir)
    rows = json.loads((run / "steps.json").read_text())
    info = json.loads((run / "run_info.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    depths = sorted({float(r["depth_limit"]) for r in rows})
    if len(depths) == 1 and _depth_key(depths[0]) not in summary:  # a one-depth run stores that depth's dict
        summary = {_depth_key(depths[0]): summary}
    return rows, summary, info


def class_mean_curves(rows: list[dict]) -> dict:
    """{depth: {method: [(step, mean SCVR over counted classes), ...]}} from steps rows."""
    acc: dict = {}
    for r in rows:
        v = r.get("scvr")
        if v is None or not math.isfinite(float(v)):
            continue
        key = (float(r["depth_limit"]), r["method"], int(r["step"]))
        s, n = acc.get(key, (0.0, 0))
        acc[key] = (s + float(v), n + 1)
    out: dict = {}
    for (d, m, step), (s, n) in sorted(acc.items()):
        out.setdefault(d, {}).setdefault(m, []).append((step, s / n))
    return out


def figure_for_depth(d: float, per: dict, titles: dict | None = None) -> matplotlib.figure.Figure:
    """The matplotlib figure comparing the methods ``per`` = {method: [(step, scvr)]} at depth ``d``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    titles = _titles() if titles is None else titles
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    for m in sorted(per, key=lambda k: (list(STYLE).index(k) if k in STYLE else 99, k)):
        pts = per[m]
        colour, ls = STYLE.get(m, (None, "-"))
        ax.plot([p[0] for p in pts], [100 * p[1] for p in pts], color=colour, ls=ls, lw=1.8,
                marker="o" if len(pts) < 12 else None, ms=3, label=titles.get(m, m))
    ax.set_xlabel("frame")
    ax.set_ylabel("SCVR (%), class mean")
    ax.set_title(f"Search-volume efficiency over time, depth limit {d:g} m" + (" (no depth)" if d == 0 else ""))
    ax.grid(True, alpha=0.3)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, frameon=False, fontsize=8)
    fig.tight_layout()
    return fig


def compare_figures(run_dir: str | Path, rows: list[dict] | None = None, dpi: int = 110) -> list[Path]:
    """Write ``plots/compare_scvr_<depth>.png`` for every depth limit; return the paths."""
    import matplotlib.pyplot as plt

    run = Path(run_dir)
    if rows is None:
        rows = load_run(run)[0]
    titles = _titles()
    pdir = run / "plots"
    pdir.mkdir(exist_ok=True)
    paths = []
    for d, per in sorted(class_mean_curves(rows).items()):
        fig = figure_for_depth(d, per, titles)
        p = pdir / f"compare_scvr_{_depth_key(d)}.png"
        fig.savefig(p, dpi=dpi, bbox_inches="tight")
        plt.close(fig)
        paths.append(p)
    return paths


def table_csv(summary: dict, methods: Sequence[str] | None = None, depth_keys: Iterable[str] | None = None) -> str:
    """Table I as CSV text: ``method, <depth> mIoU (%), <depth> SCV (%), ...``; empty = not applicable."""
    depth_keys = list(depth_keys or sorted(summary, key=lambda k: float(k.rstrip("m"))))
    if methods is None:
        seen: list = []
        for dk in depth_keys:
            seen += [m for m in summary[dk] if m not in seen]
        methods = seen
    titles = _titles()
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method"] + [f"{dk} {name} (%)" for dk in depth_keys for name, _ in METRICS])
    for m in methods:
        row = [titles.get(m, m)]
        for dk in depth_keys:
            s = (summary.get(dk) or {}).get(m)
            for _, key in METRICS:
                v = None if s is None else s.get(key)
                row.append("" if v is None or not math.isfinite(float(v)) else f"{100 * float(v):.2f}")
        w.writerow(row)
    return buf.getvalue()


def write_figures(run_dir: str | Path) -> list[Path]:
    """The comparison figures and ``table.csv`` of one srchvol run directory."""
    run = Path(run_dir)
    rows, summary, info = load_run(run)
    methods = (info.get("config") or {}).get("methods")
    (run / "table.csv").write_text(table_csv(summary, methods))
    return compare_figures(run, rows)
