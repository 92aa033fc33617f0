"""Online search-volume benchmark (paper §IV-A, Table I; docs/method.md#evaluation).

For every depth limit and method a :class:`semantic_map.map.RayFrontsMap` is fed the same frames
(read / rendered and encoded once). Every ``every`` frames and at the end, per GT class:

1. observed = the method's active occupancy voxels; unobserved = scene-volume voxels not
   observed (GT: :func:`apps.evaluation.data.ground_truth`);
2. ray labels: softmax over all class names (temperature), prompt denoising over the
   whole ray set, prediction threshold; rays labelled 0 (the "none"/sky class) ignored;
3. search volume of class c: per unobserved voxel, how many of c's shapes hold it —
   true cones of ``cone_half_angle`` (default max FoV / 2) or the reference's hexagonal
   pyramids (``cone_shape=reference``), balls for Spherical Semantic Frontiers — normalised
   by the max count and thresholded (> ``srchvol_thresh``); a class without rays predicts
   the whole unobserved volume (``default_prediction``). Counts come from the exact row
   rasteriser (:mod:`apps.evaluation.raster`, ``scoring=raster``) — identical to the
   block-test path (``scoring=blocks``), ~10–50× faster;
4. TP/FP/FN, SCV, Recall, SCVR (:mod:`apps.evaluation.metrics`), observed-region IoU of
   the semantic voxels (exact grid or kNN alignment) and the observed fraction of the
   class (stopping rule).

AUCs: per class over time until > ``stop_frac`` of its GT voxels are observed, mean over
classes (then over scenes in the report). Semantic Voxels is evaluated on the RayFronts
map with its rays dropped when ``share_maps`` (RayFronts differs from it only by casting
rays; the voxel and occupancy layers are identical — tested), which saves one map.

Encoders with a language head (NARADIO): voxel/ray features stay in encoder space and are
compared through the head at query time (:mod:`apps.evaluation.language`); class names
are embedded by the SigLIP text tower (``text_model_dir``); Semantic Poses maps the
image-level (already language-space) features.

Query defaults (the paper's): class texts are the mean of the 80 ImageNet/NACLIP prompt
templates for language encoders (``templates=auto``; the label and sim encoders' features
*are* raw name embeddings, so their class texts stay raw names), and the softmax runs over
exactly the evaluated class names (the dataset's classes incl. class 0, no invented
negatives), temperature 100.

Encoders: ``label`` (every pixel its class's name embedding — measures geometry only),
``sim`` (those embeddings degraded like a ViT's, :mod:`encoders.sim` — measures
open-vocabulary mapping under realistic feature errors) or ``naradio``.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Literal, Sequence

import numpy as np
import torch

from apps.evaluation import metrics, raster, shapes
from apps.evaluation.data import GroundTruth, ground_truth, load_frames, pack
from apps.evaluation.figures import METHOD_TITLES
from apps.evaluation.language import EvalLanguage, eval_language
from common.config import ConfigError, field_, section, to_dict
from common.frame import Frame
from edge.sources.config import SourceConfig
from encoders.config import EncoderConfig
from semantic_map.query import Similarity

if TYPE_CHECKING:
    from encoders import ImageEncoder
    from semantic_map.config import MapConfig
    from semantic_map.map import RayFrontsMap
    from synthetic_world import World

log = logging.getLogger("rayfronts.eval")

ALL_METHODS = ["rayfronts", "semantic_poses", "semantic_voxels", "spherical_semfronts", "unidirectional_semfronts"]
METRIC_KEYS = ("miou_auc", "scv_auc", "recall_auc", "scvr_auc")


def _default_source() -> SourceConfig:
    return SourceConfig(kind="synthetic", resolution="96x96", n_frames=300, hfov=90.0)


@dataclass
class SrchvolConfig:
    source: SourceConfig = field_(_default_source(), "frame source (edge.sources keys)")
    encoder: EncoderConfig = section(EncoderConfig, "image encoder (label encoder by default)")
    map: dict = field_({"max_rays_per_frame": 1000},
                       "MapConfig overrides for every method, e.g. map.fronti_subsampling=5 (default: the "
                       "CPU scaling of the online preset, 1000 rays per frame as the authors' own fallback)")
    preset: str = field_("online", "map preset (semantic_map.config.PRESETS); 'online' = the paper's online table")
    depth_limits: list[float] = field_([0.0, 10.0, 20.0], "simulated depth ranges (m); 0 = no depth")
    methods: list[str] = field_(list(ALL_METHODS), "methods to evaluate (semantic_map.config.METHODS names)")
    vox: float = field_(1.0, "voxel size (m) of maps and GT")
    every: int = field_(10, "evaluate every this many frames (and after the last)")
    gt_range: float = field_(50.0, "GT pass: depth beyond this is out of range (reference: 50 m TartanAir cutoff)")
    gt_frame_stride: int = field_(2, "GT pass uses every n-th frame")
    gt_pixel_stride: int = field_(2, "GT pass uses every n-th pixel (row and column)")
    scene_volume: Literal["observed", "bbox"] = field_(
        "observed", "scene volume: voxels the full-range GT pass observes, or its whole bounding box")
    cone_shape: Literal["true", "reference"] = field_(
        "true", "ray search shape: true cones of cone_half_angle, or the reference's hexagonal pyramids")
    cone_half_angle: float = field_(-1.0, "cone half-angle alpha (deg); <0 = max(FoV)/2 of the camera")
    scoring: Literal["raster", "blocks"] = field_(
        "raster", "shape counting: exact row rasterisation (fast) or the block-test path (slow; identical counts)")
    text_model_dir: str = field_("", "text model directory for the class names (SigLIP for NARADIO; default "
                                     "<encoder.model_dir or $RAYFRONTS_MODEL_DIR>/siglip_text)")
    templates: Literal["auto"] | bool = field_(
        "auto", "class texts = mean of the 80 ImageNet/NACLIP prompt templates (true), raw names (false), or auto: "
                "templates for language encoders (naradio), raw names for label/sim (their features are name "
                "embeddings)")
    temperature: float = field_(100.0, "softmax temperature over the class names (the softmax set = all evaluated "
                                       "class names, as the paper)")
    denoise: float = field_(0.5, "prompt denoising threshold (whole ray/voxel set)")
    pred_thresh: float = field_(0.1, "no prediction below this softmax value")
    srchvol_thresh: float = field_(0.05, "normalised count threshold of a search volume (> thresh)")
    default_prediction: bool = field_(True, "a class without evidence predicts the whole unobserved volume")
    stop_frac: float = field_(0.5, "AUC stopping rule: a class stops once more than this fraction is observed")
    align_k: int = field_(0, "observed mIoU alignment: 0 = exact voxel grid, k > 0 = kNN majority")
    share_maps: bool = field_(True, "evaluate Semantic Voxels on the RayFronts map without its rays (identical layers)")
    ray_erosion_scale: bool = field_(True, "scale the preset's ray_erosion (px at 640 wide) to the image width")
    occupancy_backend: str = field_("auto", "occupancy backend: auto | vdb | torch")
    device: str = field_("cpu", "torch device of the maps")
    plots: bool = field_(True, "write SCVR-over-time PNG plots")
    progress: bool = field_(True, "tqdm progress bars")
    variants: dict = field_({}, "extra RayFronts variants evaluated on the same frames and GT (ablations): name -> "
                                "MapConfig overrides, e.g. variants={rayfronts_absolute: {ray_cost_norm: absolute}}")

    def all_methods(self) -> list[str]:
        """The evaluated methods: ``methods`` then the ``variants`` (RayFronts with overrides)."""
        return list(self.methods) + [v for v in self.variants if v not in self.methods]

    def validate(self) -> "SrchvolConfig":
        from semantic_map.config import METHODS, PRESETS
        bad = [m for m in self.methods if m not in ALL_METHODS]
        if bad:
            raise ConfigError(f"unknown method(s) {bad}; choose from {ALL_METHODS}")
        if not self.methods:
            raise ConfigError("methods must not be empty")
        if self.preset not in PRESETS:
            raise ConfigError(f"unknown preset {self.preset!r}; choose one of {sorted(PRESETS)}")
        if any(not d >= 0 for d in self.depth_limits) or not self.depth_limits:
            raise ConfigError(f"depth_limits must be a non-empty list of numbers >= 0, got {self.depth_limits}")
        if self.vox <= 0 or self.every < 1 or self.gt_range <= 0:
            raise ConfigError("need vox > 0, every >= 1 and gt_range > 0")
        for name, over in self.variants.items():
            if name in ALL_METHODS or not isinstance(over, dict):
                raise ConfigError(f"variant {name!r} must be a new name with a dict of MapConfig overrides")
        assert set(ALL_METHODS) <= set(METHODS) | {"rayfronts"}
        return self


def applicable(method: str, depth: float) -> bool:
    """Table I: Semantic Poses only without depth; Sem Voxels and semantic frontiers only with."""
    if depth <= 0:
        return method in ("rayfronts", "semantic_poses")
    return method != "semantic_poses"


def method_map_config(cfg: SrchvolConfig, method: str, depth: float, width: int) -> MapConfig:
    from semantic_map.config import map_config

    over = dict(cfg.map)
    over["vox_size"] = cfg.vox
    over["depth_limit"] = float(depth)
    if cfg.ray_erosion_scale and "ray_erosion" not in cfg.map:
        from semantic_map.config import PRESETS
        base = PRESETS[cfg.preset].get("ray_erosion", 4)
        over["ray_erosion"] = int(round(base * width / 640))
    variant = cfg.variants.get(method)
    if variant is not None:
        method = "rayfronts"
    name = method
    if method == "rayfronts" and depth <= 0:
        name = "rayfronts_zero_depth"
    mc = map_config(cfg.preset, None, name)
    from common.config import merge
    mc = merge(mc, over)
    return (merge(mc, variant) if variant else mc).validate()


# ----------------------------------------------------------------------------- per-step scoring
@dataclass
class Snapshot:
    observed_keys: np.ndarray          # sorted packed keys of observed voxels
    ray_origins: np.ndarray            # (R, 3)
    ray_dirs: np.ndarray               # (R, 3)
    ray_labels: np.ndarray             # (R,) class id, 0 = none
    voxel_xyz: np.ndarray              # (N, 3)
    voxel_labels: np.ndarray           # (N,) class id, 0 = none


def snapshot(rmap: RayFrontsMap, text: torch.Tensor, cfg: SrchvolConfig, with_rays: bool = True,
             similarity: Similarity | None = None) -> Snapshot:
    """Observed set and labelled voxels/rays of a map (query: softmax over ``text`` rows,
    denoising over the whole layer, threshold; label = class id, 0 = none/sky).
    ``similarity``: map features × class texts → (K, N) (e.g. through a language head;
    None = cosine)."""
    ijk, _ = rmap.occupancy_view().active()
    ok = np.sort(pack(ijk.numpy())) if ijk.shape[0] else np.empty(0, np.int64)
    res = rmap.query(text, similarity=similarity, softmax=True, temperature=cfg.temperature, top_k=0,
                     denoise=cfg.denoise, threshold=cfg.pred_thresh)
    vl = res.voxel_labels.cpu().numpy().astype(np.int64)
    vl = np.where(vl < 0, 0, vl)
    rl = rmap.rays()
    if with_rays and rl.origins.shape[0]:
        lab = res.ray_labels.cpu().numpy().astype(np.int64)
        lab = np.where(lab < 0, 0, lab)
        o, d = rl.origins.cpu().numpy().astype(np.float64), rl.directions.cpu().numpy().astype(np.float64)
    else:
        lab, o, d = np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3))
    return Snapshot(ok, o, d, lab, rmap.voxel_xyz().cpu().numpy().astype(np.float64), vl)


@dataclass
class ScoringContext:
    """What every scoring step shares (computed once per run): GT voxel centres, the dense
    row grid of the scene volume and each GT voxel's cell in it."""

    gt: GroundTruth
    centres: np.ndarray               # (V, 3) float64 GT voxel centres
    grid: raster.RowGrid
    cells: np.ndarray                 # (V,) flat grid cell of each GT voxel

    @classmethod
    def build(cls, gt: GroundTruth) -> "ScoringContext":
        if len(gt.keys) == 0:
            raise ValueError("the ground-truth scene volume is empty (no frame observed anything)")
        grid = raster.RowGrid.around(gt.ijk, gt.vox)
        if grid.box_cells > raster.MAX_BOX_CELLS:
            log.warning("scene-volume box of %d cells is too large for the row rasteriser (max %d): "
                        "scoring with the slower block path", grid.box_cells, raster.MAX_BOX_CELLS)
        return cls(gt, gt.centres(), grid, grid.cells(gt.ijk))

    def observed_mask(self, observed_keys: np.ndarray) -> np.ndarray:
        """(V,) bool: GT voxels whose packed key is among ``observed_keys``."""
        keys = self.gt.keys
        obs = np.zeros(len(keys), dtype=bool)
        if observed_keys.size:
            pos = np.searchsorted(keys, observed_keys).clip(max=len(keys) - 1)
            obs[pos[keys[pos] == observed_keys]] = True
        return obs


