"""What the robot's edge sends each step: views rendered by the synthetic world at the robot's
pose, encoded, PCA-compressed and put through the wire format (encode → decode), exactly the
frames a mapper receives from ``rayfronts edge``.

Views: ``views`` yaw directions evenly spaced (the first along +x), tilted down by
``tilt_deg`` (ground) or ``drone_tilt_deg`` (drone): with a 90° field of view a ground camera
tilted 25° sees the ground from 0.55 m around the robot (it must know the space around its
body is free) up to 20° above the horizon (far towers stay in view); a drone's cameras are
tilted 10°, so they see the voxel layer just above its body from ~0.7 m out (its costmap must
know the space at its own height) and the ground from ~4 m out at its 5.5 m cruise height.
Camera: square images of ``resolution`` pixels.

The defaults of this dataclass are the exact building blocks (the unit tests' setting);
``rayfronts eval search`` runs with ``sensor=realistic``, ``encoder=sim`` and
``pca_fit=first_views`` unless told otherwise (:class:`apps.closed_loop.evaluate.SearchEvalConfig`).

Depth (``sensor``): ``realistic`` is a depth camera like a real one
(:class:`synthetic_world.depth_sensor.DepthSensorModel`: no return beyond its range for every
surface, far building and sky alike, noise σ = k·z², dropouts at grazing angles and depth
edges; draws seeded by ``sensor_seed``); ``exact`` is the world's exact depth with
``sky_no_return``: surfaces at any distance return their depth (the map's depth limit turns
those beyond it into rays), the sky returns nothing (NaN, ignored by the map).

Semantics (``encoder``): ``sim`` the simulated ViT-like encoder (class confusions,
blur, noise: :mod:`encoders.sim`), ``label`` the exact labels. PCA basis
(``pca_fit``): ``first_views`` fitted on the robot's own first views — the
encoder's output for views rendered all around the first mission's start —,
``vocabulary`` on the text embeddings of a generic vocabulary less the world's class names
(:mod:`apps.closed_loop.generic_vocabulary`: a basis fitted offline, no view of this world),
``classes`` on views around the world centre plus one cell of each of the world's
classes.

World frame z up, metres; poses camera-to-world, RDF camera axes.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal, cast

import numpy as np
import torch

from apps.closed_loop.robot import Platform, camera_pose
from common.frame import Frame
from synthetic_world import World
from synthetic_world.depth_sensor import DepthSensorModel


@dataclass(frozen=True)
class SensorConfig:
    """Camera and edge settings of the closed loop (``resolution`` in pixels, angles in degrees)."""

    resolution: int = 224               #: square image side, pixels
    views: int = 4                      #: views per step, evenly spaced in yaw
    tilt_deg: float = 25.0              #: ground robot's camera pitch below the horizon
    drone_tilt_deg: float = 10.0        #: the drone's camera pitch
    encoder: str = "label"              #: ``label`` (exact) or ``sim`` (ViT-like, encoders.sim)
    label_stride: int = 8               #: label encoder's output stride, pixels per feature cell
    pca_dim: int = 32                   #: PCA channels on the wire
    feature_codec: str = "q16z"         #: wire codec of the features (common.wire.frame)
    sky_no_return: bool = True          #: exact sensor: sky pixels give no return (NaN)
    sensor: str = "exact"               #: ``exact`` or ``realistic`` (``depth_model``)
    depth_model: DepthSensorModel = field(default_factory=DepthSensorModel)
    sensor_seed: int = 0                #: seed of the realistic sensor's noise and dropouts
    pca_fit: str = "classes"            #: PCA basis: ``classes``, ``first_views`` or ``vocabulary``

    def validate(self) -> "SensorConfig":
        """Raise ``ValueError`` naming a bad choice."""
        if self.sensor not in SENSORS:
            raise ValueError(f"sensor must be one of {', '.join(SENSORS)}, not {self.sensor!r}")
        if self.encoder not in ("sim", "label"):
            raise ValueError(f"encoder must be 'sim' or 'label', not {self.encoder!r}")
        if self.pca_fit not in PCA_FITS:
            raise ValueError(f"pca_fit must be one of {', '.join(PCA_FITS)}, not {self.pca_fit!r}")
        self.depth_model.validate()
        return self


#: the depth sensors of the loop (module docstring)
SENSORS = ("realistic", "exact")
#: where the PCA basis comes from (module docstring)
PCA_FITS = ("first_views", "vocabulary", "classes")


class EdgeChain:
    """The edge's per-frame work in process: encoder → PCA → wire encode → decode.

    The PCA basis is fitted once per world, so every policy and every episode of a world see
    the same feature space. ``pca_fit="first_views"``: on the encoder's output for
    ``fit_views`` views all around ``fit_at`` (the first mission's start: the robot's own
    first views; yaws evenly spaced, tilted down 0 and 0.3 rad in turn) — nothing of the
    world's class list. ``"classes"``: views around the
    world centre plus one cell of each of the world's classes (:meth:`class_cells`), as an
    operator who knew every class of the site would fit it. ``"vocabulary"``: the encoder's
    text embeddings of :func:`~apps.closed_loop.generic_vocabulary.vocabulary_without` the
    world's classes (no view rendered)."""

    def __init__(self, world: World, cfg: SensorConfig, fit_views: int = 8, fit_at: np.ndarray | None = None):
        from common.feature_space import FeatureSpace
        from common.pca import OnlinePCAFitter
        from edge.runtime import EdgeConfig
        from encoders import make_encoder

        cfg.validate()
        ecfg = EdgeConfig()
        kind = cast(Literal["sim", "label"], cfg.encoder)         # validate() allows only these
        ecfg = dataclasses.replace(ecfg, encoder=dataclasses.replace(ecfg.encoder, kind=kind,
                                                                     label_stride=cfg.label_stride))
        self.world, self.cfg = world, cfg
        # the simulated camera + encoder: the sim encoder turns the rendered scene's labels into
        # degraded features (it stands in for the image a ViT would see)
        self.encoder = make_encoder(ecfg.encoder, class_names=world.classes)
        hw = (cfg.resolution, cfg.resolution)
        self.hw = hw
        self.K = world.camera(hw, 90.0)
        self.rng = np.random.default_rng(cfg.sensor_seed)
        classes = cfg.pca_fit == "classes"
        centre = np.array([0.0, 0.0, 1.5]) if classes or fit_at is None else np.asarray(fit_at, np.float64)
        fit = OnlinePCAFitter(cfg.pca_dim, max_frames=fit_views + 1)
        with torch.inference_mode():
            if cfg.pca_fit == "vocabulary":
                fit.add(self._vocabulary_cells())
            else:
                for k in range(fit_views):
                    pose = camera_pose(centre, 2 * math.pi * k / fit_views, 0.3 * (k % 2))
                    r = self.render(pose)
                    fit.add(self.encoder.encode_with_global(r.rgb, r.labels, global_space="features")[0])
            if classes:
                fit.add(self.class_cells())
        self.pca = fit.fit()
        self.space = FeatureSpace.for_encoder(self.encoder, self.pca)
        self.seq = 0

    def start_episode(self) -> None:
        """Restart the random draws (depth sensor, sim encoder) from ``sensor_seed``, so every
        policy's episode from the same start meets the same noise for the same views."""
        self.rng = np.random.default_rng(self.cfg.sensor_seed)
        gen = getattr(self.encoder, "generator", None)
        if gen is not None:
            gen.manual_seed(int(getattr(self.encoder, "seed", 0)))

    def _vocabulary_cells(self) -> torch.Tensor:
        """(C, V, 1): the text embeddings of the generic vocabulary less the world's classes
        (:func:`~apps.closed_loop.generic_vocabulary.vocabulary_without`), as feature cells."""
        from apps.closed_loop.generic_vocabulary import vocabulary_without

        text = getattr(self.encoder, "text", None)           # the sim and label encoders' MiniLM
        if text is None:
            raise ValueError(f"pca_fit=vocabulary needs an encoder with a text model, not {self.cfg.encoder!r}")
        words = text.encode(vocabulary_without(list(self.world.classes))).float()   # (V, C)
        return words.T.reshape(words.shape[1], -1, 1)

    def class_cells(self, side_px: int = 32) -> torch.Tensor:
        """(K, C): the encoder's feature of an image showing only class k (``side_px`` square,
        its cells averaged), for each of the world's K classes."""
        rgb = np.zeros((side_px, side_px, 3), np.uint8)
        rows = []
        for k in range(len(self.world.classes)):
            lab = np.full((side_px, side_px), k, np.int64)
            x = self.encoder.encode_with_global(rgb, lab, global_space="features")[0]
            rows.append(x.reshape(x.shape[0], -1).mean(1))
        return torch.stack(rows)

    def view_poses(self, platform: Platform, centre: np.ndarray) -> list[np.ndarray]:
        """Camera poses of one step's views at camera centre ``centre`` (m)."""
        n = self.cfg.views
        tilt = math.radians(self.cfg.drone_tilt_deg if platform.name == "drone" else self.cfg.tilt_deg)
        return [camera_pose(centre, 2 * math.pi * k / n, tilt) for k in range(n)]

    def frame(self, pose: np.ndarray, robot: str = "sim") -> Frame:
        """One rendered view as the mapper receives it (decoded from the wire; the mapper's map
        applies its depth limit): :meth:`encode` of :meth:`render`."""
        return self.encode(self.render(pose), pose, robot)

    def render(self, pose: np.ndarray):
        """The simulated camera: the world rendered at camera pose ``pose`` (4×4 camera-to-world)."""
        return self.world.render(pose, self.K, self.hw)

    def sense_depth(self, depth: np.ndarray) -> np.ndarray:
        """The depth sensor's reading of a view's exact planar ``depth`` (m; module docstring)."""
        if self.cfg.sensor == "realistic":
            return self.cfg.depth_model.apply(depth, self.K, self.rng)
        out = np.asarray(depth, np.float32).copy()
        if self.cfg.sky_no_return:      # no surface, no return: the map ignores these pixels
            out[np.isinf(out)] = np.nan
        return out

    def encode(self, r, pose: np.ndarray, robot: str = "sim") -> Frame:
        """What the robot's edge does with a camera image ``r`` (:meth:`render`) taken at
        ``pose``: encoder → PCA → wire, and the mapper's decode."""
        from common.wire import decode_frame, encode_frame
        from edge.runtime import compress_features

        with torch.inference_mode():
            x, g = self.encoder.encode_with_global(r.rgb, r.labels, global_space="features")
        depth = self.sense_depth(r.depth)
        f = Frame(robot=robot, seq=self.seq, stamp=float(self.seq), pose=pose, intrinsics=self.K, depth=depth,
                  rgb=r.rgb, features=compress_features(self.pca, x), feature_space=self.space.id,
                  global_feature=compress_features(self.pca, g.reshape(-1, 1, 1)).reshape(-1))
        self.seq += 1
        return decode_frame(encode_frame(f, feature_codec=self.cfg.feature_codec))
