"""The assets of the pybullet world (docs/pybullet_world.md has the same table).

Every asset is a file that ships with the ``pybullet`` wheel (``pybullet_data``), loaded with
``globalScaling=scale`` and a fixed base. ``role``: ``ground`` (the plane), ``site`` (the
samurai monastery: halls, pagoda, gate, stairs, rocks, one concave mesh ~125 × 121 × 30 m),
``object`` (placed on open ground in the site, targets of ``object`` missions) or
``landmark`` (a tall asset scaled up and placed far outside the site, targets of
``landmark`` missions). ``count``: how many of it a scene holds. The class name of each body
is the asset's ``class_name``; class 0 is ``sky`` (no surface), as in the synthetic world.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Asset:
    """One pybullet_data asset as the world uses it (``scale``: globalScaling, no unit)."""

    class_name: str
    file: str
    scale: float
    role: str
    count: int = 1


ASSETS: tuple[Asset, ...] = (
    Asset("ground", "plane.urdf", 1.5, "ground"),
    Asset("monastery", "samurai.urdf", 1.0, "site"),
    Asset("table", "table/table.urdf", 1.5, "object", 2),
    Asset("teddy bear", "teddy_large.urdf", 1.0, "object", 2),
    Asset("duck", "duck_vhacd.urdf", 12.0, "object", 2),
    Asset("r2d2", "r2d2.urdf", 1.5, "object", 2),
    Asset("husky", "husky/husky.urdf", 1.5, "object", 2),
    Asset("racecar", "racecar/racecar.urdf", 3.0, "object", 2),
    Asset("shelf", "kiva_shelf/model.sdf", 1.0, "object", 2),
    Asset("soccer ball", "soccerball.urdf", 1.0, "object", 2),
    Asset("random object", "random_urdfs/000/000.urdf", 10.0, "object", 2),
    Asset("teddy bear statue", "teddy_large.urdf", 8.0, "landmark"),
    Asset("robot statue", "r2d2.urdf", 24.0, "landmark"),
)

#: class names, index = class id (0 = sky: no surface)
CLASS_NAMES: tuple[str, ...] = ("sky",) + tuple(dict.fromkeys(a.class_name for a in ASSETS))
OBJECT_CLASSES: tuple[str, ...] = tuple(a.class_name for a in ASSETS if a.role == "object")
LANDMARK_CLASSES: tuple[str, ...] = tuple(a.class_name for a in ASSETS if a.role == "landmark")