def search_volumes(snap: Snapshot, method: str, ctx: ScoringContext, un_idx: np.ndarray, classes: Sequence[int],
                   cfg: SrchvolConfig, half_angle: float, beta: float) -> dict[int, np.ndarray]:
    """{class: bool mask over the unobserved voxels ``un_idx`` (indices into the GT voxels)}
    for classes with at least one ray. ``cfg.scoring`` picks the counting path (same counts)."""
    out: dict[int, np.ndarray] = {}
    if not snap.ray_labels.size or not un_idx.size:
        return out
    spherical = method == "spherical_semfronts"
    if spherical:
        uo, inv = np.unique(np.round(snap.ray_origins, 6), axis=0, return_inverse=True)
        radii = shapes.search_volume.frontier_ball_radii(torch.as_tensor(uo), beta).numpy()[inv.reshape(-1)]
    use_raster = (cfg.scoring == "raster" and (spherical or cfg.cone_shape == "reference" or 0 < half_angle < 90)
                  and ctx.grid.box_cells <= raster.MAX_BOX_CELLS)
    cells = ctx.cells[un_idx]
    xyz: Any = None if use_raster else ctx.centres[un_idx]     # only the exact (non-raster) counts use it
    for c in classes:
        sel = snap.ray_labels == c
        if not sel.any():
            continue
        o, d = snap.ray_origins[sel], snap.ray_dirs[sel]
        if spherical:
            cnt = (raster.ball_counts(ctx.grid, o, radii[sel], cells) if use_raster else
                   shapes.ball_counts(xyz, o, radii[sel]).numpy())
        elif cfg.cone_shape == "reference":
            s = beta / cfg.vox
            cnt = (raster.reference_cone_counts(ctx.grid, o, d, s, half_angle, cells=cells) if use_raster else
                   shapes.reference_cone_counts(xyz, o, d, cfg.vox, s, half_angle).numpy())
        else:
            cnt = (raster.cone_counts(ctx.grid, o, d, half_angle, cells) if use_raster else
                   shapes.cone_counts(xyz, o, d, half_angle).numpy())
        out[int(c)] = metrics.normalized_count_mask(cnt, cfg.srchvol_thresh)
    return out


