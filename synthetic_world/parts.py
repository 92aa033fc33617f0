"""The building blocks the world generator produces and :class:`synthetic_world.World` is made of:
:class:`Part` (one labelled primitive) and :class:`Layout` (what the generator knows about
the town). Their own module so the generator and the scene both import them and not each
other.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from . import primitives


@dataclass(frozen=True)
class Part:
    """One primitive of an object: ``shape`` with its ``class_name``, the ``instance`` name it
    belongs to (parts with the same name form one instance) and an optional RGB colour
    (default: the class colour)."""

    shape: primitives.Shape
    class_name: str
    instance: str
    color: tuple[int, ...] | None = None                 # RGB 0-255


@dataclass
class Layout:
    """What the generator knows about the town (used by the trajectories)."""

    half_x: float = 40.0
    half_y: float = 25.0
    corner_radius: float = 8.0
    road_top: float = 0.02
    extra: dict = field(default_factory=dict)
