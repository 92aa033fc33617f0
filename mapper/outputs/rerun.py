"""Rerun output of the mapper (rerun-sdk 0.41 API: ``RecordingStream``, ``set_time``,
``save`` / ``serve_grpc``; never spawns a viewer). Module map: :mod:`mapper.state`.

:class:`RerunLogger` is the recording (moved here from ``mapper/rerun_log.py``);
:class:`RerunOutput` is what the mapper's jobs call: every ``rerun.every_n_frames``-th mapped
frame of a robot, the map after layers are published and at close, each answered query.
Logging failures are counted in the rate-limited log and never stop mapping.

Entity layout (world frame, z up, metres)::

    world                              ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/robots/<robot>/camera        Transform3D (camera-to-world)
    world/robots/<robot>/camera/image  Pinhole (RDF) + rgb (JPEG) + depth
    world/robots/<robot>/trajectory    LineStrips3D of camera positions
    world/map/voxels                   Points3D coloured by RGB
    world/map/frontiers                Points3D
    world/map/rays                     Arrows3D
    world/queries/<label>/heat         Points3D of voxels coloured by query score
    world/queries/<label>/rays         Arrows3D of the best rays
    world/queries/<label>/search_volume Points3D samples of the cones

Timeline ``frame`` = frames mapped so far.
"""
from __future__ import annotations

import collections
import logging
import re

import numpy as np

log = logging.getLogger("rayfronts.mapper.rerun")


def _heat(s: np.ndarray) -> np.ndarray:
    """Scores → RGB (blue → red), min-max normalised."""
    s = np.asarray(s, np.float32)
    if s.size == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = float(s.min()), float(s.max())
    t = (s - lo) / (hi - lo) if hi > lo else np.ones_like(s)
    return np.stack([255 * t, 64 * (1 - np.abs(2 * t - 1)), 255 * (1 - t)], -1).astype(np.uint8)