def score_step(snap: Snapshot, ctx: ScoringContext, method: str, classes: list[int], cfg: SrchvolConfig,
               half_angle: float, beta: float, gt_counts: np.ndarray) -> list[dict]:
    """Rows (one per GT class) of the step's metrics."""
    gt = ctx.gt
    obs = ctx.observed_mask(snap.observed_keys)
    un_idx = np.flatnonzero(~obs)
    gt_un = gt.labels[un_idx]
    masks = search_volumes(snap, method, ctx, un_idx, classes, cfg, half_angle, beta)
    sv = metrics.srchvol_metrics(masks, gt_un, classes, cfg.default_prediction)
    # observed region: semantic-voxel labels vs GT
    g_obs = gt.labels[obs]
    keep = g_obs != metrics.IGNORE
    g_obs = np.where(g_obs < 0, 0, g_obs)
    pred = metrics.knn_align(ctx.centres[obs], snap.voxel_xyz, snap.voxel_labels, cfg.align_k, gt.vox)
    ious = metrics.observed_iou(g_obs[keep], pred[keep], classes)
    obs_counts = np.bincount(g_obs, minlength=len(gt.class_names))
    n_ray = np.bincount(snap.ray_labels, minlength=len(gt.class_names)) if snap.ray_labels.size else \
        np.zeros(len(gt.class_names), dtype=np.int64)
    rows = []
    for c in classes:
        n_c = int(gt_counts[c])
        n_obs = int(obs_counts[c])
        r = dict(class_id=int(c), class_name=gt.class_names[c], gt_count=n_c,
                 observed_frac=n_obs / n_c if n_c else float("nan"), iou=ious[c],
                 n_rays=int(n_ray[c]), evidence=int(c) in masks,
                 n_unobserved=int(un_idx.size))
        r.update(sv[c])
        rows.append(r)
    return rows


