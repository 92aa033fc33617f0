"""Frame sources for the edge: each yields :class:`common.frame.Frame` objects obeying
docs/conventions.md (pose 4×4 camera-to-world with RDF camera axes, z-up world where the source
allows it; planar depth in metres, NaN = no measurement, +inf = beyond range; intrinsics
at depth resolution; sizes (H, W)).

    from edge.sources import SourceConfig, open_source
    src = open_source(SourceConfig(kind="tartanair", path="/data/tartanair", scene="AbandonedCable",
                                   sequence="P0000", resolution="320x320", depth_limit=20.0))
    for frame in src: ...

World frame per kind (``src.world_frame`` says it in one sentence):

* ``synthetic`` — the synthetic world's frame, z up (ENU), ground at z = 0.
* ``replica`` — Replica's native mesh frame as in NICE-SLAM ``traj.txt``, kept as given
  (roughly z-up, not exactly gravity-aligned).
* ``scannet`` — the ScanNet scene frame as given (roughly z-up); −inf poses skipped.
* ``tartanair`` — NED re-expressed as ENU (x east, y north, z up), gravity-aligned.
* ``recording`` — whatever frame the recording was written in (its ``info``).
* ``rosbag`` — the bag's world (``world_frame`` tf frame or the pose topic's frame),
  axes ``world_axes`` (REP-103 ENU by default) re-expressed as ENU.
* ``sim_camera`` / ``pybullet`` — the synthetic / pybullet world's frame (z up), rendered at
  poses a simulator sends over Zenoh.
* ``ros2`` — live topics over Zenoh (rmw_zenoh or zenoh-bridge-ros2dds keys): the same
  world as ``rosbag`` would give for the same messages.
"""
from __future__ import annotations

from typing import Any

from edge.sources.base import FrameSource, select_indices
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError

__all__ = ["FrameSource", "SourceConfig", "SourceError", "open_source", "select_indices", "KINDS"]

KINDS = {
    "synthetic": "edge.sources.synthetic:SyntheticSource",
    "replica": "edge.sources.replica:ReplicaSource",
    "scannet": "edge.sources.scannet:ScanNetSource",
    "tartanair": "edge.sources.tartanair:TartanAirSource",
    "recording": "edge.sources.recording:RecordingSource",
    "rosbag": "edge.sources.rosbag:RosbagSource",
    "ros2": "edge.sources.ros2:Ros2Source",
    "sim_camera": "edge.sources.sim_camera:SimCameraSource",
    "pybullet": "edge.sources.pybullet_sim:PybulletSource",
}


def open_source(cfg: SourceConfig, **kwargs: Any) -> FrameSource:
    """Open the frame source ``cfg.kind`` (modules are imported lazily, so the robot needs
    only the dependencies of the source it uses). Raises :class:`SourceError` with the
    missing path / topic / bad setting named."""
    import importlib

    if cfg.kind not in KINDS:
        raise SourceError(f"unknown source kind {cfg.kind!r}; choose one of {', '.join(KINDS)}")
    mod, cls = KINDS[cfg.kind].split(":")
    return getattr(importlib.import_module(mod), cls)(cfg, **kwargs)
