"""``rayfronts eval report``: collect srchvol / semseg run directories into one Markdown page.

Each run directory holds ``run_info.json`` (kind, configuration, encoder, data) and
``summary.json``; srchvol runs also ``steps.json``, ``table.md`` and ``plots/*.png`` (linked
relative to the page). Semseg runs are gathered into one table with the mean over runs (scenes).

One page per report: for each srchvol run the settings, the Table-I table (Markdown, with a
link to the same table as CSV), one figure per depth limit comparing all methods (SCVR over
time; :mod:`apps.evaluation.figures` redraws them from ``steps.json``, so older run
directories get them too), then the per-method plots folded away in a ``<details>`` block.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Iterable


def _load(run: Path) -> dict:
    info_p, sum_p = run / "run_info.json", run / "summary.json"
    if not info_p.is_file() or not sum_p.is_file():
        raise FileNotFoundError(f"{run}: not a run directory (run_info.json / summary.json missing)")
    return dict(dir=run, info=json.loads(info_p.read_text()), summary=json.loads(sum_p.read_text()))


def _mean(vals):
    v = [x for x in vals if x is not None and math.isfinite(x)]
    return sum(v) / len(v) if v else float("nan")


def write_report(run_dirs: Iterable[str | Path], out_file: str | Path, title: str = "RayFronts benchmark results"
                 ) -> Path:
    """Write the Markdown page ``out_file`` for ``run_dirs``; return its path."""
    from apps.evaluation.semseg import semseg_table

    out = Path(out_file)
    out.parent.mkdir(parents=True, exist_ok=True)
    runs = [_load(Path(r)) for r in run_dirs]
    lines = [f"# {title}", ""]
    sv = [r for r in runs if r["info"].get("kind") == "srchvol"]
    ss = [r for r in runs if r["info"].get("kind") == "semseg"]
    if sv:
        lines += ["## Online search volume (Table I protocol)", "",
                  "AUC over time of mIoU (observed region), SCV, Recall and SCVR, in %; a class stops "
                  "counting once more than half of its GT voxels are observed; mean over classes. "
                  "`--` = not applicable at that depth (as in the paper).", ""]
        for r in sv:
            info = r["info"]
            c = info["config"]
            lines += [f"### {r['dir'].name}", "",
                      f"- data: `{info.get('source')}`, {info.get('frames')} frames at "
                      f"{info['resolution'][0]}×{info['resolution'][1]}, FoV {info['fov_deg'][0]:.0f}°",
                      f"- encoder: `{info.get('encoder')}` ({info.get('encoder_version')}, text model "
                      f"{info.get('text_model')})",
                      f"- voxel {c['vox']} m, preset `{c['preset']}`, map overrides `{c['map']}`, evaluated every "
                      f"{c['every']} frames; search shape `{c['cone_shape']}` (half-angle "
                      f"{info.get('cone_half_angle_deg', float('nan')):.1f}°), threshold {c['srchvol_thresh']}, "
                      f"softmax T={c['temperature']}, denoise {c['denoise']}, prediction threshold {c['pred_thresh']}",
                      f"- scene volume: `{c['scene_volume']}` ({info.get('scene_volume_voxels')} voxels, GT range "
                      f"{c['gt_range']} m); classes: {', '.join(info.get('classes_evaluated', []))}",
                      f"- time: {info.get('timings_s', {}).get('total', float('nan')):.0f} s", ""]
            compare = []
            if (r["dir"] / "steps.json").is_file():
                from apps.evaluation.figures import write_figures

                compare = write_figures(r["dir"])
            tab = r["dir"] / "table.md"
            if tab.is_file():
                lines += [tab.read_text(), ""]
            if (r["dir"] / "table.csv").is_file():
                lines += [f"(as CSV: [table.csv]({os.path.relpath(r['dir'] / 'table.csv', out.parent)}))", ""]
            for p in compare:
                lines += [f"![{p.stem}]({os.path.relpath(p, out.parent)})", ""]
            per = [p for p in sorted((r["dir"] / "plots").glob("*.png")) if p not in compare] \
                if (r["dir"] / "plots").is_dir() else []
            if per:
                lines += ["<details><summary>per-method plots (each class and the class mean)</summary>", ""]
                for p in per:
                    lines += [f"![{p.stem}]({os.path.relpath(p, out.parent)})", ""]
                lines += ["</details>", ""]
    if ss:
        lines += ["## Offline 3D semantic segmentation (Tables II/III protocol)", "",
                  "Without background = background classes ignored; `bg` = all classes. In %.", ""]
        table = {r["dir"].name: r["summary"] for r in ss}
        keys = ("miou", "fmiou", "acc", "miou_bg", "fmiou_bg", "acc_bg")
        if len(ss) > 1:
            table["mean over runs"] = {k: _mean([r["summary"].get(k) for r in ss]) for k in keys}
        lines += [semseg_table(table), ""]
        for r in ss:
            info = r["info"]
            c = info["config"]
            lines += [f"- `{r['dir'].name}`: data `{info.get('source')}` ({info.get('frames')} frames at "
                      f"{info['resolution'][0]}×{info['resolution'][1]}), encoder `{info.get('encoder')}`, voxel "
                      f"{c['vox']} m, k={c['k']}, templates={c['templates']}, {info.get('n_gt_voxels')} GT voxels"]
        lines.append("")
    if not sv and not ss:
        raise ValueError("no srchvol or semseg runs among the given directories")
    out.write_text("\n".join(lines))
    return out