def summarize(rows: list[dict], stop: float) -> dict:
    """AUCs of one (depth, method): ``{miou_auc, scv_auc, recall_auc, scvr_auc}``; the mIoU
    AUC of a method that localised nothing (no defined IoU) is 0."""
    rr = [dict(r, **{"class": r["class_id"]}) for r in rows]
    out = {}
    for key, m in (("miou_auc", "iou"), ("scv_auc", "scv"), ("recall_auc", "recall"), ("scvr_auc", "scvr")):
        v = metrics.auc_table(rr, m, stop)
        if key == "miou_auc" and not math.isfinite(v):
            v = 0.0
        out[key] = v
    return out


# ----------------------------------------------------------------------------- run
#: a map's key: (depth limit, method)
MapKey = tuple[float, str]
#: one evaluated (depth, method): (depth, method, key of the map it reads, with rays)
Evaluation = tuple[float, str, MapKey, bool]


def _encode_frame(enc: ImageEncoder, f: Frame) -> tuple[torch.Tensor, torch.Tensor]:
    """``(feature map, image-level feature)`` of frame ``f`` (no autograd)."""
    with torch.inference_mode():
        if hasattr(enc, "encode_with_global"):
            return enc.encode_with_global(f.rgb, f.labels)
        return enc.encode(f.rgb, f.labels), enc.encode_global(f.rgb, f.labels)


