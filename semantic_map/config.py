"""RayFronts map configuration: every hyperparameter of the paper's appendix tables and of
the reference's ``semantic_ray_frontiers_map.yaml`` (docs/method.md#presets), with presets.

Conventions: lengths in metres, angles in degrees, periods in frames, occupancy values
are int8 log-odds counts. Schema defaults are the reference's shipped YAML (``default``
preset); ``online`` / ``throughput`` / ``offline`` are the paper's tables (docs/method.md#presets).
A period ``<= 0`` disables the step it schedules.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.config import ConfigError, field_, merge

FORMAT_FEATURE_DTYPES = ("float32", "float16")


@dataclass
class MapConfig:
    # --- voxels / occupancy -------------------------------------------------------------
    vox_size: float = field_(0.3, "voxel size alpha (m)")
    vox_accum_period: int = field_(8, "frames buffered before voxels/occupancy/frontiers are updated")
    max_pts_per_frame: int = field_(-1, "max occupied (surface) points per frame, -1 = all")
    max_empty_pts_per_frame: int = field_(
        -1, "max free-space samples per frame: when the exact traversal has more (ray, voxel) "
            "steps, this many points are drawn uniformly along the free ray segments; -1 = exact traversal")
    free_space_stride: int = field_(
        1, "free space from every k-th pixel row/column only (1 = every pixel, exact; -1 = auto: "
           "largest k whose neighbouring rays stay within vox/2 at the sensing range)")
    point_selection: Literal["random", "confidence"] = field_(
        "random", "how budgets pick points: seeded random, or most confident first (needs a confidence map)")
    max_depth_sensing: float = field_(
        -1.0, "sensing range (m): +inf pixels carve free space up to it and ray association is "
              "limited to ray_range_factor times it; <0 = use depth_limit, or the frame's max depth")
    depth_limit: float = field_(-1.0, "finite depth above this (m) becomes +inf (simulated sensor range); <0 = off")
    occ_thickness: int = field_(
        1, "occupied samples per surface pixel, spaced vox/2 along the ray, centred on the depth")
    occ_observ_weight: int = field_(7, "occupied observation adds (w - 1), free adds -1")
    max_empty_cnt: int = field_(5, "log-odds lower clamp is -max_empty_cnt")
    max_occ_cnt: int = field_(30, "log-odds upper clamp (<= 127)")
    occ_pruning_period: int = field_(8, "frames between occupancy prunes (tile merge), <=0 = never")
    occ_pruning_tolerance: int = field_(2, "values within +-tolerance are merged into a tile")
    sem_pruning_period: int = field_(8, "frames between semantic voxel prunes, <=0 = never")
    sem_pruning_thresh: int = field_(0, "semantic voxels whose occupancy value <= this are removed")
    clip_bbox: list[float] | None = field_(
        None, "[xmin,ymin,zmin,xmax,ymax,zmax] world box; geometry outside is dropped")
    feature_dtype: Literal["float32", "float16"] = field_(
        "float32", "storage dtype of voxel/ray features (accumulation is float32)")
    interp_mode: Literal["bilinear", "nearest"] = field_("bilinear", "how features/RGB are sampled at pixel centres")
    # --- frontiers ----------------------------------------------------------------------
    fronti_neighborhood_r: int = field_(1, "frontier neighbourhood radius (cells), (2r+1)^3 self included")
    fronti_min_unobserved: int = field_(9, "min unobserved cells in the neighbourhood")
    fronti_min_empty: int = field_(4, "min free cells in the neighbourhood")
    fronti_min_occupied: int = field_(0, "min occupied cells in the neighbourhood")
    fronti_subsampling: int = field_(5, "coarse frontier cell = vox_size * this (beta); 1 = no subsampling "
                                        "(every fine frontier voxel, min_fronti unused, as the reference)")
    fronti_subsampling_min_fronti: int = field_(
        12, "a coarse cell is a frontier if it holds MORE than this many fine frontiers (only when "
            "fronti_subsampling > 1)")
    # --- rays ---------------------------------------------------------------------------
    semantic_rays: bool = field_(True, "cast semantic rays (False = the Semantic Voxels baseline)")
    max_rays_per_frame: int = field_(-1, "max out-of-range rays per frame, -1 = all")
    ray_erosion: int = field_(
        4, "erosion radius (px) of the out-of-range mask; outside the image counts as out of range")
    ray_accum_period: int = field_(8, "frames buffered before rays are cast")
    ray_accum_phase: int = field_(4, "frames before the ray counter starts (offsets ray from voxel blocks)")
    ray_tracing: bool = field_(
        True, "validate associations by tracing through occupancy; re-cast rays of vanished frontiers")
    angle_bin_size: float = field_(20.0, "ray angle bin psi (deg); >= 360 = one bin per frontier (semantic frontiers)")
    ray_range_factor: float = field_(
        4.0, "frontiers farther than this times the sensing range are not candidates (paper 4, reference 3)")
    ray_reject_close: bool = field_(
        False, "reference rule: frontiers closer than 2*beta to the ray origin are not candidates")
    ray_cost_norm: Literal["paper", "absolute"] = field_(
        "paper", "ray-frontier cost scale: 'paper' = per ray over its candidates (the paper's equation; a lone "
                 "candidate costs 1, weight floored at ray_min_weight), 'absolute' = d_ortho/beta and "
                 "d_orig/(ray_range_factor*range), no floor (semantic_map.ray_frontiers)")
    ray_min_weight: float = field_(
        0.05, "floor of the ray weight 1 - cost in the 'paper' cost mode (its per-ray normalised cost is 1 for a "
              "lone candidate)")
    ray_weight_normalize: bool = field_(False, "reference behaviour: normalise weights to sum 1 per cast batch")
    zero_depth_mode: bool = field_(False, "no depth: each ray goes to the nearest frontier, no direction test")
    global_encoding: bool = field_(
        False, "Semantic Poses: one ray per frame along camera +z with the image-level feature")
    infer_direction: bool = field_(
        False, "Unidirectional: ray directions inferred from the unobserved neighbourhood of the frontier")
    infer_direction_scale: Literal["coarse", "fine"] = field_(
        "fine", "neighbourhood offsets for infer_direction: fine voxels (vox, the reference's +-1 voxel) or "
                "coarse cells (beta)")
    # --- search volumes / misc ----------------------------------------------------------
    cone_half_angle_deg: float = field_(-1.0, "search-volume cone half-angle (deg); <0 = max(FoV)/2 of the last frame")
    seed: int = field_(17, "seed of the point/ray subsampling generator")

    def validate(self) -> "MapConfig":
        if not self.vox_size > 0:
            raise ConfigError(f"vox_size must be > 0, got {self.vox_size}")
        if not 0 < self.max_occ_cnt <= 127:
            raise ConfigError(f"max_occ_cnt must be in 1..127 (int8), got {self.max_occ_cnt}")
        if not 0 < self.max_empty_cnt <= 128:
            raise ConfigError(f"max_empty_cnt must be in 1..128 (int8), got {self.max_empty_cnt}")
        if not 1 <= self.occ_observ_weight <= 128:
            raise ConfigError(f"occ_observ_weight must be in 1..128 (the occupied increment occ_observ_weight - 1 "
                              f"is an int8, <= 127), got {self.occ_observ_weight}")
        if self.occ_thickness < 1:
            raise ConfigError(f"occ_thickness must be >= 1, got {self.occ_thickness}")
        if self.fronti_subsampling < 1:
            raise ConfigError(f"fronti_subsampling must be >= 1, got {self.fronti_subsampling}")
        if self.angle_bin_size <= 0:
            raise ConfigError(f"angle_bin_size must be > 0, got {self.angle_bin_size}")
        if self.ray_erosion < 0:
            raise ConfigError(f"ray_erosion must be >= 0, got {self.ray_erosion}")
        if self.clip_bbox is not None and len(self.clip_bbox) != 6:
            raise ConfigError("clip_bbox must have 6 numbers [xmin,ymin,zmin,xmax,ymax,zmax]")
        if self.ray_cost_norm not in ("paper", "absolute"):
            raise ConfigError(f"ray_cost_norm must be paper|absolute, got {self.ray_cost_norm!r}")
        if self.point_selection not in ("random", "confidence"):
            raise ConfigError(f"point_selection must be random|confidence, got {self.point_selection!r}")
        return self

    @property
    def beta(self) -> float:
        """Coarse frontier cell size (m)."""
        return self.vox_size * self.fronti_subsampling

    def sensing_range(self) -> float:
        """Range used for +inf carving and association cutoff; <= 0 means unknown."""
        if self.max_depth_sensing >= 0:
            return self.max_depth_sensing
        if self.depth_limit >= 0:
            return self.depth_limit
        return -1.0


_ONLINE = dict(  # paper Table (online search-volume evaluation) + the reference's srchvol configs
    vox_size=1.0, vox_accum_period=2, max_pts_per_frame=-1, max_empty_pts_per_frame=-1,
    max_rays_per_frame=10000, fronti_neighborhood_r=1, fronti_min_unobserved=9,
    fronti_min_empty=4, fronti_min_occupied=0, fronti_subsampling=4,
    fronti_subsampling_min_fronti=5, ray_erosion=32, ray_tracing=True, angle_bin_size=30.0,
    max_occ_cnt=100, max_empty_cnt=10, occ_observ_weight=100, occ_thickness=2,
    occ_pruning_tolerance=2, ray_accum_period=8, ray_accum_phase=4, depth_limit=20.0,
    free_space_stride=-1,
)
_THROUGHPUT = dict(  # paper Table (mapping throughput)
    vox_size=0.3, fronti_neighborhood_r=1, fronti_min_unobserved=9, fronti_min_occupied=0,
    fronti_min_empty=4, fronti_subsampling=4, fronti_subsampling_min_fronti=5, ray_erosion=0,
    ray_tracing=False, angle_bin_size=30.0, max_occ_cnt=100, max_empty_cnt=10,
    occ_observ_weight=100, occ_thickness=1, occ_pruning_tolerance=2, max_rays_per_frame=1000,
    max_pts_per_frame=3000, max_empty_pts_per_frame=10000, vox_accum_period=8,
    ray_accum_period=8, ray_accum_phase=4, sem_pruning_period=32, occ_pruning_period=32,
    feature_dtype="float16",
)
_OFFLINE = dict(  # offline semseg (docs/method.md#presets): semantic voxels only (SemanticVoxelMap), 0.05 m (indoor)
    vox_size=0.05, vox_accum_period=4, max_pts_per_frame=-1, semantic_rays=False,
    occ_pruning_period=-1, sem_pruning_period=-1,
)

PRESETS: dict[str, dict] = {
    "default": {},
    "online": _ONLINE,
    "throughput": _THROUGHPUT,
    "offline": _OFFLINE,
}

# The paper's baselines (Table I) as overrides on top of a preset. Ray tracing per method as
# the reference runs them (its experiments/srchvol_configs): on for RayFronts (the
# preset's value; the online preset has it on), off for the two semantic-frontier baselines
# (their rays are dropped, not re-cast, when a frontier vanishes); the zero-depth methods
# never trace (no occupancy along the ray) and Semantic Voxels casts no rays.
METHODS: dict[str, dict] = {
    "rayfronts": {},
    "rayfronts_zero_depth": dict(zero_depth_mode=True, depth_limit=0.0, fronti_min_unobserved=0,
                                 fronti_min_empty=0, fronti_min_occupied=0,
                                 fronti_subsampling_min_fronti=1),
    "semantic_poses": dict(zero_depth_mode=True, global_encoding=True, depth_limit=0.0,
                           fronti_min_unobserved=0, fronti_min_empty=0, fronti_min_occupied=0,
                           fronti_subsampling_min_fronti=1),
    "semantic_voxels": dict(semantic_rays=False),
    "spherical_semfronts": dict(angle_bin_size=360.0, infer_direction=False, ray_tracing=False),
    "unidirectional_semfronts": dict(angle_bin_size=360.0, infer_direction=True, ray_tracing=False),
}


def map_config(preset: str = "default", overrides: dict | None = None, method: str | None = None) -> MapConfig:
    """``MapConfig`` from a preset name, an optional baseline ``method`` and a dict of overrides."""
    if preset not in PRESETS:
        raise ConfigError(f"unknown map preset {preset!r}; choose one of {sorted(PRESETS)}")
    cfg = merge(MapConfig(), PRESETS[preset])
    if method is not None:
        if method not in METHODS:
            raise ConfigError(f"unknown method {method!r}; choose one of {sorted(METHODS)}")
        cfg = merge(cfg, METHODS[method])
    if overrides:
        cfg = merge(cfg, overrides)
    return cfg.validate()