def _safe(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", label)[:48] or "query"


class RerunLogger:
    """One rerun recording for the mapper: to a file (``file``) and/or a gRPC server."""

    def __init__(self, app_id: str = "rayfronts", file: str | None = None, serve_grpc: bool = False,
                 grpc_port: int = 9876, recording_id: str | None = None):
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream(app_id, recording_id=recording_id)
        self.url = None
        if file:
            self.rec.save(file)
        if serve_grpc:
            self.url = self.rec.serve_grpc(grpc_port=grpc_port)
            log.info("rerun: serving %s (rerun --connect %s)", self.url, self.url)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._traj: dict[str, list] = {}

    def _t(self, frame_no: int) -> None:
        self.rec.set_time("frame", sequence=int(frame_no))

    def log_frame(self, frame, frame_no: int) -> None:
        """Camera pose + pinhole, RGB (JPEG), depth of one mapped frame."""
        rr = self.rr
        self._t(frame_no)
        self.rec.set_time("sensor_time", timestamp=float(frame.stamp))
        base = f"world/robots/{frame.robot}"
        pose = np.asarray(frame.pose, np.float64)
        self.rec.log(f"{base}/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        h, w = frame.depth.shape[:2]
        self.rec.log(f"{base}/camera/image", rr.Pinhole(image_from_camera=np.asarray(frame.intrinsics),
                                                        width=w, height=h, camera_xyz=rr.ViewCoordinates.RDF))
        rgb = np.asarray(frame.rgb)
        if rgb.shape[:2] != (h, w):
            import cv2

            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        self.rec.log(f"{base}/camera/image/rgb", rr.Image(rgb).compress(jpeg_quality=80))
        d = np.asarray(frame.depth, np.float32)
        dmm = np.where(np.isfinite(d), np.clip(d * 1000.0, 0, 65535), 0).astype(np.uint16)
        self.rec.log(f"{base}/camera/image/depth", rr.DepthImage(dmm, meter=1000.0))
        tr = self._traj.setdefault(frame.robot, [])
        tr.append(pose[:3, 3].astype(np.float32))
        self.rec.log(f"{base}/trajectory", rr.LineStrips3D([np.asarray(tr)]))

    def log_map(self, frame_no: int, vox_xyz, vox_rgb, frontiers, ray_o, ray_d, vox_size: float = 0.3) -> None:
        rr = self.rr
        self._t(frame_no)
        self.rec.log("world/map/voxels", rr.Points3D(vox_xyz, colors=vox_rgb, radii=vox_size / 2))
        self.rec.log("world/map/frontiers", rr.Points3D(frontiers, colors=[255, 200, 0], radii=vox_size / 2))
        self.rec.log("world/map/rays", rr.Arrows3D(origins=ray_o, vectors=np.asarray(ray_d) * 2.0,
                                                   colors=[0, 200, 255]))

    def log_query(self, res, m, fs, req, frame_no: int) -> None:
        """Voxels coloured by query heat, the best rays and search-volume samples."""
        from mapper.query_answer import embed_request, scores_for
        from mapper.service_map import voxel_arrays

        rr = self.rr
        self._t(frame_no)
        base = f"world/queries/{_safe(res.query)}"
        xyz, feats, _ = voxel_arrays(m)
        if len(xyz):
            q = embed_request(fs, req)
            s = scores_for(fs, feats, q, False, None)
            self.rec.log(f"{base}/heat", rr.Points3D(xyz, colors=_heat(s), radii=float(m.cfg.vox_size) / 2))
        if len(res.ray_origin):
            self.rec.log(f"{base}/rays", rr.Arrows3D(origins=res.ray_origin, vectors=res.ray_direction * 20.0,
                                                     colors=_heat(res.ray_score),
                                                     labels=[f"{x:.3f}" for x in res.ray_score]))
            # search volume: points sampled along the best ray cones
            pts = []
            for o, d in zip(res.ray_origin[:5], res.ray_direction[:5]):
                t = np.linspace(2.0, 100.0, 50, dtype=np.float32)
                pts.append(o + t[:, None] * d)
            self.rec.log(f"{base}/search_volume", rr.Points3D(np.concatenate(pts), colors=[255, 0, 255], radii=0.5))
        if len(res.cluster_xyz):
            self.rec.log(f"{base}/clusters", rr.Boxes3D(centers=res.cluster_xyz, half_sizes=res.cluster_extent / 2,
                                                        labels=[f"{res.query} {x:.3f}" for x in res.cluster_score]))

    def close(self) -> None:
        try:
            self.rec.flush()
        except Exception:
            pass
        try:
            self.rec.disconnect()
        except Exception as e:
            log.debug("rerun disconnect: %s", e)


class RerunOutput:
    """The mapper's rerun output over the shared state (``state``: :class:`mapper.state.MapperState`)."""

    def __init__(self, state, logger: RerunLogger):
        self.state = state
        self.logger = logger
        self._count: collections.Counter = collections.Counter()   # mapped frames per robot

    def frame_mapped(self, robot: str, frame) -> None:
        """Log every ``rerun.every_n_frames``-th mapped frame of ``robot`` (map worker thread)."""
        s = self.state
        self._count[robot] += 1
        if (self._count[robot] - 1) % max(1, s.cfg.rerun.every_n_frames) == 0:
            try:
                self.logger.log_frame(frame, s.mapped)
            except Exception as e:
                s.warn("rerun", "rerun logging failed: %s", e)

    def log_layers(self) -> None:
        """The whole map (voxels, frontiers, rays: no layer size caps); caller holds the map lock."""
        from mapper.service_map import layer_arrays

        s = self.state
        if s.map is None:
            return
        big = type(s.cfg.layers)(rate_hz=0, max_voxels=10 ** 9, max_rays=10 ** 9)
        vox, _ = layer_arrays(s.map, "voxels", big)
        fr, _ = layer_arrays(s.map, "frontiers", big)
        rays, _ = layer_arrays(s.map, "rays", big)
        self.logger.log_map(s.mapped, vox["xyz"], vox["rgb"], fr["xyz"], rays["origin"], rays["direction"],
                            vox_size=float(s.cfg.map.vox_size))

    def layers_published(self) -> None:
        s = self.state
        try:
            with s.lock:
                self.log_layers()
        except Exception as e:
            s.warn("rerun", "rerun layer logging failed: %s", e)

    def query_answered(self, res, req) -> None:
        s = self.state
        try:
            with s.lock:
                self.logger.log_query(res, s.map, s.space, req, s.mapped)
        except Exception as e:
            s.warn("rerun", "rerun query logging failed: %s", e)

    def close(self) -> None:
        """Log the final map and close the recording."""
        with self.state.lock:
            self.log_layers()
        self.logger.close()