def _build_maps(cfg: SrchvolConfig, enc: ImageEncoder, lang: EvalLanguage, first: tuple[torch.Tensor, torch.Tensor],
                width: int) -> tuple[dict[MapKey, RayFrontsMap], dict[MapKey, Similarity | None], list[Evaluation]]:
    """``(maps, similarities, evaluations)``: one map per applicable (depth, method) —
    "semantic_voxels" may share the rayfronts map (evaluated without its rays). Maps of
    image-level features (Semantic Poses) hold language-space vectors: cosine, no head."""
    from semantic_map.map import RayFrontsMap

    maps: dict[MapKey, RayFrontsMap] = {}
    sims: dict[MapKey, Similarity | None] = {}
    evals: list[Evaluation] = []
    for d in cfg.depth_limits:
        for m in cfg.all_methods():
            if not applicable("rayfronts" if m in cfg.variants else m, d):
                continue
            if m == "semantic_voxels" and cfg.share_maps and "rayfronts" in cfg.methods:
                evals.append((d, m, (d, "rayfronts"), False))
                continue
            mc = method_map_config(cfg, m, d, width)
            dim = int(first[1].shape[0]) if mc.global_encoding else enc.feature_dim
            if mc.global_encoding and dim != lang.lang_dim:
                raise ValueError(f"image-level features are {dim}-d but class texts {lang.lang_dim}-d")
            maps[(d, m)] = RayFrontsMap(mc, dim, enc.name, device=cfg.device,
                                        occupancy_backend=cfg.occupancy_backend)
            sims[(d, m)] = None if mc.global_encoding else lang.similarity
            evals.append((d, m, (d, m), m != "semantic_voxels"))
    return maps, sims, evals


