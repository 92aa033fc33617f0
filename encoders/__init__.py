"""Image encoders for the edge: the label encoder and NARADIO.

Common interface (:class:`ImageEncoder`): attributes ``name``, ``version``, ``feature_dim``,
``stride`` (input pixels per output cell), ``text_model`` ("minilm-l6" | "siglip") and
``language_head`` (an MLP2 the mapper applies at query time, or None), and::

    encode(rgb (H, W, 3) uint8, labels (H, W) int | None = None) -> torch.Tensor (C, h, w) float32
    encode_global(rgb, labels=None) -> torch.Tensor (C_lang,) float32
    encode_with_global(rgb, labels=None, global_space="language")
        -> (both of the above; NARADIO: one forward pass). ``global_space="features"``
        gives the image vector in the dense features' space instead (what the edge sends:
        the map stores it next to the dense features, through the same PCA)

For the label encoder C = C_lang = 384 (MiniLM space). For NARADIO ``encode`` gives RADIO
space (C = 768/1024, stride 16) and ``encode_global`` SigLIP space (the head is applied).

``common.feature_space.FeatureSpace.for_encoder(enc, pca)`` describes an encoder's output.
"""
from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np
import torch

from common.model_files import ModelFileError
from encoders.config import EncoderConfig


class ImageEncoder(Protocol):
    name: str
    version: str
    feature_dim: int
    stride: int
    text_model: str

    @property
    def language_head(self) -> torch.nn.Module | None: ...   # read-only: encoders narrow it

    def encode(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> torch.Tensor: ...

    def encode_global(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> torch.Tensor: ...

    def encode_with_global(self, rgb: np.ndarray, labels: np.ndarray | None = None,
                           global_space: str = "language") -> tuple[torch.Tensor, torch.Tensor]: ...


def make_encoder(cfg: EncoderConfig, class_names: Sequence[str] | None = None,
                 device: str | torch.device | None = None) -> ImageEncoder:
    """Build the encoder ``cfg.kind`` on ``device`` (default ``cfg.device``)."""
    dev = device or cfg.device
    if cfg.kind == "label":
        from encoders.label import LabelEncoder
        return LabelEncoder(class_names or [], stride=cfg.label_stride, pooling=cfg.label_pooling,
                            device=dev, text_model_dir=cfg.text_model_dir or None)
    if cfg.kind == "naradio":
        from encoders.naradio import NaradioEncoder
        return NaradioEncoder(cfg, device=dev)
    if cfg.kind == "sim":
        from encoders.sim import SimEncoder
        return SimEncoder(class_names or [], patch=cfg.sim_patch, input_width=cfg.sim_input_width,
                          upsample=cfg.sim_upsample, bleed=cfg.sim_bleed, bias=cfg.sim_bias,
                          confusion=cfg.sim_confusion, snr_db=cfg.sim_snr_db, related=cfg.sim_related,
                          seed=cfg.sim_seed, device=dev, text_model_dir=cfg.text_model_dir or None)
    raise ValueError(f"unknown encoder kind {cfg.kind!r}; choose 'label', 'naradio' or 'sim'")


__all__ = ["EncoderConfig", "ImageEncoder", "ModelFileError", "make_encoder"]
