"""The frame contract: what every source yields, the edge sends and the mapper maps."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Frame:
    """One posed RGB-D frame with encoder features (docs/conventions.md, docs/messages.md#frame).

    Attributes:
        robot: robot id (``[A-Za-z0-9_-]+``).
        seq: per-robot sequence number (int ≥ 0).
        stamp: sensor timestamp, seconds (float, Unix time or dataset time).
        pose: (4, 4) float64 camera-to-world, RDF camera axes, z-up world.
        intrinsics: (3, 3) float64 at the depth resolution.
        depth: (H, W) float32 planar depth in metres; NaN = no measurement, +inf = beyond range.
        rgb: (H', W', 3) uint8, RGB order (may differ in size from depth).
        features: (C, h, w) float16 encoder features (PCA-compressed on the wire) or None.
        feature_space: feature-space id (encoder + version + PCA basis hash); "" if none.
        labels: optional (H, W) int32 ground-truth class ids at depth resolution (0 = none/sky).
        confidence: optional (H, W) float32 in [0, 1] (1 = most confident).
        global_feature: optional (C,) float16 image-level feature (image queries, Semantic Poses).
        meta: free-form small dict (source name, frame index, ...).
    """

    robot: str
    seq: int
    stamp: float
    pose: np.ndarray
    intrinsics: np.ndarray
    depth: np.ndarray
    rgb: np.ndarray
    features: np.ndarray | None = None
    feature_space: str = ""
    labels: np.ndarray | None = None
    confidence: np.ndarray | None = None
    global_feature: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def depth_hw(self) -> tuple[int, int]:
        return tuple(self.depth.shape[:2])  # type: ignore[return-value]