def _integrate(maps: dict[MapKey, RayFrontsMap], f: Frame, feats: torch.Tensor, gfeat: torch.Tensor,
               last: bool) -> None:
    """Frame ``f`` into every map (flushed after the ``last`` frame): image-level maps take
    only the global feature, the others only the feature map."""
    for rmap in maps.values():
        g = rmap.cfg.global_encoding
        rmap.integrate(f.pose, f.intrinsics, f.depth, f.rgb, None if g else feats, gfeat if g else None)
    if last:
        for rmap in maps.values():
            rmap.flush()


@dataclass
class _StepScorer:
    """Scores every evaluated (depth, method) at a step: what the steps of a run share."""

    cfg: SrchvolConfig
    text: torch.Tensor
    ctx: ScoringContext
    classes: list[int]
    half_angle: float
    gt_counts: np.ndarray
    maps: dict[MapKey, RayFrontsMap]
    sims: dict[MapKey, Similarity | None]
    evals: list[Evaluation]

    def score(self, step: int, rows: dict[MapKey, list[dict]]) -> None:
        """Append the rows of ``step`` (one per GT class) to ``rows[(depth, method)]``."""
        snaps = {key: snapshot(mp, self.text, self.cfg, True, self.sims[key]) for key, mp in self.maps.items()}
        for d, m, key, with_rays in self.evals:
            sn = snaps[key]
            if not with_rays:
                sn = dataclasses.replace(sn, ray_origins=np.empty((0, 3)), ray_dirs=np.empty((0, 3)),
                                         ray_labels=np.empty(0, np.int64))
            for r in score_step(sn, self.ctx, m, self.classes, self.cfg, self.half_angle, self.maps[key].cfg.beta,
                                self.gt_counts):
                r.update(step=step, depth_limit=d, method=m)
                rows[(d, m)].append(r)


def _summaries(cfg: SrchvolConfig, rows: dict[MapKey, list[dict]]) -> dict[str, dict]:
    """``{depth_key: {method: AUCs or None (not applicable)}}``."""
    summary: dict[str, dict] = {}
    for d in cfg.depth_limits:
        dk = depth_key(d)
        summary[dk] = {}
        for m in cfg.all_methods():
            summary[dk][m] = summarize(rows[(d, m)], cfg.stop_frac) if (d, m) in rows else None
    return summary


