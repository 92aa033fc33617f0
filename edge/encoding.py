"""The edge's encoder and PCA chain: building the encoder for the source's classes, choosing
the PCA basis (a file, none, the map's basis asked from the mapper, or an online fit over the
first frames, holding them meanwhile), the start-up checks of the encoder × ``encoder.output`` ×
PCA combination, the feature space the edge serves, and compressing each frame's features.

Start-up checks (``check_setup``): the PCA output dimension within the encoder's feature
dimension, a basis file fitted on the features this encoder/output gives and with the configured
``pca.out_dim``, enough samples for an online fit; a failing check is a *refusal*
(:class:`EdgeRefused`: one error line naming the combination). The image-level vector sent with
each frame is in the dense features' space (``encode_with_global(..., global_space="features")``),
compressed by the same PCA."""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from edge.config import EdgeConfig, basis_file

if TYPE_CHECKING:
    import torch

    from common.feature_space import FeatureSpace
    from common.pca import PCA
    from encoders import ImageEncoder

log = logging.getLogger("rayfronts.edge")


class EdgeRefused(Exception):
    """The edge cannot start with this configuration; the text is the one-line reason."""


def _combo(cfg: EdgeConfig) -> str:
    e = cfg.encoder
    enc = f"encoder.kind={e.kind}" + (f" encoder.output={e.output}" if e.kind == "naradio" else "")
    pca = ("pca.out_dim=0 (no PCA)" if cfg.pca.out_dim <= 0 else
           f"pca.basis={cfg.pca.basis}" if cfg.pca.basis else f"pca.out_dim={cfg.pca.out_dim} (fitted online)")
    return f"{enc}, {pca}"


def check_setup(cfg: EdgeConfig, encoder: ImageEncoder, pca: PCA | None) -> None:
    """Refuse (:class:`EdgeRefused`) an encoder × output × PCA combination that cannot run."""
    d = int(encoder.feature_dim)
    k = int(cfg.pca.out_dim)
    where = _combo(cfg)
    if k < 0:
        raise EdgeRefused(f"{where}: pca.out_dim must be >= 0 (0 = no PCA)")
    if cfg.publish.feature_codec not in ("q16z", "q8z", "f16"):
        raise EdgeRefused(f"publish.feature_codec={cfg.publish.feature_codec!r}: choose q16z, q8z or f16")
    if not 1 <= cfg.publish.jpeg_quality <= 100:
        raise EdgeRefused(f"publish.jpeg_quality={cfg.publish.jpeg_quality}: must be in 1..100")
    if k > d:
        raise EdgeRefused(f"{where}: pca.out_dim={k} exceeds the encoder's {d}-d features; use at most {d}")
    if pca is not None:
        if pca.in_dim != d:
            hint = ""
            if cfg.encoder.kind == "naradio":
                hint = (" (encoder.output=radio gives backbone-width features, output=language the language "
                        "head's width: fit the basis with the same output, `rayfronts edge fit-pca`)")
            raise EdgeRefused(f"{where}: the basis was fitted on {pca.in_dim}-d features but this encoder "
                              f"gives {d}-d features{hint}")
        if pca.out_dim != k:
            raise EdgeRefused(f"{where}: the basis has {pca.out_dim} components but pca.out_dim={k}; set "
                              f"pca.out_dim={pca.out_dim} to use this basis")
    elif k > 0 and not cfg.pca.basis:      # an online fit
        n = max(1, cfg.pca.fit_frames) * cfg.pca.pixels_per_frame
        if n <= k:
            raise EdgeRefused(f"{where}: an online fit over pca.fit_frames={cfg.pca.fit_frames} x "
                              f"pca.pixels_per_frame={cfg.pca.pixels_per_frame} = {n} samples cannot give {k} "
                              "components; raise them or give pca.basis")


