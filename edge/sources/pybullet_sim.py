"""A robot in pybullet (``source.kind=pybullet``): the pybullet world of ``source.seed``
(:mod:`synthetic_world.pybullet_world`, scenes of pybullet_data assets) rendered by
pybullet's CPU renderer at the camera poses a simulator sends over Zenoh — the
``sim_camera`` source (same key ``<p>/robots/<robot>/sim/views``, same queue, counters and
``sky_depth``) with another world. Frames carry RGB, planar depth (+inf, or NaN with
``sky_depth=nan``, where no surface) and the class labels from pybullet's segmentation
(class names: docs/pybullet_world.md). ``source.preset`` is not used.

World frame: the pybullet world's, z up, ground at z = 0, metres; poses camera-to-world,
RDF camera axes.
"""
from __future__ import annotations

from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.sim_camera import SimCameraSource


class PybulletSource(SimCameraSource):
    kind = "pybullet"

    def _make_world(self, cfg: SourceConfig):
        """The pybullet scene of ``source.seed``."""
        try:
            from synthetic_world.pybullet_world import PybulletWorld
        except ImportError as e:
            raise SourceError(f"pybullet: the pybullet package is not installed ({e}); pip install pybullet") from None
        try:
            world = PybulletWorld.generate(cfg.seed)
        except ValueError as e:
            raise SourceError(f"pybullet: cannot assemble the scene of seed={cfg.seed}: {e}") from None
        self.world_frame_text = "pybullet world frame, z up, ground at z = 0"
        return world