def run_srchvol(cfg: SrchvolConfig, out_dir: str | Path, world: World | None = None) -> dict:
    """Run the benchmark; write CSV/JSON rows, summary.json, table.md and plots into
    ``out_dir``. Returns ``{depth_key: {method: {metric: value}}}`` (values in [0, 1] or
    ``None`` for N/A)."""
    cfg.validate()
    from encoders import make_encoder

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    torch.manual_seed(0)
    frames, src = load_frames(cfg.source, progress=cfg.progress, world=world)
    if cfg.source.kind == "synthetic" and world is None:
        world = getattr(src, "world", None)
    class_names = list(src.class_names or [])
    if not class_names:
        raise ValueError("the source has no class names; the search-volume benchmark needs GT labels")
    t_load = time.perf_counter()
    gt = ground_truth(frames, class_names, cfg.vox, cfg.gt_range, world=world, frame_stride=cfg.gt_frame_stride,
                      pixel_stride=cfg.gt_pixel_stride, scene_volume=cfg.scene_volume,
                      occupancy_backend=cfg.occupancy_backend, progress=cfg.progress)
    t_gt = time.perf_counter()
    gt_counts = gt.class_counts()
    classes = [c for c in range(1, len(class_names)) if gt_counts[c] > 0]
    enc = make_encoder(cfg.encoder, class_names, device=cfg.device)
    from apps.evaluation.language import use_templates
    templates = use_templates(cfg.templates, enc)
    lang = eval_language(enc, class_names, templates, model_dir=cfg.text_model_dir, device=cfg.device)
    H, W = frames[0].depth.shape
    K0 = frames[0].intrinsics
    fov = (math.degrees(2 * math.atan(0.5 * W / K0[0, 0])), math.degrees(2 * math.atan(0.5 * H / K0[1, 1])))
    half_angle = cfg.cone_half_angle if cfg.cone_half_angle > 0 else max(fov) / 2
    ctx = ScoringContext.build(gt)

    first = _encode_frame(enc, frames[0])
    maps, sims, evals = _build_maps(cfg, enc, lang, first, W)
    scorer = _StepScorer(cfg, lang.text, ctx, classes, half_angle, gt_counts, maps, sims, evals)
    rows: dict[MapKey, list[dict]] = {(d, m): [] for d, m, _, _ in evals}
    n = len(frames)
    steps = sorted(set(list(range(cfg.every, n + 1, cfg.every)) + [n]))
    it: Iterable[tuple[int, Frame]] = enumerate(frames)
    if cfg.progress:
        from tqdm import tqdm
        it = tqdm(it, total=n, desc="search volume", unit="frame")
    t_map = t_score = 0.0
    for i, f in it:
        t0 = time.perf_counter()
        feats, gfeat = first if i == 0 else _encode_frame(enc, f)
        step = i + 1
        _integrate(maps, f, feats, gfeat, last=step == n)
        t1 = time.perf_counter()
        t_map += t1 - t0
        if step in steps:
            scorer.score(step, rows)
            t_score += time.perf_counter() - t1
    del first
    t_end = time.perf_counter()

    summary = _summaries(cfg, rows)
    info = dict(
        config=to_dict(cfg), class_names=class_names, classes_evaluated=[class_names[c] for c in classes],
        gt_class_voxels={class_names[c]: int(gt_counts[c]) for c in classes}, scene_volume_voxels=int(len(gt.keys)),
        frames=n, resolution=[H, W], fov_deg=list(fov), cone_half_angle_deg=half_angle, encoder=enc.name,
        templates=templates, softmax_set=list(class_names),
        encoder_version=getattr(enc, "version", ""), text_model=lang.text_model,
        language_head=lang.similarity is not None,
        source=getattr(src, "name", cfg.source.kind), steps=steps,
        map_configs={f"{d:g}m/{m}": to_dict(maps[(d, m)].cfg) for (d, m) in maps},
        timings_s=dict(load=t_load - t_start, ground_truth=t_gt - t_load, mapping=t_map, scoring=t_score,
                       total=t_end - t_start),
    )
    write_outputs(out, rows, summary, info, cfg)
    return summary


def depth_key(d: float) -> str:
    return f"{d:g}m"


# ----------------------------------------------------------------------------- outputs
def _json_safe(v: object) -> object:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return _json_safe(float(v))
    if isinstance(v, np.bool_):
        return bool(v)
    return v


ROW_FIELDS = ["depth_limit", "method", "step", "class_id", "class_name", "gt_count", "observed_frac", "n_unobserved",
              "n_rays", "evidence", "tp", "fp", "fn", "tn", "vol", "scv", "recall", "scvr", "iou"]


