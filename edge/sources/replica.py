"""NICE-SLAM Replica reader.

Layout: ``<root>/cam_params.json`` (``{"camera": {w, h, fx, fy, cx, cy, scale}}``),
``<root>/<scene>/traj.txt`` (one camera-to-world 4×4 per line, 16 numbers, OpenCV RDF
camera axes), ``<root>/<scene>/results/frameNNNNNN.jpg`` and ``depthNNNNNN.png`` (uint16,
metres = value / scale, scale 6553.5; 0 → NaN). ``path`` may also be the scene directory
itself (``cam_params.json`` is then looked up there and in its parent).

World frame: Replica's native mesh frame, poses kept exactly as given (re-expressed only
if ``world_axes`` is not ENU). NICE-SLAM's Replica scenes are not gravity-aligned in
general: their world z is roughly, not exactly, up, so ray angle bins are only
approximately horizon-aligned on this source.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common.conventions import convert_pose
from edge.sources.base import DirectorySource, filter_poses, native_frame, number_rows
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.imageops import read_depth_u16, read_rgb


def read_traj(path: Path) -> np.ndarray:
    """(N, 4, 4) poses from a NICE-SLAM ``traj.txt`` (16 numbers per line)."""
    if not path.is_file():
        raise SourceError(f"missing trajectory file: {path}")
    rows = [np.array(vals).reshape(4, 4) for vals in number_rows(path, 16, "(a row-major 4×4)")]
    return np.array(rows).reshape(-1, 4, 4)


class ReplicaSource(DirectorySource):
    kind = "replica"
    default_fps = 30.0

    def __init__(self, cfg: SourceConfig):
        super().__init__(cfg)
        scene = self._scene_dir(self.root)
        params = next((p for p in (self.root / "cam_params.json", scene / "cam_params.json",
                                    scene.parent / "cam_params.json") if p.is_file()), None)
        if params is None:
            raise SourceError(f"replica: missing file: {self.root / 'cam_params.json'}")
        try:
            cam = json.loads(params.read_text())["camera"]
            w, h = int(cam["w"]), int(cam["h"])
            self.native_K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]],
                                     dtype=np.float64)
            self.depth_scale = float(cam.get("scale", 6553.5))
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
            raise SourceError(f"replica: {params} lacks camera w/h/fx/fy/cx/cy ({e})") from None
        self.native_hw = (h, w)
        self.scene_dir = scene
        self.results = scene / "results"
        if not self.results.is_dir():
            raise SourceError(f"replica: missing directory: {self.results}")
        poses = read_traj(scene / "traj.txt")
        self.poses = np.array([convert_pose(p, "RDF", cfg.world_axes) for p in poses]).reshape(-1, 4, 4)
        self.name = f"replica:{scene.name}"
        self.world_frame = ("Replica native mesh frame as given by NICE-SLAM traj.txt "
                            "(roughly but not exactly z-up; not gravity-aligned in general)")
        self._select(filter_poses(self.poses, "traj.txt", self))
        self._report_skips()

    def _load(self, i: int):
        rgb = read_rgb(self.results / f"frame{i:06d}.jpg")
        depth = read_depth_u16(self.results / f"depth{i:06d}.png", self.depth_scale)
        if depth.shape != self.native_hw:
            raise SourceError(f"replica: {self.results / f'depth{i:06d}.png'} is {depth.shape}, "
                              f"cam_params.json says {self.native_hw}")
        return native_frame(i, i / self.fps, self.poses[i], self.native_K, depth, rgb)
