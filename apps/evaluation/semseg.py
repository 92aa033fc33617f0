"""Offline zero-shot 3D semantic segmentation (paper §IV-B, Tables II/III; docs/method.md#evaluation).

1. Map the sequence with semantic voxels only (``RayFrontsMap`` with ``semantic_rays=False``
   — the reference's SemanticVoxelMap; semantic pruning is off, ``sem_pruning_period = -1``,
   so the occupancy grid does not change the voxels).
2. Predict every voxel: softmax (temperature) over the class-name text embeddings (raw
   names, or the mean of the encoder's prompt templates with ``templates=true``), prompt
   denoising over the **whole map** (the reference denoises per chunk), prediction
   threshold (below → 0 = no prediction).
3. GT voxels: the synthetic world's exact ``voxel_labels`` of the voxels the GT pass
   observes as occupied, or for datasets the majority of the fused one-hot GT label images
   (label 0 = unlabelled, not evaluated) at the same voxel size, or — for sources without
   label images (NICE-SLAM Replica) — an external labelled point cloud (``gt_points``,
   :mod:`apps.evaluation.gt_points`) voxelised by majority vote.
4. Align (exact grid, ``k = 0``, or kNN majority, default ``k = 5``) and score mIoU, f-mIoU,
   Acc with and without the background classes.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Sequence

import numpy as np
import torch

from apps.evaluation import metrics
from apps.evaluation.data import load_frames
from apps.evaluation.language import eval_language
from apps.evaluation.srchvol import _json_safe
from common.config import ConfigError, field_, section, to_dict
from edge.sources.config import SourceConfig
from encoders.config import EncoderConfig

if TYPE_CHECKING:
    from encoders import ImageEncoder
    from semantic_map.query import Similarity
    from synthetic_world import World

#: the reference's background classes (Replica; ScanNet adds the three "other*" classes)
BACKGROUND_REFERENCE = ["wall", "floor", "ceiling", "door", "window", "background", "otherprop", "otherstructure",
                        "otherfurniture"]
#: the synthetic world's background-like classes (its stand-ins for floor / wall / sky); ours, not the paper's
BACKGROUND_SYNTHETIC = ["sky", "ground", "road"]
BACKGROUND = BACKGROUND_REFERENCE + BACKGROUND_SYNTHETIC


def _default_source() -> SourceConfig:
    return SourceConfig(kind="synthetic", resolution="120x160", n_frames=40, hfov=90.0, depth_limit=None)


@dataclass
class SemsegConfig:
    source: SourceConfig = field_(_default_source(), "frame source (edge.sources keys)")
    encoder: EncoderConfig = section(EncoderConfig, "image encoder (label encoder by default)")
    map: dict = field_({}, "MapConfig overrides (on top of the 'offline' preset)")
    vox: float = field_(0.5, "voxel size (m); paper 0.05 indoor, 1.0 TartanAir")
    depth_range: float = field_(50.0, "depth beyond this (m) is ignored for mapping and GT (TartanAir cutoff)")
    k: int = field_(5, "alignment: k nearest predicted voxels majority vote; 0 = exact voxel grid")
    templates: Literal["auto"] | bool = field_(
        "auto", "class texts = mean of the 80 ImageNet/NACLIP prompt templates (true), raw names (false), or auto: "
                "templates for language encoders (naradio), raw names for label/sim (their features are name "
                "embeddings)")
    temperature: float = field_(100.0, "softmax temperature over classes")
    denoise: float = field_(0.5, "prompt denoising threshold over the whole map")
    pred_thresh: float = field_(0.1, "no prediction below this softmax value")
    background: list[str] = field_(
        list(BACKGROUND), "class names treated as background ('without background' columns): the reference's "
                          "list (wall, floor, ceiling, door, window, background, otherprop, otherstructure, "
                          "otherfurniture) plus the synthetic world's sky, ground, road; written to summary.json")
    text_model_dir: str = field_("", "text model directory for the class names (SigLIP for NARADIO; default "
                                     "<encoder.model_dir or $RAYFRONTS_MODEL_DIR>/siglip_text)")
    gt_points: str = field_("", "external GT: labelled points (.npz with xyz (N,3), labels (N,) [, class_names]; or "
                                ".ply with x, y, z and an integer vertex property gt_label_field) in the source's "
                                "world frame, voxelised by majority vote; needed where frames carry no labels "
                                "(NICE-SLAM Replica)")
    gt_label_field: str = field_("label", "vertex property of a .ply gt_points file holding the class id")
    class_names: list[str] = field_([], "class names (index = class id) where the source gives none; a gt_points "
                                        ".npz may carry them instead")
    occupancy_backend: str = field_("auto", "occupancy backend: auto | vdb | torch")
    device: str = field_("cpu", "torch device")
    progress: bool = field_(True, "tqdm progress bars")

    def validate(self) -> "SemsegConfig":
        if self.vox <= 0 or self.k < 0 or self.depth_range <= 0:
            raise ConfigError("need vox > 0, k >= 0 and depth_range > 0")
        return self


def class_text(enc: ImageEncoder, class_names: Sequence[str], templates: bool, model_dir: str = "") -> torch.Tensor:
    """(K, D) class-name embeddings in the encoder's language space (raw names, or the mean
    of the 80 ImageNet prompt templates); see :mod:`apps.evaluation.language`."""
    return eval_language(enc, class_names, templates, model_dir).text


def predict_labels(feats: torch.Tensor, text: torch.Tensor, temperature: float = 100.0, denoise: float = 0.5,
                   thresh: float = 0.1, similarity: Similarity | None = None) -> np.ndarray:
    """(N,) class id per feature row: argmax of softmax(temperature·cos) over the classes,
    classes whose maximum probability over **all** rows is < ``denoise`` disabled, 0 where
    the best probability is < ``thresh`` (class 0 itself is a valid prediction only if it
    names a real class; callers treat 0 as "none")."""
    from semantic_map.query import run_query

    n = feats.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    empty = torch.empty((0, feats.shape[1]))
    res = run_query(text, feats, torch.zeros((n, 3)), empty, torch.empty((0, 3)), torch.empty((0, 3)),
                    similarity=similarity, softmax=True, temperature=temperature, top_k=0, denoise=denoise,
                    threshold=thresh)
    lab = res.voxel_labels.cpu().numpy().astype(np.int64)
    return np.where(lab < 0, 0, lab)


def scores_with_without_bg(gt: np.ndarray, pred: np.ndarray, class_names: Sequence[str],
                           background: Sequence[str]) -> dict:
    """{miou, fmiou, acc} without background classes, {..._bg} with all, per_class."""
    present = sorted(int(c) for c in np.unique(gt) if c > 0)
    bg = {i for i, n in enumerate(class_names) if n.lower() in {b.lower() for b in background}}
    fg = [c for c in present if c not in bg]
    s_all = metrics.semseg_scores(gt, pred, present)
    s_fg = metrics.semseg_scores(gt, pred, fg) if fg else dict(miou=float("nan"), fmiou=float("nan"), acc=float("nan"))
    return dict(miou=s_fg["miou"], fmiou=s_fg["fmiou"], acc=s_fg["acc"], miou_bg=s_all["miou"],
                fmiou_bg=s_all["fmiou"], acc_bg=s_all["acc"],
                per_class={class_names[c]: dict(s_all["per_class"][c], background=c in bg) for c in present})


def run_semseg(cfg: SemsegConfig, out_dir: str | Path, world: World | None = None) -> dict:
    """Map, predict, align and score one sequence; write ``summary.json`` (and
    ``run_info.json``) into ``out_dir``; return the summary."""
    cfg.validate()
    from encoders import make_encoder
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    frames, src = load_frames(cfg.source, progress=False, world=world)
    if cfg.source.kind == "synthetic" and world is None:
        world = getattr(src, "world", None)
    ext = None
    if cfg.gt_points:
        from apps.evaluation.gt_points import load_labelled_points
        ext = load_labelled_points(cfg.gt_points, cfg.gt_label_field)
    if ext is None and any(f.labels is None for f in frames):
        raise ValueError(f"source {getattr(src, 'name', cfg.source.kind)!r} gives frames without GT labels; "
                         "pass external GT with gt_points=FILE")
    names = list(cfg.class_names or src.class_names or (ext[2] if ext is not None else None) or [])
    if not names:
        raise ValueError("no class names: the source gives none; set class_names or use a gt_points .npz "
                         "with class_names")
    if ext is not None and ext[1].size and ext[1].max() >= len(names):
        raise ValueError(f"GT point labels go up to {int(ext[1].max())} but there are only {len(names)} class names")
    needs_labels = cfg.encoder.kind in ("label", "sim")
    if needs_labels and any(f.labels is None for f in frames):
        raise ValueError(f"the {cfg.encoder.kind} encoder needs frames with GT labels; use encoder.kind=naradio")
    enc = make_encoder(cfg.encoder, names, device=cfg.device)
    from apps.evaluation.language import use_templates
    templates = use_templates(cfg.templates, enc)
    lang = eval_language(enc, names, templates, cfg.text_model_dir, device=cfg.device)
    over = dict(vox_size=cfg.vox, depth_limit=float(cfg.depth_range), semantic_rays=False,
                occ_pruning_period=-1, sem_pruning_period=-1)
    over.update(cfg.map)
    mc = map_config("offline", over)
    pmap = RayFrontsMap(mc, enc.feature_dim, enc.name, device=cfg.device, occupancy_backend=cfg.occupancy_backend)
    gcfg = map_config("offline", dict(vox_size=cfg.vox, depth_limit=float(cfg.depth_range), semantic_rays=False,
                                      occ_pruning_period=-1, sem_pruning_period=-1, interp_mode="nearest",
                                      vox_accum_period=mc.vox_accum_period))
    nc = len(names)
    gmap = RayFrontsMap(gcfg, nc, "gt-onehot", occupancy_backend=cfg.occupancy_backend)
    it = frames
    if cfg.progress:
        from tqdm import tqdm
        it = tqdm(frames, desc="semseg", unit="frame")
    for f in it:
        with torch.inference_mode():
            feats = enc.encode(f.rgb, f.labels) if needs_labels else enc.encode(f.rgb)
        pmap.integrate(f.pose, f.intrinsics, f.depth, f.rgb, feats, None)
        if ext is not None:
            continue
        assert f.labels is not None        # checked above: without gt_points every frame has labels
        onehot = torch.nn.functional.one_hot(torch.as_tensor(f.labels.astype(np.int64)).clamp(0, nc - 1), nc)
        gmap.integrate(f.pose, f.intrinsics, f.depth, None, onehot.permute(2, 0, 1).to(torch.float32), None)
    pmap.flush()
    gmap.flush()
    t_map = time.perf_counter()
    pv = pmap.voxels()
    pred = predict_labels(pv.features.to(torch.float32), lang.text, cfg.temperature, cfg.denoise, cfg.pred_thresh,
                          lang.similarity)
    gv = gmap.voxels()
    gxyz = gv.xyz.numpy().astype(np.float64)
    if ext is not None:
        from apps.evaluation.gt_points import voxelize_labels
        gxyz, glab = voxelize_labels(ext[0], ext[1], cfg.vox)
    elif world is not None:
        gijk = np.floor(gxyz / cfg.vox).astype(np.int64)
        glab = world.voxel_labels(gijk, cfg.vox).astype(np.int64)
    else:
        glab = gv.features.to(torch.float32).argmax(1).numpy().astype(np.int64)
    aligned = metrics.knn_align(gxyz, pv.xyz.numpy().astype(np.float64), pred, cfg.k, cfg.vox)
    summary = scores_with_without_bg(glab, aligned, names, cfg.background)
    summary["background_classes"] = [n for n in names if n.lower() in {b.lower() for b in cfg.background}]
    t_end = time.perf_counter()
    info = dict(kind="semseg", config=to_dict(cfg), class_names=names, encoder=enc.name, text_model=lang.text_model,
                templates=templates, background_classes=summary["background_classes"],
                language_head=lang.similarity is not None, gt="points" if ext is not None else "frames",
                encoder_version=getattr(enc, "version", ""), source=getattr(src, "name", cfg.source.kind),
                frames=len(frames), resolution=list(frames[0].depth.shape), n_pred_voxels=int(len(pred)),
                n_gt_voxels=int((glab > 0).sum()), map_config=to_dict(mc),
                timings_s=dict(mapping=t_map - t0, scoring=t_end - t_map, total=t_end - t0))
    (out / "summary.json").write_text(json.dumps(_json_safe(summary), indent=2))
    (out / "run_info.json").write_text(json.dumps(_json_safe(info), indent=2))
    (out / "table.md").write_text(semseg_table({out.name: summary}))
    return summary


def semseg_table(summaries: dict[str, dict]) -> str:
    """Markdown table (Table II layout): run, then mIoU/f-mIoU/Acc without and with background (%)."""
    lines = ["| Run | mIoU (%) | f-mIoU (%) | Acc (%) | mIoU bg (%) | f-mIoU bg (%) | Acc bg (%) |",
             "|---|---:|---:|---:|---:|---:|---:|"]

    def f(v):
        return "nan" if v is None or not math.isfinite(v) else f"{100 * v:.2f}"
    metrics = ("miou", "fmiou", "acc", "miou_bg", "fmiou_bg", "acc_bg")
    for name, s in summaries.items():
        lines.append(f"| {name} | " + " | ".join(f(s.get(k)) for k in metrics) + " |")
    return "\n".join(lines) + "\n"