def write_outputs(out: Path, rows: dict, summary: dict, info: dict, cfg: SrchvolConfig) -> None:
    import csv

    allrows = [r for (d, m), rs in rows.items() for r in rs]
    with open(out / "steps.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=ROW_FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in allrows:
            w.writerow({k: r.get(k) for k in ROW_FIELDS})
    (out / "steps.json").write_text(json.dumps(_json_safe(allrows)))
    single = len(cfg.depth_limits) == 1
    top = summary[depth_key(cfg.depth_limits[0])] if single else summary
    (out / "summary.json").write_text(json.dumps(_json_safe(top), indent=2))
    (out / "run_info.json").write_text(json.dumps(_json_safe(dict(info, kind="srchvol")), indent=2))
    (out / "table.md").write_text(table_markdown(summary, cfg.all_methods(), [depth_key(d) for d in cfg.depth_limits]))
    if cfg.plots:
        plot_scvr(out, rows, cfg)
        from apps.evaluation.figures import write_figures  # methods compared per depth; table.csv

        write_figures(out)


def table_markdown(summary: dict, methods: Sequence[str], depth_keys: Sequence[str]) -> str:
    """Table I layout: one row per method, (mIoU, SCV, Recall, SCVR) AUCs in % per depth."""
    cols = ["mIoU", "SCV", "Recall", "SCVR"]
    keys = ["miou_auc", "scv_auc", "recall_auc", "scvr_auc"]
    head = "| Method | " + " | ".join(f"{dk} {c} (%)" for dk in depth_keys for c in cols) + " |"
    sep = "|---|" + "---:|" * (len(cols) * len(depth_keys))
    lines = [head, sep]
    best = {}
    for dk in depth_keys:
        vals = [(summary[dk].get(m) or {}).get("scvr_auc") for m in methods]
        fin = [v for v in vals if v is not None and math.isfinite(v)]
        best[dk] = max(fin) if fin else None
    for m in methods:
        cells = []
        for dk in depth_keys:
            s = summary[dk].get(m)
            for k in keys:
                if s is None:
                    cells.append("--")
                    continue
                v = s[k]
                txt = "nan" if v is None or not math.isfinite(v) else f"{100 * v:.2f}"
                is_best = best[dk] is not None and v is not None and math.isfinite(v) and v == best[dk] and v > 0
                if k == "scvr_auc" and is_best:
                    txt = f"**{txt}**"
                cells.append(txt)
        lines.append(f"| {METHOD_TITLES.get(m, m)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_scvr(out: Path, rows: dict, cfg: SrchvolConfig) -> list[Path]:
    """One PNG per (method, depth): class-mean SCVR (bold) and per-class SCVR over frames."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pdir = out / "plots"
    pdir.mkdir(exist_ok=True)
    paths = []
    for (d, m), rs in rows.items():
        if not rs:
            continue
        fig, ax = plt.subplots(figsize=(6, 3.5))
        by: dict[str, list] = {}
        for r in rs:
            by.setdefault(r["class_name"], []).append((r["step"], r["scvr"]))
        steps = sorted({r["step"] for r in rs})
        for name, pts in sorted(by.items()):
            pts.sort()
            ax.plot([p[0] for p in pts], [100 * p[1] for p in pts], lw=0.8, alpha=0.6, label=name)
        mean = [np.nanmean([r["scvr"] for r in rs if r["step"] == s] or [np.nan]) for s in steps]
        ax.plot(steps, [100 * v for v in mean], "k-", lw=2.2, label="class mean")
        ax.set_xlabel("frame")
        ax.set_ylabel("SCVR (%)")
        ax.set_title(f"{METHOD_TITLES.get(m, m)} — depth {d:g} m")
        ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)  # outside the data
        fig.tight_layout()
        p = pdir / f"scvr_{m}_{depth_key(d)}.png"
        fig.savefig(p, dpi=90, bbox_inches="tight")
        plt.close(fig)
        paths.append(p)
    return paths