def check_first_features(cfg: EdgeConfig, feats: torch.Tensor) -> None:
    """After the first frame: an online PCA fit needs more feature vectors than components."""
    k = int(cfg.pca.out_dim)
    if k > 0 and not cfg.pca.basis:
        per = min(int(feats.shape[-1] * feats.shape[-2]), cfg.pca.pixels_per_frame)
        n = per * max(1, cfg.pca.fit_frames)
        if n <= k:
            raise EdgeRefused(f"{_combo(cfg)}: the encoder gives {per} feature vectors per frame, so an online "
                              f"fit over {cfg.pca.fit_frames} frames has {n} samples for {k} components; raise "
                              "pca.fit_frames, lower pca.out_dim or give pca.basis")


def compress_features(pca: PCA | None, feats: torch.Tensor | np.ndarray) -> np.ndarray:
    """(C, h, w) encoder features → (D, h, w) float16 PCA coefficients (``pca=None``: cast only)."""
    import torch

    f = feats if isinstance(feats, torch.Tensor) else torch.as_tensor(np.asarray(feats))
    c, h, w = f.shape
    if pca is None:
        return f.to(torch.float16).cpu().numpy()
    flat = f.reshape(c, h * w).T.to(torch.float32)
    z = pca.compress(flat)
    z = z if isinstance(z, torch.Tensor) else torch.as_tensor(np.asarray(z))
    return z.T.reshape(-1, h, w).to(torch.float16).cpu().numpy()




