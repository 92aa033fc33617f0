"""The RayFronts map: semantic voxels, occupancy, frontiers and semantic ray frontiers.

Computation only — no I/O, no transport, no threads (``tests/test_layers.py`` holds it to
that). Usable on its own::

    from semantic_map import RayFrontsMap, MapConfig
    m = RayFrontsMap(MapConfig(), feature_dim=384)

Conventions (frames, units, voxel indexing) are those of ``docs/conventions.md``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from semantic_map.config import MapConfig
    from semantic_map.map import RayFrontsMap
    from semantic_map.occupancy.base import OccupancyGrid

__all__ = ["RayFrontsMap", "MapConfig", "OccupancyGrid"]


def __getattr__(name: str):  # lazy, so that `from semantic_map import kernels` loads no map
    if name == "RayFrontsMap":
        from semantic_map.map import RayFrontsMap
        return RayFrontsMap
    if name == "MapConfig":
        from semantic_map.config import MapConfig
        return MapConfig
    if name == "OccupancyGrid":      # the occupancy grid's interface (what planners read)
        from semantic_map.occupancy.base import OccupancyGrid
        return OccupancyGrid
    raise AttributeError(name)
