"""Rerun output of the mapper (rerun-sdk 0.41 API: ``RecordingStream``, ``set_time``, sinks;
never spawns a viewer). Module map: :mod:`mapper.state`. The operator's view (blueprint,
colour scale, labels, cones, the loopback-bound server) is :mod:`mapper.outputs.rerun_view`.

:class:`RerunLogger` is the recording (moved here from ``mapper/rerun_log.py``);
:class:`RerunOutput` is what the mapper's jobs call: every ``rerun.every_n_frames``-th mapped
frame of a robot, the map after layers are published and at close, each answered query.
Logging failures are counted in the rate-limited log and never stop mapping.

Entity paths: :mod:`common.rerun_paths` (robots' cameras and trajectories, the map's layers,
each query's heat / clusters / rays / search volume and legend, each search's instances and
goals).

Timeline ``frame`` = frames mapped so far.
"""
from __future__ import annotations

import collections
import logging
from typing import TYPE_CHECKING

import numpy as np

from common import rerun_paths as paths

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from common.frame import Frame
    from common.messages import QueryRequest, QueryResult
    from common.search_messages import SearchReply, SearchRequest
    from mapper.service_config import MapperConfig
    from mapper.state import MapperState
    from semantic_map.map import RayFrontsMap

log = logging.getLogger("rayfronts.mapper.rerun")


def search_boxes(rep: SearchReply) -> dict:
    """A search reply's instances as boxes: ``centers`` / ``half_sizes`` (N, 3) m (world, z
    up), ``ids`` (N,) the instances' stable ids, ``labels`` ``"<target> #<id> <confidence>"``."""
    lo = np.array([f["box_min"] for f in rep.found], np.float64).reshape(-1, 3)
    hi = np.array([f["box_max"] for f in rep.found], np.float64).reshape(-1, 3)
    return {"centers": (lo + hi) / 2, "half_sizes": np.maximum(hi - lo, 1e-3) / 2,
            "ids": np.array([int(f["id"]) for f in rep.found], np.int64),
            "labels": [f"{f.get('target', '')} #{f['id']} {float(f.get('confidence', 0.0)):.2f}" for f in rep.found]}