class EncoderChain:
    """Encoder → PCA of one edge run. ``set_phase(text)`` reports what it is doing;
    ``ask_map_space(timeout)`` returns ``(the map's FeatureSpace or None, why not)``;
    ``serve(reply)`` publishes the edge's encoded feature space once it is known. ``cfg`` may
    change once: ``pca.basis=map`` adopts the map's ``pca.out_dim``."""

    def __init__(self, cfg: EdgeConfig, set_phase: Callable[[str], None],
                 ask_map_space: Callable[[float], tuple[FeatureSpace | None, str]],
                 serve: Callable[[bytes], None]):
        self.cfg = cfg
        self._set_phase, self._ask_map_space, self._serve = set_phase, ask_map_space, serve
        self.encoder: Any = None          # ImageEncoder once loaded
        self.pca: Any = None              # PCA or None
        self.fs: Any = None               # FeatureSpace once known
        self.fitter: Any = None           # OnlinePCAFitter while fitting PCA online
        self.pending: list = []           # frames held while fitting PCA online

    def load(self, names: list[str] | None) -> None:
        """Build the encoder (for the source's class ``names``) and the PCA: a basis file, none,
        or an online fitter (``fs`` stays None until the fit is done)."""
        from common.pca import PCA
        from encoders import make_encoder

        cfg = self.cfg
        self._set_phase(f"loading the {cfg.encoder.kind} encoder")
        self.encoder = make_encoder(cfg.encoder, class_names=names)
        if basis_file(cfg) and cfg.pca.out_dim > 0:
            self.pca = PCA.load(basis_file(cfg))
        elif cfg.pca.basis in ("", "map") and cfg.pca.out_dim > 0:
            self.pca = self._map_basis(self.encoder, required=cfg.pca.basis == "map")
            if self.pca is not None and self.pca.out_dim != cfg.pca.out_dim:   # only with pca.basis=map
                log.info("pca.out_dim=%d -> %d: the map's basis", cfg.pca.out_dim, self.pca.out_dim)
                self.cfg = cfg = dataclasses.replace(cfg, pca=dataclasses.replace(cfg.pca, out_dim=self.pca.out_dim))
        check_setup(cfg, self.encoder, self.pca)
        if cfg.pca.out_dim <= 0:
            self.fs = self._feature_space(None)
        elif self.pca is not None:
            self.fs = self._feature_space(self.pca)
        else:
            from common.pca import OnlinePCAFitter

            log.warning("no PCA basis file given: fitting PCA-%d online over the first %d frames "
                        "(frames are held until then; give pca.basis for a fixed, shared basis)",
                        cfg.pca.out_dim, cfg.pca.fit_frames)
            self.fitter = OnlinePCAFitter(cfg.pca.out_dim, max(1, cfg.pca.fit_frames), cfg.pca.pixels_per_frame)
            self._set_phase(f"fitting PCA-{cfg.pca.out_dim} online over the first "
                            f"{max(1, cfg.pca.fit_frames)} frames")

    def _map_basis(self, encoder: ImageEncoder, required: bool) -> PCA | None:
        """The map's PCA basis, asked on ``<p>/mapper/feature_space`` for up to
        ``pca.map_wait_s``: adopted when the map's encoder family is this encoder's (and, unless
        ``required`` (``pca.basis=map``), its components are ``pca.out_dim``); else None, or
        :class:`EdgeRefused` when required."""
        from common.feature_space import FeatureSpace, compatibility

        cfg = self.cfg
        self._set_phase("asking the mapper for the map's PCA basis")
        map_fs, why = self._ask_map_space(max(0.1, float(cfg.pca.map_wait_s)))
        if map_fs is not None:
            why = compatibility(map_fs, FeatureSpace.for_encoder(encoder, None))
            pca = map_fs.pca
            if not why and pca is None:
                why = "the map stores uncompressed features"
            if not why and pca is not None and not required and pca.out_dim != cfg.pca.out_dim:
                why = f"the map's basis has {pca.out_dim} components, pca.out_dim={cfg.pca.out_dim}"
            if not why:
                log.info("adopting the map's PCA basis (feature space %s): no re-projection at the mapper", map_fs.id)
                return pca
        if required:
            raise EdgeRefused(f"pca.basis=map: cannot adopt the map's basis: {why}")
        log.info("not adopting the map's PCA basis (%s): fitting one online", why)
        return None

    def _feature_space(self, pca: PCA | None) -> FeatureSpace:
        from common.feature_space import FeatureSpace
        from common.messages import encode_feature_space

        fs = FeatureSpace.for_encoder(self.encoder, pca)
        self._serve(encode_feature_space(self.cfg.robot, fs.to_body()))
        log.info("feature space %s (dim %d)", fs.id, fs.dim)
        self._set_phase("sending frames")
        return fs

    def to_send(self, fr: Any, feats: torch.Tensor, gfeat: torch.Tensor | None) -> list | None:
        """``[(frame, features, global feature)]`` to send now: this frame, or while fitting PCA
        online None (held) until the fit is done, then the whole backlog."""
        if self.fs is not None:
            return [(fr, feats, gfeat)]
        self.pending.append((fr, feats, gfeat))
        if not self.fitter.add(feats):
            return None
        self.pca = self.fitter.fit()
        if self.cfg.pca.save_fitted:
            self.pca.save(self.cfg.pca.save_fitted)
        self.fs = self._feature_space(self.pca)
        todo, self.pending = self.pending, []
        return todo

    def compressed(self, fr: Any, seq: int, feats: torch.Tensor, gfeat: torch.Tensor | None) -> Any:
        """``fr`` as sent: robot, ``seq``, the compressed features and global feature, the
        feature space id, and in its meta ``t_send`` (hand-off wall clock, for the mapper's
        latency) and ``cpu_s`` (this process's CPU time so far: the mapper reports the edge's
        CPU per frame from it)."""
        import torch

        out = dataclasses.replace(
            fr, robot=self.cfg.robot, seq=seq, features=compress_features(self.pca, feats),
            feature_space=self.fs.id,
            global_feature=None if gfeat is None else compress_features(
                self.pca, torch.as_tensor(gfeat).reshape(-1, 1, 1)).reshape(-1))
        out.meta = {**(out.meta or {}), "t_send": time.time(), "cpu_s": time.process_time()}
        return out
