"""ScanNet reader (SensReader export).

Layout under the scene directory: ``color/<i>.jpg``, ``depth/<i>.png`` (uint16 mm; 0 →
NaN), ``pose/<i>.txt`` (4×4 camera-to-world, OpenCV RDF camera axes),
``intrinsic/intrinsic_depth.txt`` (4×4; the top-left 3×3 is K at depth resolution),
optional labels ``label-filt/<i>.png`` or ``<scene>_2d-label-filt/label-filt/<i>.png``
(raw ScanNet ids at colour resolution, resampled nearest to depth resolution). With a
``scannetv2-labels.combined.tsv`` (``label_map`` or found next to the scene) raw ids are
mapped to NYU40 ids and ``class_names`` are the NYU40 names (0 = none).

Frames whose pose is not finite (ScanNet stores ``-inf`` poses where tracking failed) are
skipped and counted (``skipped``); the reference implementation feeds them to the map.

World frame: the ScanNet scene frame, poses as given (roughly z-up, aligned to the
reconstruction, not exactly gravity-aligned).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from common.conventions import convert_pose
from edge.sources.base import FrameSource, filter_poses, native_frame
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.imageops import read_depth_u16, read_png_unchanged, read_rgb


def read_matrix(path: Path) -> np.ndarray:
    """A whitespace-separated 4×4 matrix text file (``inf`` / ``-inf`` allowed)."""
    if not path.is_file():
        raise SourceError(f"missing file: {path}")
    try:
        m = np.array([float(v) for v in path.read_text().split()], dtype=np.float64)
    except ValueError:
        raise SourceError(f"{path}: not a list of numbers") from None
    if m.size != 16:
        raise SourceError(f"{path}: expected a 4×4 matrix (16 numbers), got {m.size}")
    return m.reshape(4, 4)


def read_nyu40_map(tsv: Path) -> tuple[dict[int, int], list[str]]:
    """Raw ScanNet id → NYU40 id, and the 41 class names (index 0 = 'none')."""
    mapping, names = {}, ["none"] + [""] * 40
    try:
        with open(tsv, newline="") as fh:
            for row in csv.DictReader(fh, delimiter="\t"):
                if not row.get("id") or not row.get("nyu40id"):
                    continue
                raw, nyu = int(row["id"]), int(row["nyu40id"])
                mapping[raw] = nyu
                if 0 < nyu <= 40 and row.get("nyu40class"):
                    names[nyu] = row["nyu40class"]
    except (OSError, ValueError, KeyError) as e:
        raise SourceError(f"scannet: cannot read label map {tsv}: {e}") from None
    return mapping, names


class ScanNetSource(FrameSource):
    kind = "scannet"
    default_fps = 30.0

    def __init__(self, cfg: SourceConfig):
        super().__init__(cfg)
        scene = self._scene_dir(Path(cfg.path))
        for sub in ("color", "depth", "pose"):
            if not (scene / sub).is_dir():
                raise SourceError(f"scannet: missing directory: {scene / sub}")
        self.scene_dir = scene
        K4 = read_matrix(scene / "intrinsic" / "intrinsic_depth.txt")
        self.native_K = K4[:3, :3].copy()
        ids = sorted(int(p.stem) for p in (scene / "pose").glob("*.txt") if p.stem.isdigit())
        if not ids:
            raise SourceError(f"scannet: no pose files in {scene / 'pose'}")
        poses = [read_matrix(scene / "pose" / f"{i}.txt") for i in ids]
        self.poses = {i: convert_pose(p, "RDF", cfg.world_axes) if np.all(np.isfinite(p)) else p
                      for i, p in zip(ids, poses, strict=True)}
        valid = [ids[k] for k in filter_poses(poses, "pose/*.txt (ScanNet -inf poses)", self)]

        self.label_dir = next((d for d in (scene / "label-filt", scene / f"{scene.name}_2d-label-filt" / "label-filt")
                               if d.is_dir()), None)
        self.label_lut: np.ndarray | None = None
        if self.label_dir is not None:
            tsv = Path(cfg.label_map) if cfg.label_map else next(
                (p for p in (scene / "scannetv2-labels.combined.tsv", scene.parent / "scannetv2-labels.combined.tsv")
                 if p.is_file()), None)
            if tsv is not None:
                if not tsv.is_file():
                    raise SourceError(f"scannet: label map not found: {tsv}")
                mapping, self.class_names = read_nyu40_map(tsv)
                lut = np.zeros(max(mapping, default=0) + 1, dtype=np.int32)
                for raw, nyu in mapping.items():
                    lut[raw] = nyu
                self.label_lut = lut
        first = read_depth_u16(scene / "depth" / f"{valid[0] if valid else ids[0]}.png", 1000.0)
        self.native_hw = first.shape
        self.name = f"scannet:{scene.name}"
        self.world_frame = "ScanNet scene frame as given (roughly z-up, not exactly gravity-aligned)"
        self._select(valid)
        self._report_skips()

    def _load(self, i: int):
        s = self.scene_dir
        rgb = read_rgb(s / "color" / f"{i}.jpg")
        depth = read_depth_u16(s / "depth" / f"{i}.png", 1000.0)
        labels = None
        if self.label_dir is not None:
            raw = read_png_unchanged(self.label_dir / f"{i}.png").astype(np.int64)
            if raw.ndim != 2:
                raise SourceError(f"scannet: label image {self.label_dir / f'{i}.png'} must be single-channel")
            if self.label_lut is not None:
                raw = np.where(raw < len(self.label_lut), self.label_lut[np.minimum(raw, len(self.label_lut) - 1)], 0)
            labels = raw.astype(np.int32)
        return native_frame(i, i / self.fps, self.poses[i], self.native_K, depth, rgb, labels)