class RerunLogger:
    """One rerun recording for the mapper: to a file (``file``) and/or a live stream (a
    loopback-bound rerun server child, :class:`mapper.outputs.rerun_view.RerunServer`), with
    the operator blueprint (:func:`mapper.outputs.rerun_view.build_blueprint`)."""

    def __init__(self, app_id: str = "rayfronts", file: str | None = None, serve_grpc: bool = False,
                 grpc_port: int = 9876, recording_id: str | None = None, serve_web: bool = False,
                 web_port: int = 9090, bind: str = "127.0.0.1", search_rays: int = 10,
                 search_range_m: float = 200.0, memory_limit: str = "512MiB"):
        import rerun as rr

        from mapper.outputs.rerun_view import RerunServer, build_blueprint

        self.rr = rr
        self.rec = rr.RecordingStream(app_id, recording_id=recording_id)
        self.url = None
        self.web_url = None
        self.server = None
        self.search_rays = int(search_rays)
        self.search_range_m = float(search_range_m)
        self._queries: list[str] = []     # entity names of the queries seen, oldest first
        self._selected: str | None = None
        self._robots: list[str] = []
        self._eye: tuple[list, list] | None = None      # camera (position, look target)
        bp = build_blueprint(None, [], [])
        sinks: list = []
        if file:
            sinks.append(rr.FileSink(str(file)))
        if serve_grpc or serve_web:
            self.server = RerunServer(bind=bind, grpc_port=grpc_port, serve_web=serve_web, web_port=web_port,
                                      memory_limit=memory_limit)
            self.url, self.web_url = self.server.url, self.server.web_url
            sinks.append(rr.GrpcSink(self.url))
            if self.web_url:
                log.info("rerun: web viewer at %s", self.web_url)
            log.info("rerun: streaming to %s (native viewer: rerun --connect %s)", self.url, self.url)
        if sinks:
            self.rec.set_sinks(*sinks, default_blueprint=bp)
        self.rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._traj: dict[str, list] = {}

    @classmethod
    def from_config(cls, cfg: MapperConfig) -> RerunLogger:
        """From a :class:`mapper.service_config.MapperConfig` (``rerun`` and ``query`` sections)."""
        r = cfg.rerun
        return cls(r.app_id, file=r.file or None, serve_grpc=r.serve_grpc, grpc_port=r.grpc_port,
                   serve_web=getattr(r, "serve_web", False), web_port=getattr(r, "web_port", 9090),
                   bind=getattr(r, "bind", "127.0.0.1"), search_rays=cfg.query.search_rays,
                   search_range_m=cfg.query.search_range_m,
                   memory_limit=getattr(r, "server_memory_limit", "512MiB"))

    def _send_blueprint(self) -> None:
        from mapper.outputs.rerun_view import build_blueprint

        self.rec.send_blueprint(build_blueprint(self._selected, self._queries, self._robots, self._eye),
                                make_active=True, make_default=True)

    def _t(self, frame_no: int) -> None:
        self.rec.set_time("frame", sequence=int(frame_no))

    def log_frame(self, frame: Frame, frame_no: int) -> None:
        """Camera pose + pinhole, RGB (JPEG), depth of one mapped frame."""
        rr = self.rr
        self._t(frame_no)
        self.rec.set_time("sensor_time", timestamp=float(frame.stamp))
        pose = np.asarray(frame.pose, np.float64)
        cam = paths.ROBOTS(frame.robot, paths.CAMERA)
        self.rec.log(cam, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        h, w = frame.depth.shape[:2]
        image = paths.ROBOTS(frame.robot, paths.IMAGE)
        self.rec.log(image, rr.Pinhole(image_from_camera=np.asarray(frame.intrinsics), width=w, height=h,
                                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=1.0))
        rgb = np.asarray(frame.rgb)
        if rgb.shape[:2] != (h, w):
            import cv2

            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        self.rec.log(f"{image}/rgb", rr.Image(rgb).compress(jpeg_quality=80))
        d = np.asarray(frame.depth, np.float32)
        dmm = np.where(np.isfinite(d), np.clip(d * 1000.0, 0, 65535), 0).astype(np.uint16)
        self.rec.log(f"{image}/depth", rr.DepthImage(dmm, meter=1000.0))
        tr = self._traj.setdefault(frame.robot, [])
        tr.append(pose[:3, 3].astype(np.float32))
        self.rec.log(paths.ROBOTS(frame.robot, paths.TRAJECTORY),
                     rr.LineStrips3D([np.asarray(tr)], colors=[255, 255, 255]))
        if frame.robot not in self._robots:
            self._robots.append(frame.robot)
            self._send_blueprint()

    def log_map(self, frame_no: int, vox_xyz: np.ndarray, vox_rgb: np.ndarray, frontiers: np.ndarray,
                ray_o: np.ndarray, ray_d: np.ndarray, vox_size: float = 0.3) -> None:
        rr = self.rr
        self._t(frame_no)
        self.rec.log(paths.MAP_VOXELS, rr.Points3D(vox_xyz, colors=vox_rgb, radii=vox_size / 2))
        self.rec.log(paths.MAP_FRONTIERS, rr.Points3D(frontiers, colors=[0, 220, 160], radii=vox_size / 2))
        self.rec.log(paths.MAP_RAYS, rr.Arrows3D(origins=ray_o, vectors=np.asarray(ray_d) * 2.0, colors=[0, 200, 255]))
        if self._eye is None and len(vox_xyz):
            from mapper.outputs.rerun_view import eye_for

            self._eye = eye_for(vox_xyz)
            self._send_blueprint()

    def log_query(self, res: QueryResult, m: RayFrontsMap, fs: FeatureSpace, req: QueryRequest,
                  frame_no: int) -> None:
        """The query's own entity tree: voxel heat (with its colour scale and range), labelled
        clusters, the best rays and the outlines of the search-volume cones; a new query text
        becomes the selected one."""
        from mapper.outputs.rerun_view import colour_scale_image, cone_outlines, heat_colors, thin_labels
        from mapper.query_answer import embed_request, scores_for
        from mapper.service_map import voxel_arrays

        rr = self.rr
        self._t(frame_no)
        name = paths.entity_name(res.query)
        base = paths.QUERIES(name)
        vox = float(m.cfg.vox_size)
        xyz, feats, _ = voxel_arrays(m)
        lo = hi = float("nan")
        if len(xyz):
            q = embed_request(fs, req)
            s = scores_for(fs, feats, q, False, None)
            s = s.detach().cpu().numpy() if hasattr(s, "detach") else np.asarray(s)
            cols, lo, hi = heat_colors(s)
            self.rec.log(f"{base}/heat", rr.Points3D(xyz, colors=cols, radii=0.55 * vox))
            self.rec.log(f"{paths.SCALE(name)}/colour_scale", rr.Image(colour_scale_image(lo, hi)))
            if self._eye is None:
                from mapper.outputs.rerun_view import eye_for

                self._eye = eye_for(xyz)
        if len(res.cluster_xyz):
            keep = set(thin_labels(res.cluster_xyz, res.cluster_score, min_sep=max(3.0, 6 * vox)))
            labels = [f"{res.query} #{i + 1} {sc:.3f}" if i in keep else ""
                      for i, sc in enumerate(res.cluster_score)]
            self.rec.log(f"{base}/clusters", rr.Boxes3D(centers=res.cluster_xyz,
                                                        half_sizes=np.maximum(np.asarray(res.cluster_extent) / 2,
                                                                              vox / 2),
                                                        colors=[255, 255, 255], labels=labels,
                                                        show_labels=True))
        else:
            self.rec.log(f"{base}/clusters", rr.Clear(recursive=False))
        n = min(self.search_rays, len(res.ray_origin))
        if len(res.ray_origin):
            cols, _, _ = heat_colors(res.ray_score)
            labels = [f"best ray {res.ray_score[0]:.3f}"] + [""] * (len(res.ray_origin) - 1)
            self.rec.log(f"{base}/rays", rr.Arrows3D(origins=res.ray_origin,
                                                     vectors=np.asarray(res.ray_direction) * 20.0,
                                                     colors=cols, labels=labels, show_labels=True))
            strips = cone_outlines(res.ray_origin[:n], res.ray_direction[:n], float(m.cone_half_angle()),
                                   self.search_range_m)
            self.rec.log(f"{base}/search_volume", rr.LineStrips3D(strips, colors=[255, 120, 255, 110],
                                                                  radii=rr.Radius.ui_points(1.0)))
        else:
            self.rec.log(f"{base}/rays", rr.Clear(recursive=False))
            self.rec.log(f"{base}/search_volume", rr.Clear(recursive=False))
        rng = f"{lo:.3f} (blue) to {hi:.3f} (yellow)" if np.isfinite(lo) else "no voxels yet"
        self.rec.log(f"{paths.SCALE(name)}/legend", rr.TextDocument(
            f"### {res.query}\n\n"
            f"- heat: similarity of every voxel, {rng}\n"
            f"- clusters: {len(res.cluster_xyz)} (white boxes; the best ones, apart, labelled)\n"
            f"- rays beyond range: {len(res.ray_origin)}; search volume of the best {n} cones: "
            f"{res.search_volume_m3:,.0f} m³ (cut at {self.search_range_m:g} m)\n"
            f"- {res.frames_mapped} frames mapped\n\n"
            f"Other queries: `{paths.QUERIES.root}/<query>` in the blueprint panel (eye icon).",
            media_type=rr.MediaType.MARKDOWN))
        if name not in self._queries:
            self._queries.append(name)
        if self._selected != name:
            self._selected = name
            self._send_blueprint()

    def log_search(self, targets: list[str], rep: SearchReply, frame_no: int) -> None:
        """A search answer (:class:`common.search_messages.SearchReply`): its instances as
        labelled boxes whose class ids are the instances' stable ids, and its look-next goals."""
        rr = self.rr
        self._t(frame_no)
        base = paths.SEARCHES(paths.entity_name(",".join(targets)))
        b = search_boxes(rep)
        if len(b["centers"]):
            self.rec.log(f"{base}/instances", rr.Boxes3D(centers=b["centers"], half_sizes=b["half_sizes"],
                                                         class_ids=b["ids"], labels=b["labels"], show_labels=True))
        else:
            self.rec.log(f"{base}/instances", rr.Clear(recursive=False))
        goals = np.array([g["position"] for g in rep.look_next], np.float64).reshape(-1, 3)
        if len(goals):
            self.rec.log(f"{base}/goals", rr.Points3D(goals, colors=[80, 220, 80], radii=0.3,
                                                      labels=[f"goal {g['score']:.2f}" for g in rep.look_next]))
        else:
            self.rec.log(f"{base}/goals", rr.Clear(recursive=False))

    def close(self) -> None:
        try:
            self.rec.flush()
        except Exception:
            pass
        try:
            self.rec.disconnect()
        except Exception as e:
            log.debug("rerun disconnect: %s", e)
        if self.server is not None:
            self.server.close()
            self.server = None


class RerunOutput:
    """The mapper's rerun output over the shared state (``state``: :class:`mapper.state.MapperState`)."""

    def __init__(self, state: MapperState, logger: RerunLogger) -> None:
        self.state = state
        self.logger = logger
        self._count: collections.Counter = collections.Counter()   # mapped frames per robot

    def frame_mapped(self, robot: str, frame: Frame) -> None:
        """Log every ``rerun.every_n_frames``-th mapped frame of ``robot`` (map worker thread)."""
        state = self.state
        self._count[robot] += 1
        if (self._count[robot] - 1) % max(1, state.cfg.rerun.every_n_frames) == 0:
            try:
                self.logger.log_frame(frame, state.mapped)
            except Exception as e:
                state.warn("rerun", "rerun logging failed: %s", e)

    def log_layers(self) -> None:
        """The whole map (voxels, frontiers, rays: no layer size caps); caller holds the map lock."""
        from mapper.service_map import layer_arrays

        state = self.state
        if state.map is None:
            return
        big = type(state.cfg.layers)(rate_hz=0, max_voxels=10 ** 9, max_rays=10 ** 9)
        vox, _ = layer_arrays(state.map, "voxels", big)
        fr, _ = layer_arrays(state.map, "frontiers", big)
        rays, _ = layer_arrays(state.map, "rays", big)
        self.logger.log_map(state.mapped, vox["xyz"], vox["rgb"], fr["xyz"], rays["origin"], rays["direction"],
                            vox_size=float(state.cfg.map.vox_size))

    def layers_published(self) -> None:
        state = self.state
        try:
            with state.lock:
                self.log_layers()
        except Exception as e:
            state.warn("rerun", "rerun layer logging failed: %s", e)

    def query_answered(self, res: QueryResult, req: QueryRequest) -> None:
        state = self.state
        try:
            with state.lock:
                assert state.map is not None and state.space is not None     # a query answered: both exist
                self.logger.log_query(res, state.map, state.space, req, state.mapped)
        except Exception as e:
            state.warn("rerun", "rerun query logging failed: %s", e)

    def search_answered(self, rep: SearchReply, req: SearchRequest) -> None:
        """Log a search answer (no map access: the reply carries everything)."""
        try:
            self.logger.log_search(list(req.targets), rep, self.state.mapped)
        except Exception as e:
            self.state.warn("rerun", "rerun search logging failed: %s", e)

    def close(self) -> None:
        """Log the final map and close the recording."""
        with self.state.lock:
            self.log_layers()
        self.logger.close()
