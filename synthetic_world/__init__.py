"""The procedural synthetic outdoor world: data for the demo, ground truth for the tests,
scenes for the benchmarks (docs/synthetic_world.md).

    from synthetic_world import World
    w = World.generate(seed=0)
    poses = w.trajectory("ground", n_frames=100)
    K = w.camera((480, 640), hfov_deg=90)
    r = w.render(poses[0], K, (480, 640))   # r.rgb, r.depth (planar, +inf sky), r.labels, r.instance

World frame z up (x east, y north), ground at z = 0; poses camera-to-world, RDF camera axes.
"""
from .classes import CLASS_COLORS, CLASS_NAMES, FAR_CLASSES, IN_RANGE_CLASSES
from .parts import Part
from .primitives import Box, Cone, Cylinder, Frustum, Sphere
from .render import Render
from .scene import Instance, World

__all__ = ["World", "Part", "Instance", "Render", "Box", "Frustum", "Cylinder", "Cone", "Sphere",
           "CLASS_NAMES", "CLASS_COLORS", "IN_RANGE_CLASSES", "FAR_CLASSES"]
