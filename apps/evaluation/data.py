"""Frames and ground truth for the benchmarks.

* :func:`load_frames` — read a source once (no depth limit) into memory (each frame is
  rendered / read exactly once; every method is then fed the same frames).
* :func:`ground_truth` — the scene volume and per-voxel GT classes at voxel size ``vox``:

  - scene volume = every voxel a full-range occupancy pass over the trajectory observes
    (the reference's construction, docs/method.md#evaluation: all active voxels, free or occupied), with
    depth beyond ``gt_range`` treated as out of range (+inf pixels carve free space up to
    ``gt_range``, like the reference's 50 m TartanAir cutoff). To keep it affordable the
    pass may use every ``frame_stride``-th frame and every ``pixel_stride``-th pixel.
    ``scene_volume="bbox"`` takes instead every voxel of the pass's bounding box.
  - classes: the synthetic world's exact geometry (``World.voxel_labels``) when a world
    is given, else the majority of the fused one-hot GT label images (label 0 = none →
    ``IGNORE``); voxels of the volume without a label are ``EMPTY`` (0).

Voxel index convention: ``floor(xyz / vox)`` (``common.conventions.voxel_index``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import torch

from apps.evaluation.metrics import EMPTY, IGNORE
from common.frame import Frame

if TYPE_CHECKING:
    from edge.sources import FrameSource, SourceConfig
    from synthetic_world import World


@dataclass
class GroundTruth:
    ijk: np.ndarray        # (V, 3) int64 scene-volume voxels, sorted by packed key
    keys: np.ndarray       # (V,) int64 packed keys (ascending)
    labels: np.ndarray     # (V,) int64: IGNORE, EMPTY or class id
    vox: float
    class_names: list[str]

    def centres(self) -> np.ndarray:
        return (self.ijk.astype(np.float64) + 0.5) * self.vox

    def class_counts(self) -> np.ndarray:
        """(K,) voxels per class id (index 0 unused)."""
        lab = self.labels[self.labels > 0]
        return np.bincount(lab, minlength=len(self.class_names))


def pack(ijk: npt.ArrayLike) -> np.ndarray:
    from semantic_map import cell_keys
    return cell_keys.pack(torch.as_tensor(np.asarray(ijk), dtype=torch.int64)).numpy()


def load_frames(source_cfg: SourceConfig, progress: bool = True,
                world: World | None = None) -> tuple[list[Frame], FrameSource]:
    """All frames of the source (depth limit removed) and the source object."""
    from edge.sources import open_source

    cfg = dataclasses.replace(source_cfg, depth_limit=None, progress=progress)
    src = open_source(cfg, world=world) if (world is not None and cfg.kind == "synthetic") else open_source(cfg)
    frames = list(src)
    if not frames:
        raise ValueError(f"source {src.name!r} yielded no frames")
    return frames, src


def subsample_frame(depth: np.ndarray, K: np.ndarray, stride: int, labels: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Every ``stride``-th pixel (pixel centres at +0.5): depth, K and labels."""
    if stride <= 1:
        return depth, K, labels
    d = np.ascontiguousarray(depth[::stride, ::stride])
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, 0] /= stride
    K2[1, 1] /= stride
    K2[0, 2] = (K[0, 2] - 0.5) / stride + 0.5
    K2[1, 2] = (K[1, 2] - 0.5) / stride + 0.5
    lab = None if labels is None else np.ascontiguousarray(labels[::stride, ::stride])
    return d, K2, lab


def ground_truth(frames: list[Frame], class_names: list[str], vox: float, gt_range: float = 50.0,
                 world: World | None = None, frame_stride: int = 1, pixel_stride: int = 1,
                 scene_volume: str = "observed",
                 occupancy_backend: str = "auto", progress: bool = False) -> GroundTruth:
    """Scene volume and GT classes (see module doc)."""
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap

    if scene_volume not in ("observed", "bbox"):
        raise ValueError(f"scene_volume must be 'observed' or 'bbox', got {scene_volume!r}")
    nc = len(class_names)
    fuse_labels = world is None
    cfg = map_config("online", dict(vox_size=vox, depth_limit=float(gt_range), semantic_rays=False,
                                    occ_pruning_period=-1, sem_pruning_period=-1, interp_mode="nearest",
                                    vox_accum_period=2))
    gmap = RayFrontsMap(cfg, max(nc, 1), "gt-onehot", occupancy_backend=occupancy_backend)
    sel = frames[::max(1, frame_stride)]
    it = sel
    if progress:
        from tqdm import tqdm
        it = tqdm(sel, desc="ground truth", unit="frame")
    for f in it:
        d, K, lab = subsample_frame(f.depth, f.intrinsics, pixel_stride, f.labels)
        feats = None
        if fuse_labels:
            if lab is None:
                raise ValueError("the source provides no GT labels; the search-volume/semseg GT needs them")
            lt = torch.as_tensor(lab.astype(np.int64)).clamp(0, nc - 1)
            feats = torch.nn.functional.one_hot(lt, nc).permute(2, 0, 1).to(torch.float32)
        gmap.integrate(f.pose, K, d, None, feats, None)
    gmap.flush()
    ijk: Any                               # the torch indices, then numpy int64
    ijk, _ = gmap.occupancy_view().active()
    ijk = ijk.numpy().astype(np.int64)
    if scene_volume == "bbox" and len(ijk):
        lo, hi = ijk.min(0), ijk.max(0)
        g = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)], indexing="ij"), -1)
        ijk = g.reshape(-1, 3)
    keys = pack(ijk)
    order = np.argsort(keys, kind="stable")
    ijk, keys = ijk[order], keys[order]
    if world is not None:
        labels = world.voxel_labels(ijk, vox).astype(np.int64)
    else:
        labels = np.full(len(ijk), EMPTY, dtype=np.int64)
        vl = gmap.voxels()
        if vl.xyz.shape[0]:
            vk = pack(np.floor(vl.xyz.numpy().astype(np.float64) / vox).astype(np.int64))
            cls = vl.features.to(torch.float32).argmax(1).numpy().astype(np.int64)
            pos = np.searchsorted(keys, vk).clip(max=max(len(keys) - 1, 0))
            hit = keys[pos] == vk if len(keys) else np.zeros(len(vk), bool)
            labels[pos[hit]] = np.where(cls[hit] == 0, IGNORE, cls[hit])
    return GroundTruth(ijk, keys, labels, vox, list(class_names))
