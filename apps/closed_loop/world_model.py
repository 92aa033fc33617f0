"""What a policy sees of the map each step (:class:`Observation`), from the mapper's own code
run in this process (:class:`LocalMapper`) or from a real mapper over Zenoh
(:mod:`apps.closed_loop.distributed`).

The local mapper integrates decoded frames into a :class:`semantic_map.map.RayFrontsMap` and
answers searches with :func:`mapper.search_answer.answer_search` on a
:class:`semantic_map.query_copy.QueryCopy` — the functions the mapper service calls —
so in-process and distributed episodes see the same answers for the same frames. World
frame, metres, z up.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from common.frame import Frame


@dataclass
class Observation:
    """One step's view of the map: search answer parts (dicts as on the wire: ``found``,
    ``look_next`` and, for the ray policies, ``estimates`` from ``beyond``), the 2D
    costmap of the body band (``states`` int8 FREE/OCCUPIED/UNKNOWN indexed [x, y],
    ``origin`` (2,) m of cell 0's min corner, ``cell`` m) and, for Semantic Poses, the
    scored camera poses ``(position (3,), unit heading (3,), probability, margin z-score)``
    (:meth:`LocalMapper._scored_poses`)."""

    found: list[dict]
    look_next: list[dict]
    states: np.ndarray
    origin: np.ndarray
    cell: float
    poses: list[tuple[np.ndarray, np.ndarray, float, float]] = field(default_factory=list)
    search_ms: float = 0.0
    estimates: list[dict] = field(default_factory=list)   # the search's beyond.estimates (semantic only)


#: per-frame point budgets of the closed loop's maps (the online preset maps every pixel;
#: a robot's step integrates several views, so points and free-space rays are subsampled)
POINT_BUDGETS = dict(max_pts_per_frame=12000, max_empty_pts_per_frame=8000)


def mapper_config(method: str, depth_limit_m: float, vox_m: float, width_px: int, preset: str = "online",
                  background: list[str] | None = None, ray_evidence: str = "distinct", distinct_phrases: int = 0,
                  angle_bin_deg: float | None = None):
    """The mapper config of one policy's map: ``preset`` with ``method``'s overrides
    (semantic_map.config.METHODS), voxel size, depth limit and :data:`POINT_BUDGETS`; ray
    erosion scaled to the image width as the search-volume benchmark scales it;
    ``background``: the search's background phrases (None: the mapper's default);
    ``ray_evidence``, ``distinct_phrases``: ``search.ray_evidence``, ``search.distinct_phrases``;
    ``angle_bin_deg``: the map's ``angle_bin_size`` (None: the preset's; a baseline with one
    bin per frontier keeps its 360)."""
    from mapper.service_config import load_mapper_config
    from semantic_map.config import map_config

    cfg = load_mapper_config(None, [f"preset={preset}", "search.warm_up=false"])
    erosion = 1   # a far landmark is a few pixels wide at 224 px: erode the beyond-range mask by 1 px only
    mc = map_config(preset, dict(POINT_BUDGETS, vox_size=vox_m, depth_limit=depth_limit_m, ray_erosion=erosion),
                    method)
    if angle_bin_deg is not None and mc.angle_bin_size < 360:
        mc = dataclasses.replace(mc, angle_bin_size=float(angle_bin_deg))
    if background is not None:
        cfg = dataclasses.replace(cfg, search=dataclasses.replace(cfg.search, background=list(background)))
    cfg = dataclasses.replace(cfg, search=dataclasses.replace(cfg.search, ray_evidence=ray_evidence,
                                                              distinct_phrases=int(distinct_phrases)).validate())
    return dataclasses.replace(cfg, map=mc.validate())


class LocalMapper:
    """The mapper's map and search answering in this process (no Zenoh, no threads)."""

    def __init__(self, space, cfg, band_m: tuple[float, float], window_m: float = 30.0,
                 score_poses: bool = False):
        from mapper.search_answer import TrackerStore
        from mapper.service_map import create_map
        from semantic_map.query_copy import QueryCopy

        self.space, self.cfg = space, cfg
        self.map = create_map(cfg, space)
        self.snap = QueryCopy()
        self.trackers = TrackerStore(cfg.search.max_trackers)
        self.band, self.window = band_m, float(window_m)
        self.frames = 0
        self.score_poses = score_poses
        self._poses: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def integrate(self, frames: list[Frame]) -> None:
        """Fuse one step's decoded frames and flush (the next search sees all of them)."""
        from mapper.service_map import integrate

        for f in frames:
            integrate(self.map, f, self.cfg.device)
            if self.score_poses and f.global_feature is not None:
                self._poses.append((f.pose[:3, 3].copy(), f.pose[:3, 2].copy(),
                                    np.asarray(f.global_feature, np.float32)))
            self.frames += 1
        self.map.flush()

    def observe(self, targets: list[str], at: np.ndarray, max_goals: int = 96, threshold: float = 0.5,
                semantic: bool = True, z_band: tuple[float, float] | None = None) -> Observation:
        """Search for ``targets`` from camera centre ``at`` (m) and read the costmap around it.
        ``semantic=False``: look-next goals ranked without ray scores (pure geometry)."""
        import time

        from common.search_messages import SearchRequest
        from mapper.search_answer import answer_search
        from planning.occupancy_queries import costmap_slice

        t = time.perf_counter()
        self.snap.reserve(self.map)
        self.snap.sync(self.map, self.frames, self.frames)
        req = SearchRequest(targets=list(targets), from_xyz=[float(v) for v in at], threshold=threshold,
                            max_goals=max_goals, max_instances=20,
                            z_band=None if z_band is None else [float(v) for v in z_band]).validate()
        rep = answer_search(self.snap, self.space, req, self._search_cfg(semantic), self.trackers,
                            lambda fn: fn(self.map), map_version=self.frames)
        ms = (time.perf_counter() - t) * 1e3
        vox = float(self.map.cfg.vox_size)
        lo, hi = np.asarray(at[:2]) - self.window, np.asarray(at[:2]) + self.window
        states, origin, cell = costmap_slice(self.map.occupancy_view(), vox, lo, hi, self.band)
        poses = self._scored_poses(targets) if self.score_poses else []
        goals = rep.look_next
        if not semantic:
            goals = [dict(g, score=0.0, target=None) for g in goals]
        return Observation(rep.found, goals, states, np.asarray(origin, np.float64), float(cell), poses, ms,
                           list(rep.beyond.get("estimates", [])) if semantic else [])

    def _search_cfg(self, semantic: bool):
        if semantic:
            return self.cfg
        # geometry only: look-next candidates by distance (no ray may attach to a frontier)
        return dataclasses.replace(self.cfg, search=dataclasses.replace(self.cfg.search, ray_radius_m=1e-9))

    def _scored_poses(self, targets: list[str]) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
        """Each mapped view's image-level feature scored like a search: ``(position, heading,
        probability, z)`` with the best target's probability (softmax over targets +
        background at the search temperature) and ``z``, the modified z-score of the pose's
        target margin (best target cosine minus best background cosine) among all poses so
        far, as the rays' ``ray_z`` (:func:`planning.look_next.ray_outlier_z`: 0 with
        fewer than 10 poses)."""
        from common.search_messages import SearchRequest
        from mapper.search_answer import embed_phrases
        from planning.look_next import ray_outlier_z

        if not self._poses:
            return []
        scfg = self.cfg.search
        bg = [b for b in scfg.background if b not in targets]
        req = SearchRequest(targets=list(targets)).validate()
        q = embed_phrases(self.space, req, bg, self.cfg.device, self.cfg.text_model_dir, "auto")
        feats = torch.as_tensor(np.stack([p[2] for p in self._poses]))
        sim = self.space.similarity(feats, q)           # (T + B, N)
        p = torch.softmax(sim * scfg.temperature, dim=0)[:len(targets)].max(0).values.numpy()
        t = len(targets)
        margin = (sim[:t].max(0).values - (sim[t:].max(0).values if len(bg) else 0.0)).double().numpy()
        z = ray_outlier_z(margin)[0]
        return [(o, d, float(s), float(zz)) for (o, d, _), s, zz in zip(self._poses, p, z, strict=True)]
