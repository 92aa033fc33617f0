"""TartanAir v2 / TartanGround reader.

Layout: ``<root>/<scene>/<difficulty>/<sequence>/`` (e.g. ``Data_ground/P0000``) holding
``image_<cam>/NNNNNN_<cam>.png``, ``depth_<cam>/NNNNNN_<cam>_depth.png`` (float32 metres
packed little-endian into the 4 bytes of an RGBA PNG), optional ``seg_<cam>/NNNNNN_<cam>_seg.png``
(uint8 ids) and ``pose_<cam>.txt`` (``tx ty tz qx qy qz qw`` per line: camera pose in a
NED world with an FRD body). ``<cam>`` defaults to ``lcam_front``. Intrinsics: fx = fy =
320, cx = cy = 320 at 640×640 (90° FoV). With empty ``scene``/``sequence`` the path is taken
as the trajectory directory itself.

Depth: values above ``depth_cutoff`` (default 100 m as in the reference; its search-volume
benchmark uses 50 m; TartanAir's sky is ~1e4 m) become +inf, 0 → NaN.

Poses: converted once with :func:`common.conventions.convert_pose` (FRD body → RDF, NED
world → ENU), so the world is z-up: x = East, y = North, z = Up, with the origin of the
NED frame (not the reference's T·P·T⁻¹, which leaves gravity along +y).

Labels: raw segmentation ids; ``class_names`` come from ``seg_label_map.json``
(``{"name_map": {name: id}}``) found in the scene or root directory, if any.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common.conventions import convert_pose
from edge.sources.base import DirectorySource, filter_poses, native_frame, number_rows
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.imageops import decode_rgba_float32, read_png_unchanged, read_rgb
from edge.sources.transforms import pose_from_tq

TARTANAIR_HW = (640, 640)
TARTANAIR_K = np.array([[320.0, 0.0, 320.0], [0.0, 320.0, 320.0], [0.0, 0.0, 1.0]])


def read_tartanair_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses in NED/FRD from ``tx ty tz qx qy qz qw`` lines."""
    if not path.is_file():
        raise SourceError(f"tartanair: missing pose file: {path}")
    out = []
    for v in number_rows(path, 7, "'tx ty tz qx qy qz qw'"):
        if not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9:
            out.append(np.full((4, 4), np.nan))
        else:
            out.append(pose_from_tq(v[:3], v[3:]))
    return np.array(out).reshape(-1, 4, 4)


def read_tartanair_depth(path: Path) -> np.ndarray:
    """Float32 depth (metres) from a TartanAir RGBA-packed depth PNG."""
    img = read_png_unchanged(path, dtypes=(np.uint8,))
    if img.ndim != 3 or img.shape[2] != 4:
        raise SourceError(f"tartanair: {path} is not a 4-channel (RGBA-packed float32) depth PNG, shape {img.shape}")
    return decode_rgba_float32(img)


class TartanAirSource(DirectorySource):
    kind = "tartanair"
    default_fps = 10.0

    def __init__(self, cfg: SourceConfig):
        super().__init__(cfg)
        if cfg.scene:
            traj = self.root / cfg.scene / cfg.difficulty
            traj = traj / cfg.sequence if cfg.sequence else traj
        else:
            traj = self.root / cfg.sequence if cfg.sequence else self.root
        if not traj.is_dir():
            raise SourceError(f"tartanair: trajectory directory not found: {traj}")
        if not cfg.depth_cutoff > 0:
            raise SourceError(f"tartanair: depth_cutoff must be > 0, got {cfg.depth_cutoff}")
        cam = cfg.camera
        self.traj_dir = traj
        self.img_dir, self.depth_dir, self.seg_dir = (traj / f"{k}_{cam}" for k in ("image", "depth", "seg"))
        for d in (self.img_dir, self.depth_dir):
            if not d.is_dir():
                raise SourceError(f"tartanair: missing directory: {d}")
        raw = read_tartanair_poses(traj / f"pose_{cam}.txt")
        self.poses = np.array([convert_pose(p, body="FRD", world="NED") if np.all(np.isfinite(p)) else p
                               for p in raw]).reshape(-1, 4, 4)
        self.native_hw, self.native_K = TARTANAIR_HW, TARTANAIR_K.copy()
        self.has_seg = self.seg_dir.is_dir()
        if self.has_seg:
            for d in (traj, traj.parent, traj.parent.parent, self.root):
                f = d / "seg_label_map.json"
                if f.is_file():
                    self.class_names = self._class_names(f)
                    break
        self.name = f"tartanair:{'/'.join(traj.parts[-3:])}"
        self.world_frame = "TartanAir NED frame re-expressed as ENU (x east, y north, z up; gravity-aligned)"
        self._select(filter_poses(self.poses, f"pose_{cam}.txt", self))
        self._report_skips()

    @staticmethod
    def _class_names(path: Path) -> list[str] | None:
        try:
            name_map = json.loads(path.read_text())["name_map"]
            n = max(int(v) for v in name_map.values()) + 1
            names = [""] * n
            for k, v in name_map.items():
                names[int(v)] = str(k)
            return names
        except (KeyError, ValueError, TypeError, json.JSONDecodeError):
            return None

    def _load(self, i: int):
        cam = self.cfg.camera
        rgb = read_rgb(self.img_dir / f"{i:06d}_{cam}.png")
        dpath = self.depth_dir / f"{i:06d}_{cam}_depth.png"
        depth = read_tartanair_depth(dpath)
        with np.errstate(invalid="ignore"):
            depth[np.isfinite(depth) & (depth > self.cfg.depth_cutoff)] = np.inf
        K = self.native_K
        if depth.shape != self.native_hw:  # other TartanAir cameras keep the 90° FoV
            K = np.array([[depth.shape[1] / 2, 0, depth.shape[1] / 2], [0, depth.shape[0] / 2, depth.shape[0] / 2],
                          [0, 0, 1.0]])
        labels = None
        if self.has_seg:
            seg = read_png_unchanged(self.seg_dir / f"{i:06d}_{cam}_seg.png")
            labels = (seg if seg.ndim == 2 else seg[..., 0]).astype(np.int32)
        return native_frame(i, i / self.fps, self.poses[i], K, depth, rgb, labels)
