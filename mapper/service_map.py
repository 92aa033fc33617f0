"""What the mapper process does with its map, kept free of Zenoh: create/load the map,
integrate a decoded frame, flush, read the layers (module map: ARCHITECTURE.md).
Query answering is :mod:`mapper.query_answer`.
World frame, metres, z up.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from common.conventions import voxel_center
from common.messages import MessageError
from mapper.query_answer import to_numpy

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from common.frame import Frame
    from semantic_map.config import MapConfig
    from semantic_map.map import RayFrontsMap


# what this module reads of mapper.service_config's sections (which import this module's
# users: protocols, not imports, keep the modules free of a cycle)
class MapSettings(Protocol):
    """The map settings of :class:`mapper.service_config.MapperConfig`."""

    map: MapConfig
    device: str
    occupancy_backend: str


class LayerLimits(Protocol):
    """The layer limits of :class:`mapper.service_config.LayersSection`."""

    max_voxels: int
    max_rays: int


# ------------------------------------------------------------------- map life
def create_map(cfg: MapSettings, fs: FeatureSpace) -> RayFrontsMap:
    """A new RayFrontsMap for feature space ``fs`` with the service config's map section."""
    from semantic_map.map import RayFrontsMap

    return RayFrontsMap(cfg.map, fs.dim, fs.id, device=cfg.device, occupancy_backend=cfg.occupancy_backend)


def restore_map(path: str | Path, cfg: MapSettings, fs: FeatureSpace) -> RayFrontsMap:
    """The map saved at ``path`` (a snapshot's ``map`` directory), checked against space ``fs``."""
    from mapper.snapshot import load_map
    from semantic_map.map import RayFrontsMap

    m = load_map(path, RayFrontsMap, device=cfg.device, occupancy_backend=cfg.occupancy_backend)
    got_id = getattr(m, "feature_space", "")
    if got_id and got_id != fs.id:
        raise MessageError(f"snapshot map space {got_id} != its feature_space file {fs.id}")
    return m


def integrate(m: RayFrontsMap, frame: Frame, device: str | torch.device = "cpu") -> None:
    """Fuse one decoded (validated) frame into the map."""
    # decoded arrays are read-only views of the message: hand the map writable copies
    g = None if frame.global_feature is None else np.array(frame.global_feature)
    m.integrate(frame.pose, frame.intrinsics, frame.depth, np.array(frame.rgb), np.array(frame.features), g)


def flush(m: RayFrontsMap) -> None:
    """Process whatever the map holds in its accumulation buffers."""
    m.flush()


def map_stats(m: RayFrontsMap) -> dict:
    s = m.stats()
    return dict(s) if isinstance(s, dict) else {"stats": str(s)}


# --------------------------------------------------------------- map accessors
def voxel_arrays(m: RayFrontsMap) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """``(xyz (N,3) float32 centres, features (N,D) tensor, rgb (N,3) uint8)``."""
    v = m.voxels()
    xyz = to_numpy(v.xyz).astype(np.float32, copy=False)
    rgb = np.clip(to_numpy(v.rgb).astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return xyz, v.features, rgb


def ray_arrays(m: RayFrontsMap) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """``(origins (R,3), unit directions (R,3), features (R,D))``."""
    r = m.rays()
    return to_numpy(r.origins).astype(np.float32), to_numpy(r.directions).astype(np.float32), r.features


def frontier_xyz(m: RayFrontsMap) -> np.ndarray:
    return to_numpy(m.frontiers().centres).astype(np.float32).reshape(-1, 3)


def layer_arrays(m: RayFrontsMap, layer: str, lcfg: LayerLimits) -> tuple[dict, dict]:
    """Arrays and meta of one map layer, subsampled to the layer limits (seeded, stable)."""
    rng = np.random.default_rng(0)
    if layer == "voxels":
        # straight from the voxel store: only the kept rows are decoded (no feature copies)
        from semantic_map import cell_keys

        keys, rgb = m.voxel_colours()
        n = len(keys)
        if n > lcfg.max_voxels:
            idx = torch.from_numpy(np.sort(rng.choice(n, lcfg.max_voxels, replace=False))).to(keys.device)
            keys, rgb = keys[idx], rgb[idx]
        centres = voxel_center(cell_keys.unpack(keys), float(m.cfg.vox_size))
        xyz = to_numpy(centres).astype(np.float32, copy=False).reshape(-1, 3)
        rgb = np.clip(to_numpy(rgb).astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8).reshape(-1, 3)
        return {"xyz": xyz, "rgb": rgb}, {"total": n, "vox_size": float(m.cfg.vox_size)}
    if layer == "frontiers":
        f = frontier_xyz(m)
        return {"xyz": f}, {"total": len(f)}
    if layer == "rays":
        ro, rd, _ = m.ray_geometry()
        o = to_numpy(ro).astype(np.float32).reshape(-1, 3)
        d = to_numpy(rd).astype(np.float32).reshape(-1, 3)
        n = len(o)
        if n > lcfg.max_rays:
            ridx = np.sort(rng.choice(n, lcfg.max_rays, replace=False))
            o, d = o[ridx], d[ridx]
        return {"origin": o, "direction": d}, {"total": n}
    if layer == "occupancy":
        return {}, {k: v for k, v in map_stats(m).items() if isinstance(v, (int, float, str, bool))}
    raise MessageError(f"unknown layer {layer!r}")
