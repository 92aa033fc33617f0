"""``RayFrontsMap``: semantic voxels + occupancy + frontiers + semantic ray frontiers.

Pure computation (no I/O besides :meth:`save`/:meth:`load`). One frame at a time through
:meth:`RayFrontsMap.integrate`; the schedule is the reference's (docs/method.md#integration-schedule):

* per frame: geometry (:mod:`semantic_map.depth_geometry`), feature/RGB sampling at the needed
  pixels only, per-frame pre-aggregation of semantic points per voxel, buffering;
* every ``vox_accum_period`` frames, the **voxel block**: occupancy insert (frame by frame,
  free −1 / occupied +(w−1), clamped after each row) → semantic fuse → occupancy prune if
  due → semantic prune if due → frontier update on the updated box;
* every ``ray_accum_period`` frames once ``ray_accum_phase`` frames have passed, the **ray
  block**: prune rays of vanished frontiers (re-queued when ray tracing is on) → cast →
  direction inference (Unidirectional baseline).

Not internally locked: callers that integrate and query from different threads hold
their own lock (the map keeps no global state).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
import torch

from common.conventions import is_rigid, sanitize_depth, voxel_center
from semantic_map import cell_keys, kernels
from semantic_map.config import MapConfig
from semantic_map.depth_geometry import ArrayOrTensor, FrameGeometry, aggregate_samples, frame_geometry, sample_image
from semantic_map.frontiers import FrontierTable
from semantic_map.occupancy import from_state as occupancy_from_state
from semantic_map.occupancy import make_occupancy
from semantic_map.occupancy.base import OccupancyView
from semantic_map.query import LayerScores, Similarity, run_query
from semantic_map.ray_frontiers import (
    RayBatch,
    RayStore,
    angles_deg,
    associate,
    associate_near,
    infer_directions,
    warn_infer_direction,
)
from semantic_map.semantic_voxels import SemanticVoxels

#: one frame's semantic points summed per voxel: (keys, rgb sums, feature sums, counts)
SemanticSums = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


@dataclass
class VoxelLayer:
    xyz: torch.Tensor        # (N, 3) float32 voxel centres (m)
    rgb: torch.Tensor        # (N, 3) float32 in [0, 1]
    features: torch.Tensor   # (N, C) feature dtype
    counts: torch.Tensor     # (N,) float32 hit counts


@dataclass
class FrontierLayer:
    centres: torch.Tensor    # (F, 3) float32 coarse cell centres (m)
    keys: torch.Tensor       # (F,) int64 packed coarse ijk (semantic_map.cell_keys)
    counts: torch.Tensor     # (F,) int64 fine frontier voxels in each coarse cell


@dataclass
class RayLayer:
    origins: torch.Tensor        # (R, 3) float32 frontier centres
    directions: torch.Tensor     # (R, 3) float32 unit (weighted mean direction of the bin)
    angles: torch.Tensor         # (R, 2) float32 (theta, phi) degrees, world axes
    features: torch.Tensor       # (R, C)
    weights: torch.Tensor        # (R,) float32 accumulated weight
    frontier_keys: torch.Tensor  # (R,) int64


@dataclass
class PreparedFrame:
    """One frame after :meth:`RayFrontsMap.prepare`: what :meth:`RayFrontsMap.commit` buffers."""
    occ_ijk: torch.Tensor            # (Mo, 3) int64 occupied voxels
    free_ijk: torch.Tensor           # (Mf, 3) int64 free voxels
    sem: SemanticSums | None         # (keys, rgb sums, feature sums, counts) per voxel, or None
    rays: RayBatch | None            # (origins, unit dirs, features), or None
    fov_deg: tuple[float, float]     # horizontal / vertical field of view
    timings: dict[str, float]        # ms of validate / geometry / sample


_DTYPES = {"float32": torch.float32, "float16": torch.float16}


def _as_tensor(x: ArrayOrTensor, dtype: torch.dtype | None = None,
               device: str | torch.device = "cpu") -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x
    else:
        t = torch.as_tensor(np.ascontiguousarray(x))
    return t.to(device=device, dtype=dtype) if dtype is not None else t.to(device)


def _lap(tm: dict[str, float], name: str, t0: float) -> float:
    """Add the ms since ``t0`` to ``tm[name]``; returns now (the next stage's start)."""
    t1 = time.perf_counter()
    tm[name] = tm.get(name, 0.0) + (t1 - t0) * 1e3
    return t1


def _check_pose_intrinsics(pose: ArrayOrTensor, intrinsics: ArrayOrTensor) -> tuple[np.ndarray, np.ndarray]:
    """``(pose, K)`` as float64 arrays; raises ValueError unless the pose is a finite rigid 4×4
    and K a finite 3×3 with positive focal lengths."""
    pose_np = np.asarray(pose.cpu() if isinstance(pose, torch.Tensor) else pose, dtype=np.float64)
    if not is_rigid(pose_np):
        raise ValueError("pose must be a finite rigid 4x4 camera-to-world transform")
    K = np.asarray(intrinsics.cpu() if isinstance(intrinsics, torch.Tensor) else intrinsics, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"intrinsics must be a finite 3x3 with fx, fy > 0, got {K.tolist()}")
    return pose_np, K


class RayFrontsMap:
    """The RayFronts map (see module docstring)."""

    def __init__(self, cfg: MapConfig, feature_dim: int, feature_space: str = "", device: str | torch.device = "cpu",
                 occupancy_backend: str = "auto") -> None:
        self.cfg = cfg.validate()
        if feature_dim <= 0:
            raise ValueError(f"feature_dim must be > 0, got {feature_dim}")
        self.feature_dim = int(feature_dim)
        self.feature_space = feature_space
        self.device = torch.device(device)
        self.occupancy_backend = occupancy_backend
        dt = _DTYPES[cfg.feature_dtype]
        self.occupancy = make_occupancy(cfg.vox_size, -cfg.max_empty_cnt, cfg.max_occ_cnt,
                                        backend=occupancy_backend, device="cpu")
        self.sem = SemanticVoxels(cfg.vox_size, self.feature_dim, dt, self.device)
        self.fronts = FrontierTable(cfg.vox_size, cfg.fronti_subsampling, cfg.fronti_subsampling_min_fronti,
                                    self.device)
        self.ray_store = RayStore(cfg.beta, cfg.angle_bin_size, self.feature_dim, dt, self.device)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        if cfg.infer_direction:
            warn_infer_direction(cfg.angle_bin_size)
        self.counters = dict(frames=0, vox=0, occ_prune=0, sem_prune=0, ray_phase=0, ray=0,
                             voxel_blocks=0, ray_blocks=0)
        self.last_fov_deg = (90.0, 90.0)
        self._reset_buffers()
        self._rng_state_source: Callable[[], torch.Tensor] | None = None  # set by mapper.pipeline.MapPipeline
        self._occupancy_view: OccupancyView | None = None
        self.timings: dict[str, float] = {}
        self.timings_total: dict[str, float] = {}

    def rng_state(self) -> torch.Tensor:
        """The budget generator's state after the last committed frame (what a snapshot
        saves): with frames prepared ahead by a pipeline, the state before the oldest one."""
        src = self._rng_state_source
        return src() if src is not None else self.generator.get_state()

    def prepared_rng_state(self) -> torch.Tensor:
        """The budget generator's state now: after every frame prepared so far, committed or
        not (a pipeline notes it before each prepare)."""
        return self.generator.get_state()

    def attach_rng_state_source(self, source: Callable[[], torch.Tensor]) -> None:
        """Let ``source`` answer :meth:`rng_state` (a pipeline that prepares frames ahead
        knows the state after the last committed one)."""
        self._rng_state_source = source

    def detach_rng_state_source(self, source: Callable[[], torch.Tensor]) -> None:
        """Stop asking ``source`` (a no-op when another source is attached)."""
        if self._rng_state_source == source:
            self._rng_state_source = None

    def _reset_buffers(self) -> None:
        self._buf_occ: list[tuple[torch.Tensor, torch.Tensor]] = []
        self._buf_sem: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = []
        self._buf_rays: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        self._pending_prune: list[torch.Tensor] = []

    # ------------------------------------------------------------------------------------
    def _tick(self, name: str, t0: float) -> float:
        t = time.perf_counter()
        ms = (t - t0) * 1e3
        self.timings[name] = self.timings.get(name, 0.0) + ms
        self.timings_total[name] = self.timings_total.get(name, 0.0) + ms
        return t

    def integrate(self, pose: ArrayOrTensor, intrinsics: ArrayOrTensor, depth: ArrayOrTensor,
                  rgb: ArrayOrTensor | None = None, features: ArrayOrTensor | None = None,
                  global_feature: ArrayOrTensor | None = None, confidence: ArrayOrTensor | None = None
                  ) -> dict[str, float]:
        """Add one frame. ``pose`` 4×4 camera-to-world (RDF), ``intrinsics`` 3×3 at depth
        resolution, ``depth`` (H, W) planar metres (NaN ignore, +inf beyond range), ``rgb``
        (H', W', 3) uint8 (or float in [0, 1]), ``features`` (C, h, w) any float dtype with
        h ≤ H, w ≤ W, ``global_feature`` (C,), ``confidence`` (H, W). Returns per-stage ms.

        Same as ``commit(prepare(...))``: :class:`mapper.pipeline.MapPipeline` runs the two
        halves on different threads (frame N+1 prepared while frame N is committed)."""
        return self.commit(self.prepare(pose, intrinsics, depth, rgb, features, global_feature, confidence))

    def prepare(self, pose: ArrayOrTensor, intrinsics: ArrayOrTensor, depth: ArrayOrTensor,
                rgb: ArrayOrTensor | None = None, features: ArrayOrTensor | None = None,
                global_feature: ArrayOrTensor | None = None, confidence: ArrayOrTensor | None = None) -> PreparedFrame:
        """First half of :meth:`integrate`: validation, geometry and feature / RGB sampling of
        one frame. Reads only the configuration and advances only ``self.generator`` (the
        budgets' random draws), so prepared frames must be committed in the order they were
        prepared; touches no map state (safe to run while another thread commits / queries)."""
        cfg = self.cfg
        tm: dict[str, float] = {}
        t = time.perf_counter()
        pose_np, K = _check_pose_intrinsics(pose, intrinsics)
        d = self._check_depth(depth)
        H, W = d.shape
        feats = self._check_features(features, H, W)
        gfeat = self._check_global_feature(global_feature)
        rgb_t = self._check_rgb(rgb)
        conf = self._check_confidence(confidence, H, W)
        fov = (math.degrees(2 * math.atan(0.5 * W / K[0, 0])), math.degrees(2 * math.atan(0.5 * H / K[1, 1])))
        t = _lap(tm, "validate", t)

        use_rays = cfg.semantic_rays and not cfg.global_encoding
        g = frame_geometry(pose_np, K, d, cfg.vox_size, max_depth_sensing=cfg.sensing_range(),
                           occ_thickness=cfg.occ_thickness, max_pts=cfg.max_pts_per_frame,
                           max_empty_pts=cfg.max_empty_pts_per_frame, max_rays=cfg.max_rays_per_frame,
                           ray_erosion=cfg.ray_erosion, want_rays=use_rays, generator=self.generator,
                           confidence=conf, free_stride=cfg.free_space_stride, device=self.device)
        occ_ijk, free_ijk, pts, pix = self._clip_to_bbox(g)
        t = _lap(tm, "geometry", t)

        sem = self._semantic_sums(pts, pix, (H, W), feats, gfeat, rgb_t)
        rays = self._frame_rays(pose_np, g, (H, W), feats, gfeat) if cfg.semantic_rays else None
        _lap(tm, "sample", t)
        return PreparedFrame(occ_ijk, free_ijk, sem, rays, fov, tm)

    def _check_depth(self, depth: ArrayOrTensor) -> torch.Tensor:
        """``depth`` as a sanitised (H, W) float32 tensor on the map's device (see :meth:`integrate`)."""
        d = _as_tensor(depth, torch.float32)
        if d.ndim == 3 and d.shape[0] == 1:
            d = d[0]
        if d.ndim != 2 or d.numel() == 0:
            raise ValueError(f"depth must be (H, W), got shape {tuple(d.shape)}")
        return sanitize_depth(d, self.cfg.depth_limit if self.cfg.depth_limit >= 0 else None).to(self.device)

    def _check_features(self, features: ArrayOrTensor | None, H: int, W: int) -> torch.Tensor | None:
        """``features`` as a (C, h, w) float tensor no larger than the (H, W) depth, or None."""
        if features is None:
            return None
        feats = _as_tensor(features, None, self.device)
        if feats.ndim != 3 or feats.shape[0] != self.feature_dim:
            raise ValueError(f"features must be (C={self.feature_dim}, h, w), got {tuple(feats.shape)}")
        if feats.shape[1] > H or feats.shape[2] > W:
            raise ValueError(f"feature map {tuple(feats.shape[1:])} larger than depth {(H, W)}")
        if not feats.is_floating_point():
            raise ValueError("features must be a float array")
        return feats

    def _check_global_feature(self, global_feature: ArrayOrTensor | None) -> torch.Tensor | None:
        """``global_feature`` as a (C,) float32 tensor, or None."""
        if global_feature is None:
            return None
        gfeat = _as_tensor(global_feature, torch.float32, self.device).reshape(-1)
        if gfeat.numel() != self.feature_dim:
            raise ValueError(f"global_feature has {gfeat.numel()} values, expected {self.feature_dim}")
        return gfeat

    def _check_rgb(self, rgb: ArrayOrTensor | None) -> torch.Tensor | None:
        """``rgb`` (H', W', 3) as a (3, H', W') float32 tensor in [0, 1], or None."""
        if rgb is None:
            return None
        r = _as_tensor(rgb, None, self.device)
        if r.ndim != 3 or r.shape[2] != 3:
            raise ValueError(f"rgb must be (H', W', 3), got {tuple(r.shape)}")
        rgb_t = r.permute(2, 0, 1)
        return rgb_t.to(torch.float32) / 255.0 if not r.is_floating_point() else rgb_t.to(torch.float32)

    def _check_confidence(self, confidence: ArrayOrTensor | None, H: int, W: int) -> torch.Tensor | None:
        """``confidence`` as an (H, W) float32 tensor; None when absent or unused (random selection)."""
        conf = None if confidence is None else _as_tensor(confidence, torch.float32, self.device)
        if conf is not None and tuple(conf.shape) != (H, W):
            raise ValueError(f"confidence must be {(H, W)}, got {tuple(conf.shape)}")
        if self.cfg.point_selection == "random":
            conf = None
        return conf

    def _clip_to_bbox(self, g: FrameGeometry) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(occ_ijk, free_ijk, pts_xyz, pts_pix)`` of ``g`` inside ``cfg.clip_bbox`` (all when unset)."""
        cfg = self.cfg
        occ_ijk, free_ijk, pts, pix = g.occ_ijk, g.free_ijk, g.pts_xyz, g.pts_pix
        if cfg.clip_bbox is None:
            return occ_ijk, free_ijk, pts, pix
        lo = torch.tensor(cfg.clip_bbox[:3], dtype=torch.float32, device=self.device)
        hi = torch.tensor(cfg.clip_bbox[3:], dtype=torch.float32, device=self.device)

        def inside(x: torch.Tensor) -> torch.Tensor:
            return ((x > lo) & (x < hi)).all(1)
        occ_ijk = occ_ijk[inside(voxel_center(occ_ijk, cfg.vox_size))]
        free_ijk = free_ijk[inside(voxel_center(free_ijk, cfg.vox_size))]
        keep = inside(pts)
        return occ_ijk, free_ijk, pts[keep], pix[keep]

    def _semantic_sums(self, pts: torch.Tensor, pix: torch.Tensor, hw: tuple[int, int], feats: torch.Tensor | None,
                       gfeat: torch.Tensor | None, rgb_t: torch.Tensor | None) -> SemanticSums | None:
        """Semantic points pre-aggregated per voxel: (keys, rgb sums, feature sums, counts), or
        None without points or without a feature source."""
        cfg = self.cfg
        sem_feat_src = feats is not None or (cfg.global_encoding and gfeat is not None)
        if not (pts.shape[0] and sem_feat_src):
            return None
        vk = kernels.voxel_keys(pts, cfg.vox_size)
        uk, inv, cnt = kernels.unique_keys(vk)
        n = uk.numel()
        if cfg.global_encoding and gfeat is not None:
            fs = cnt.to(torch.float32)[:, None] * gfeat[None]
        else:
            assert feats is not None  # sem_feat_src without a global feature
            fs = aggregate_samples(feats, pix, hw, inv, n, cfg.interp_mode)
        if rgb_t is not None:
            cs = aggregate_samples(rgb_t, pix, hw, inv, n, cfg.interp_mode)
        else:
            cs = torch.zeros((n, 3), dtype=torch.float32, device=self.device)
        return (uk, cs, fs, cnt.to(torch.float32))

    def _frame_rays(self, pose_np: np.ndarray, g: FrameGeometry, hw: tuple[int, int], feats: torch.Tensor | None,
                    gfeat: torch.Tensor | None) -> RayBatch | None:
        """The frame's semantic rays (origins, unit directions, features), or None: one ray along
        camera +z with the image-level feature under ``global_encoding``, else the out-of-range rays."""
        cfg = self.cfg
        if cfg.global_encoding:
            gf: torch.Tensor | None
            if gfeat is not None:
                gf = gfeat
            else:
                gf = feats.to(torch.float32).mean((1, 2)) if feats is not None else None
            if gf is None:
                return None
            o = torch.as_tensor(pose_np[:3, 3], dtype=torch.float64, device=self.device)[None]
            dz = torch.as_tensor(pose_np[:3, 2], dtype=torch.float32, device=self.device)[None]
            return (o, dz / dz.norm(), gf[None])
        if g.ray_dirs.shape[0] and feats is not None:
            rf = sample_image(feats, g.ray_pix, hw, cfg.interp_mode)
            o = g.origin[None].expand(g.ray_dirs.shape[0], 3)
            return (o, g.ray_dirs, rf)
        return None

    def commit(self, p: PreparedFrame) -> dict[str, float]:
        """Second half of :meth:`integrate`: buffer a prepared frame and run the voxel / ray
        blocks that are due. Returns per-stage ms (the prepare stages included)."""
        cfg = self.cfg
        t_start = t = time.perf_counter()
        self.timings = {}
        for k, v in p.timings.items():
            self.timings[k] = self.timings.get(k, 0.0) + v
            self.timings_total[k] = self.timings_total.get(k, 0.0) + v
        self.last_fov_deg = p.fov_deg
        if p.sem is not None:
            self._buf_sem.append(p.sem)
        if p.rays is not None:
            self._buf_rays.append(p.rays)
        self._buf_occ.append((p.occ_ijk, p.free_ijk))

        counters = self.counters
        counters["frames"] += 1
        counters["vox"] += 1
        counters["occ_prune"] += 1
        counters["sem_prune"] += 1
        if counters["ray_phase"] < cfg.ray_accum_phase:
            counters["ray_phase"] += 1
        else:
            counters["ray"] += 1
        if counters["vox"] >= max(1, cfg.vox_accum_period):
            self._voxel_block()
        if cfg.semantic_rays and counters["ray"] >= max(1, cfg.ray_accum_period):
            self._ray_block()
        t = time.perf_counter()
        self.timings["commit"] = (t - t_start) * 1e3
        self.timings_total["commit"] = self.timings_total.get("commit", 0.0) + self.timings["commit"]
        tot = sum(p.timings.values()) + self.timings["commit"]
        self.timings["total"] = tot
        self.timings_total["total"] = self.timings_total.get("total", 0.0) + tot
        return dict(self.timings)

    # ------------------------------------------------------------------------------------
    def _voxel_block(self) -> None:
        cfg = self.cfg
        counters = self.counters
        counters["vox"] = 0
        counters["voxel_blocks"] += 1
        t = time.perf_counter()
        if not self._buf_occ and not self._buf_sem:
            return
        parts_ijk, parts_inc = [], []
        for occ, free in self._buf_occ:
            parts_ijk += [free, occ]
            parts_inc += [torch.full((free.shape[0],), -1, dtype=torch.int8),
                          torch.full((occ.shape[0],), cfg.occ_observ_weight - 1, dtype=torch.int8)]
        self._buf_occ = []
        ijk = torch.cat(parts_ijk) if parts_ijk else torch.empty((0, 3), dtype=torch.int64)
        if ijk.shape[0]:
            self.occupancy.update(ijk.cpu(), torch.cat(parts_inc).to(torch.int64))
        t = self._tick("occupancy", t)
        if self._buf_sem:
            uk, cs, fs, cnt = (torch.cat(x) for x in zip(*self._buf_sem, strict=True))
            self._buf_sem = []
            self.sem.fuse_sums(uk, cs, fs, cnt)
        t = self._tick("fuse", t)
        if ijk.shape[0] and cfg.sem_pruning_period > 0:
            self._pending_prune.append(torch.unique(cell_keys.pack(ijk)))
        if cfg.occ_pruning_period > 0 and counters["occ_prune"] >= cfg.occ_pruning_period:
            counters["occ_prune"] = 0
            self.occupancy.prune(cfg.occ_pruning_tolerance)
            t = self._tick("occ_prune", t)
        if cfg.sem_pruning_period > 0 and counters["sem_prune"] >= cfg.sem_pruning_period:
            counters["sem_prune"] = 0
            self.prune_semantic()
            t = self._tick("sem_prune", t)
        if ijk.shape[0]:
            self.fronts.update(self.occupancy, ijk.min(0).values, ijk.max(0).values,
                               min_unobserved=cfg.fronti_min_unobserved, min_free=cfg.fronti_min_empty,
                               min_occupied=cfg.fronti_min_occupied, radius=cfg.fronti_neighborhood_r)
        self._tick("frontiers", t)

    def prune_semantic(self) -> int:
        """Remove semantic voxels among those updated since the last prune whose occupancy
        value is <= ``sem_pruning_thresh``. Returns how many were removed."""
        if not self._pending_prune:
            return 0
        keys = torch.unique(torch.cat(self._pending_prune))
        self._pending_prune = []
        present = self.sem.index.lookup(keys) >= 0
        keys = keys[present]
        if keys.numel() == 0:
            return 0
        vals = torch.as_tensor(self.occupancy.query(cell_keys.unpack(keys).cpu())).to(self.device)
        return self.sem.remove(keys[vals.to(torch.int64) <= self.cfg.sem_pruning_thresh])

    def _ray_block(self) -> None:
        cfg = self.cfg
        self.counters["ray"] = 0
        self.counters["ray_blocks"] += 1
        t = time.perf_counter()
        fk = self.fronts.keys
        gone = self.fronts.take_removed()  # frontiers removed since the last ray block
        if gone is None:  # history unknown (restored table): prune against the whole table
            requeued = self.ray_store.prune(fk, requeue=cfg.ray_tracing)
        else:
            gone = gone[~self.fronts.contains(gone)] if gone.numel() else gone
            requeued = self.ray_store.prune_keys(gone, requeue=cfg.ray_tracing)
        t = self._tick("ray_prune", t)
        bufs = list(self._buf_rays)
        self._buf_rays = []
        if requeued is not None and requeued[0].shape[0]:
            bufs.append((requeued[0].to(torch.float64), requeued[1], requeued[2]))
        if bufs and fk.numel():
            o = torch.cat([b[0].to(torch.float64) for b in bufs])
            dr = torch.cat([b[1].to(torch.float32) for b in bufs])
            fe = torch.cat([b[2].to(torch.float32) for b in bufs])
            self._cast(o, dr, fe, t)
        if cfg.infer_direction and len(self.ray_store):
            t = time.perf_counter()
            uk = torch.unique(self.ray_store.fkey)
            dirs = infer_directions(self.occupancy, uk, cfg.beta, cfg.vox_size, cfg.infer_direction_scale)
            ok = dirs.norm(dim=1) > 0
            self.ray_store.set_frontier_directions(uk[ok], dirs[ok])
            self._tick("infer_direction", t)

    def _cast(self, o: torch.Tensor, dr: torch.Tensor, fe: torch.Tensor, t: float) -> None:
        cfg = self.cfg
        fk = self.fronts.keys
        rng = cfg.sensing_range()
        max_dist = cfg.ray_range_factor * rng if rng > 0 else -1.0
        if max_dist > 0 and not cfg.zero_depth_mode:
            # only frontiers within max_dist of a ray's origin can be its candidates
            ri, fi, cost = associate_near(o, dr, fk, cfg.beta, max_dist, reject_close=cfg.ray_reject_close,
                                          cost=cfg.ray_cost_norm)
        else:
            ri, fi, cost = associate(o, dr, cell_keys.unpack(fk), cfg.beta, max_dist=max_dist,
                                     reject_close=cfg.ray_reject_close, zero_depth=cfg.zero_depth_mode,
                                     cost=cfg.ray_cost_norm)
        t = self._tick("ray_associate", t)
        if cfg.ray_tracing and not cfg.zero_depth_mode and ri.numel():
            p = voxel_center(cell_keys.unpack(fk[fi]), cfg.beta).to(torch.float64)
            oo, dd = o[ri], dr[ri].to(torch.float64)
            tq = ((p - oo) * dd).sum(1)
            blocked = torch.as_tensor(self.occupancy.first_blocked(oo.cpu(), dd.cpu(), float(tq.max()) + cfg.vox_size))
            keep = blocked.to(self.device) >= tq - cfg.vox_size
            ri, fi, cost = ri[keep], fi[keep], cost[keep]
            t = self._tick("ray_trace", t)
        w = 1.0 - cost
        if cfg.ray_cost_norm == "paper" or cfg.zero_depth_mode:
            w = w.clamp_min(cfg.ray_min_weight)
        w = w.to(torch.float32)
        pos = w > 0          # absolute cost without floor: a ray at both limits carries nothing
        if not bool(pos.all()):
            ri, fi, w = ri[pos], fi[pos], w[pos]
        if ri.numel() == 0:
            return
        if cfg.ray_weight_normalize:
            w = w / w.sum()
        self.ray_store.merge(fk[fi], fk, dr[ri], fe[ri], w)
        self._tick("ray_merge", t)

    def has_buffered(self) -> bool:
        """Frames committed but not yet in a voxel / ray block (what :meth:`flush` integrates)."""
        return bool(self._buf_occ or self._buf_sem or self._buf_rays)

    def flush(self) -> None:
        """Run the voxel block and then the ray block now, whatever the counters say (the
        ray block also runs without buffered rays when rays exist: it prunes rays of
        vanished frontiers and re-infers directions against the final occupancy)."""
        if self._buf_occ or self._buf_sem:
            self._voxel_block()
        if self.cfg.semantic_rays and (self._buf_rays or len(self.ray_store)):
            self._ray_block()

    # ------------------------------------------------------------------------------------
    def voxels(self) -> VoxelLayer:
        """The semantic voxels in row order (:class:`VoxelLayer`; centres in m, world frame;
        copies of the rows)."""
        return VoxelLayer(self.sem.xyz(), self.sem.rgb.clone(), self.sem.feat.clone(), self.sem.count.clone())

    def frontiers(self) -> FrontierLayer:
        """The coarse frontier cells, sorted by packed key (:class:`FrontierLayer`; centres in m,
        cell size ``cfg.beta``; copies)."""
        return FrontierLayer(self.fronts.centres(), self.fronts.keys.clone(), self.fronts.counts.clone())

    def rays(self) -> RayLayer:
        """The ray bins by (frontier key, angle bin) (:class:`RayLayer`; origins are frontier
        centres in m, unit directions and angles in world axes; copies)."""
        rs = self.ray_store
        dirs = rs.directions()
        return RayLayer(rs.origins(), dirs, angles_deg(dirs).to(torch.float32), rs.feat,   # fields are copies
                        rs.weight, rs.fkey)

    def query(self, queries: ArrayOrTensor, *, similarity: Similarity | None = None, softmax: bool = False,
              temperature: float = 100.0, top_k: int = 10, denoise: float | None = None,
              threshold: float | None = None) -> LayerScores:
        """Similarity of every voxel and ray to each query (see :mod:`semantic_map.query`)."""
        q = _as_tensor(queries, torch.float32, self.device)
        rs = self.ray_store
        dirs = rs.directions()
        return run_query(q, self.sem.feat, self.sem.xyz(), rs.feat, rs.origins(), dirs,
                         similarity=similarity, softmax=softmax, temperature=temperature, top_k=top_k,
                         denoise=denoise, threshold=threshold)

    def cone_half_angle(self) -> float:
        a = self.cfg.cone_half_angle_deg
        return a if a > 0 else max(self.last_fov_deg) / 2

    # ------------------------------------------------------------------------------------
    def memory_bytes(self) -> int:
        """Bytes held by the semantic layers: voxels (rows at capacity and key index), ray
        bins (rows, index) and the frontier table. The occupancy grid is apart
        (:meth:`occupancy_memory_bytes`): it grows with observed space, not with voxels."""
        return int(sum(self.memory_parts().values()))

    def occupancy_memory_bytes(self) -> int:
        """Bytes held by the occupancy grid (OpenVDB ``memUsage``; torch: keys + values)."""
        return int(self.occupancy.memory_bytes())

    def memory_parts(self) -> dict[str, int]:
        """Bytes of each semantic layer: ``voxels`` (rows and key index), ``rays`` (bins and
        index), ``frontiers`` (the table); their sum is :meth:`memory_bytes`."""
        return {"voxels": int(self.sem.memory_bytes()), "rays": int(self.ray_store.memory_bytes()),
                "frontiers": int(self.fronts.memory_bytes())}

    def stats(self) -> dict:
        """Sizes (``n_voxels``, ``n_frontiers``, ``n_rays``, ``n_occupancy_active``), schedule
        (``frames``, ``voxel_blocks``, ``ray_blocks``), bytes, feature space and the per-stage
        ms summed over all frames (``timings_ms_total``). Walks the occupancy grid."""
        return dict(n_voxels=len(self.sem), n_frontiers=len(self.fronts), n_rays=len(self.ray_store),
                    n_occupancy_active=int(self.occupancy.num_active), frames=self.counters["frames"],
                    voxel_blocks=self.counters["voxel_blocks"], ray_blocks=self.counters["ray_blocks"],
                    memory_bytes=self.memory_bytes(), occupancy_memory_bytes=self.occupancy_memory_bytes(),
                    feature_dim=self.feature_dim,
                    feature_space=self.feature_space,
                    timings_ms_total={k: round(v, 3) for k, v in self.timings_total.items()})


    # ------------------------------------------------------------------ read access
    def occupancy_view(self) -> OccupancyView:
        """Read-only view of the occupancy grid (:class:`semantic_map.occupancy.base.OccupancyView`:
        int8 log-odds per voxel, ``ijk = floor(xyz / vox_size)``, world frame). The same
        object while the grid is the same one, so planners may cache per view and revision."""
        grid = self.occupancy
        view = self._occupancy_view
        if view is None or view._grid is not grid:
            view = self._occupancy_view = OccupancyView(grid)
        return view

    def voxel_xyz(self) -> torch.Tensor:
        """(N, 3) float32 semantic voxel centres (m), in the voxel rows' order (that of
        :meth:`voxels`), without copying the features."""
        return self.sem.xyz()

    def voxel_ijk(self) -> torch.Tensor:
        """(N, 3) int64 semantic voxel indices (``floor(xyz / vox_size)``), in row order."""
        return self.sem.ijk()

    def voxel_colours(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(keys, rgb)`` of the semantic voxels in row order: (N,) int64 packed voxel ijk
        (:mod:`semantic_map.cell_keys`) and (N, 3) mean colour in [0, 1] (feature dtype).
        Views of the live rows, valid until the map next changes; no feature copy."""
        return self.sem.keys, self.sem.rgb

    def ray_geometry(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(origins, directions, weights)`` of the ray bins in :meth:`rays` order, without
        the features: (R, 3) float32 frontier centres (m), (R, 3) float32 unit directions
        (world axes), (R,) float32 accumulated weights."""
        rs = self.ray_store
        return rs.origins(), rs.directions(), rs.weight

    def n_voxels(self) -> int:
        """Number of semantic voxels."""
        return len(self.sem)

    def n_frontiers(self) -> int:
        """Number of coarse frontier cells."""
        return len(self.fronts)

    def n_rays(self) -> int:
        """Number of ray bins (one per frontier and angle bin)."""
        return len(self.ray_store)

    def schedule_counters(self) -> dict[str, int]:
        """A copy of the integration schedule's counters: ``frames`` committed, frames since the
        last voxel block / occupancy prune / semantic prune / ray block (``vox``,
        ``occ_prune``, ``sem_prune``, ``ray``), ``ray_phase``, ``voxel_blocks``, ``ray_blocks``."""
        return dict(self.counters)

    # ------------------------------------------------------------------ direct writes
    def fuse_samples(self, xyz: torch.Tensor, rgb: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Fuse semantic points into the voxels directly, without depth, occupancy or rays
        (synthetic maps for benches and tests): ``xyz`` (P, 3) world metres, ``rgb`` (P, 3) in
        [0, 1], ``features`` (P, C). Returns the packed keys of the touched voxels (sorted)."""
        return self.sem.fuse(xyz, rgb, features)

    def fuse_sums(self, keys: torch.Tensor, rgb_sums: torch.Tensor, feature_sums: torch.Tensor,
                  counts: torch.Tensor) -> torch.Tensor:
        """As :meth:`fuse_samples` with samples pre-aggregated per voxel: packed voxel ``keys``
        (K,) (may repeat), sums of RGB (K, 3) and features (K, C) over ``counts`` (K,) points."""
        return self.sem.fuse_sums(keys, rgb_sums, feature_sums, counts)

    def remove_voxels(self, ijk: torch.Tensor) -> int:
        """Remove the semantic voxels ``ijk`` (K, 3) int64 (absent ones are ignored), as a
        semantic prune does (rows move); returns how many were removed."""
        return self.sem.remove(cell_keys.pack(ijk.to(self.device)))

    def replace_ray_bins(self, bins: Mapping[str, torch.Tensor]) -> None:
        """Replace every ray bin (synthetic maps for benches and tests): ``bins`` holds
        ``fkey`` (R,) int64 packed coarse frontier ijk, ``tbin`` / ``pbin`` (R,) int64 angle
        bins, ``feat`` (R, C), ``weight`` (R,) and ``dsum`` (R, 3) weighted direction sums;
        each (fkey, bin) pair once."""
        self.ray_store.load_state(dict(bins))

    # ------------------------------------------------------------------ whole state
    def export_state(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """``(arrays, meta)``: everything needed to continue exactly where the map stands,
        pending buffers included (nothing is flushed). ``arrays`` maps the names of
        docs/snapshot_format.md (``occ_ijk``, ``occ_values``, ``sem_*``, ``front_*``,
        ``ray_*``, ``rng_state``, ``buf_*``) to tensors or numpy arrays, some of them views
        of the map's memory (copy them before the map changes); ``meta`` is JSON-able:
        ``feature_dim``, ``feature_space``, ``counters``, ``occupancy`` (vox, lo, hi),
        ``last_fov_deg``, ``buffers`` (how many of each). The config is :attr:`cfg`."""
        arrays: dict[str, Any] = {}
        occ = self.occupancy.state()
        arrays["occ_ijk"], arrays["occ_values"] = occ["ijk"], occ["values"]
        for prefix, part in (("sem_", self.sem), ("front_", self.fronts), ("ray_", self.ray_store)):
            for k, v in part.state().items():
                arrays[prefix + k] = v
        arrays["rng_state"] = self.rng_state()  # after the last committed frame (mapper.pipeline)
        buffers = {"occ": len(self._buf_occ), "sem": len(self._buf_sem), "rays": len(self._buf_rays),
                   "prune": len(self._pending_prune)}
        for i, (a, b) in enumerate(self._buf_occ):
            arrays[f"buf_occ_{i}_occ"], arrays[f"buf_occ_{i}_free"] = a, b
        for name, bufs in (("sem", self._buf_sem), ("rays", self._buf_rays)):
            for i, parts in enumerate(bufs):
                for j, x in enumerate(parts):
                    arrays[f"buf_{name}_{i}_{j}"] = x
        for i, x in enumerate(self._pending_prune):
            arrays[f"buf_prune_{i}"] = x
        meta = {"feature_dim": self.feature_dim, "feature_space": self.feature_space,
                "counters": dict(self.counters),
                "occupancy": {"vox": float(occ["vox"]), "lo": int(occ["lo"]), "hi": int(occ["hi"])},
                "last_fov_deg": list(self.last_fov_deg), "buffers": buffers}
        return arrays, meta

    @classmethod
    def from_state(cls, cfg: MapConfig, arrays: Mapping[str, Any], meta: Mapping[str, Any],
                   device: str | torch.device = "cpu", occupancy_backend: str = "auto") -> RayFrontsMap:
        """A map restored from :meth:`export_state`'s ``(arrays, meta)`` (numpy arrays or
        tensors) with config ``cfg``: same answers bit for bit, and the next frames integrate
        as they would have. A missing array is ``arrays[name]``'s error (KeyError for a dict)."""
        m = cls(cfg, meta["feature_dim"], meta["feature_space"], device=device, occupancy_backend=occupancy_backend)

        def saved(name: str) -> torch.Tensor:
            return torch.as_tensor(arrays[name]).to(device)

        occ = dict(meta["occupancy"], ijk=arrays["occ_ijk"], values=arrays["occ_values"])
        m.occupancy = occupancy_from_state(occ, backend=occupancy_backend)
        m.sem.load_state({k: saved("sem_" + k) for k in ("keys", "rgb", "feat", "count")})
        m.fronts.load_state({k: saved("front_" + k) for k in ("keys", "counts")})
        m.ray_store.load_state({k: saved("ray_" + k) for k in m.ray_store._fields()})
        m.generator.set_state(torch.as_tensor(arrays["rng_state"]))
        m.counters = dict(meta["counters"])
        m.last_fov_deg = tuple(meta["last_fov_deg"])
        b = meta["buffers"]
        m._buf_occ = [(saved(f"buf_occ_{i}_occ"), saved(f"buf_occ_{i}_free")) for i in range(b["occ"])]
        m._buf_sem = [(saved(f"buf_sem_{i}_0"), saved(f"buf_sem_{i}_1"), saved(f"buf_sem_{i}_2"),
                       saved(f"buf_sem_{i}_3")) for i in range(b["sem"])]
        m._buf_rays = [(saved(f"buf_rays_{i}_0"), saved(f"buf_rays_{i}_1"), saved(f"buf_rays_{i}_2"))
                       for i in range(b["rays"])]
        m._pending_prune = [saved(f"buf_prune_{i}") for i in range(b["prune"])]
        return m
