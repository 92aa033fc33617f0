"""The RayFronts map: semantic voxels, occupancy, frontiers and semantic ray frontiers.

Computation only — no I/O, no transport, no threads (``tests/test_layers.py`` holds it to
that). Usable on its own::

    from semantic_map import RayFrontsMap, MapConfig
    m = RayFrontsMap(MapConfig(), feature_dim=384)

Outside this package the map is reached through ``RayFrontsMap``'s methods only (its parts,
``occupancy``, ``sem``, ``fronts``, ``ray_store`` ..., are its own; ``tests/test_map_api.py``):
layers (``voxels``, ``frontiers``, ``rays``, ``voxel_xyz``, ``ray_geometry`` ...), the
read-only ``occupancy_view``, ``stats`` / ``memory_parts``, ``export_state`` /
``RayFrontsMap.from_state`` for snapshots. ``voxel_components_26`` is the map's C++ kernel
for the 26-connected components of a sorted voxel key set (the planners' instance labelling),
``voxel_instance_groups`` the one for the kept groups' statistics of such a labelled set,
``voxel_key_order`` the one sorting a voxel key set (its stable argsort).

Conventions (frames, units, voxel indexing) are those of ``docs/conventions.md``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from semantic_map.config import MapConfig
    from semantic_map.map import RayFrontsMap
    from semantic_map.occupancy.base import OccupancyView

__all__ = ["RayFrontsMap", "MapConfig", "OccupancyView", "voxel_components_26", "voxel_instance_groups",
           "voxel_key_order"]


def __getattr__(name: str):  # lazy, so that `from semantic_map import kernels` loads no map
    if name == "RayFrontsMap":
        from semantic_map.map import RayFrontsMap
        return RayFrontsMap
    if name == "MapConfig":
        from semantic_map.config import MapConfig
        return MapConfig
    if name == "OccupancyView":  # what RayFrontsMap.occupancy_view() hands out (read-only)
        from semantic_map.occupancy.base import OccupancyView
        return OccupancyView
    if name == "voxel_components_26":  # the C++ labelling of a voxel key set (None: kernels off)
        from semantic_map.kernels import components_26_sorted
        return components_26_sorted
    if name == "voxel_instance_groups":  # the C++ group step of instance tracking (None: kernels off)
        from semantic_map.kernels import instance_groups
        return instance_groups
    if name == "voxel_key_order":  # the C++ stable argsort of a voxel key set (None: kernels off)
        from semantic_map.kernels import argsort_voxel_keys
        return argsort_voxel_keys
    raise AttributeError(name)
