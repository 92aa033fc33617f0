"""NARADIO: RADIO v2.5 features with NACLIP last-block attention, aligned to SigLIP by
RADIO's SigLIP summary head (RayFronts' encoder; docs/models.md#encoders).

``encode(rgb)`` returns RADIO-space features ``(D, H'/p, W'/p)`` (D = 768 b / 1024 l,
p = 16) where ``(H', W')`` is the input size after optional resizing to
``input_resolution`` and rounding to multiples of p; the map averages these, and the
mapper applies :attr:`language_head` at query time (after averaging). With
``output='language'`` the head is applied here instead. ``encode_global`` is the
language-space (SigLIP) image vector: the head applied to the SigLIP class token.

The image-level vector the edge *sends* must live in the same space as the dense features
(the map stores both in one space and the PCA basis is fitted on it):
``encode_with_global(..., global_space="features")`` gives the SigLIP teacher's class token
in RADIO space for ``output='radio'`` (768/1024-d; the mapper's language head maps it at
query time, exactly like an averaged voxel feature) and the head applied to it for
``output='language'``. With PCA it goes through the same basis as the dense features
(fitted on patch tokens, so the class token is compressed with some extra loss).
"""
from __future__ import annotations

from typing import cast

import numpy as np
import torch

from encoders.config import EncoderConfig
from encoders.files import find_radio_checkpoint
from encoders.heads import summary_head, summary_slot
from encoders.naclip import NaclipBlock
from encoders.radio import (
    PRESETS,
    Block,
    RadioCheckpoint,
    RadioConfig,
    RadioModel,
    RadioOutput,
    build_radio,
    read_checkpoint,
)

_DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def round_to_patch(n: int, p: int) -> int:
    """Nearest positive multiple of ``p``."""
    return max(p, int(round(n / p)) * p)


class NaradioEncoder:
    name = "naradio"
    text_model = "siglip"

    def __init__(self, cfg: EncoderConfig, device: str | torch.device | None = None,
                 ckpt: RadioCheckpoint | None = None):
        """Load the checkpoint named by ``cfg`` (or use an already read ``ckpt``)."""
        self.cfg = cfg
        self.device = torch.device(device or cfg.device)
        self.dtype = _DTYPES[cfg.dtype]
        if ckpt is None:
            ckpt = read_checkpoint(find_radio_checkpoint(cfg.model, cfg.model_dir, cfg.checkpoint))
        path = ckpt.path
        expect = RadioConfig.preset(cfg.model) if cfg.model in PRESETS else None
        self.model: RadioModel = build_radio(ckpt, self.device, self.dtype, expect=expect)
        self.model.normalize_input = bool(cfg.normalize_input)
        self.head = summary_head(ckpt, cfg.lang_adaptor, self.device, self.dtype)
        self.slot = cfg.summary_slot if cfg.summary_slot >= 0 else summary_slot(ckpt, cfg.lang_adaptor)
        rc = self.model.cfg
        if not 0 <= self.slot < rc.num_cls_tokens:
            raise ValueError(f"summary_slot {self.slot} outside the {rc.num_cls_tokens} class tokens")
        if self.head.in_dim != rc.embed_dim:
            raise ValueError(f"language head expects {self.head.in_dim}-d input, backbone gives {rc.embed_dim}")
        self.last_block = (NaclipBlock(cast(Block, self.model.base_model.blocks[-1]), rc.num_prefix, cfg.gauss_std,
                                       cfg.reduced_block) if cfg.naclip else None)
        self.checkpoint_path = str(path)
        arch = cfg.model if cfg.model in PRESETS else rc.arch
        self.stride = rc.patch_size
        # the version names everything that changes the features (weights, input conditioning,
        # NACLIP and its settings, output space), so maps of different settings never mix
        naclip_tag = ".plain" if not cfg.naclip else (
            (f".g{cfg.gauss_std:g}" if cfg.gauss_std != 7.0 else "") + (".reduced" if cfg.reduced_block else ""))
        self.version = f"{arch}.{ckpt.weights_hash()}" + ("" if cfg.normalize_input else ".nonorm") + \
            naclip_tag + (".lang" if cfg.output == "language" else "") + \
            ("" if not cfg.input_resolution else ".r{}x{}".format(*self.input_size(1, 1)))
        self.feature_dim = self.head.out_dim if cfg.output == "language" else rc.embed_dim
        #: the head the mapper applies at query time (None when features are already language-space)
        self.language_head = None if cfg.output == "language" else self.head

    @property
    def query_config(self) -> dict:
        """The settings another process needs to build this encoder for image queries
        (``FeatureSpace.encoder_config``): ``EncoderConfig`` keys, without device and dtype."""
        c = self.cfg
        return {"kind": "naradio", "model": c.model, "checkpoint": c.checkpoint, "lang_adaptor": c.lang_adaptor,
                "summary_slot": int(self.slot), "naclip": bool(c.naclip), "gauss_std": float(c.gauss_std),
                "reduced_block": bool(c.reduced_block), "normalize_input": bool(c.normalize_input),
                "input_resolution": [int(v) for v in c.input_resolution], "output": c.output}

    # ---------------------------------------------------------------- input
    def input_size(self, h: int, w: int) -> tuple[int, int]:
        """Size the image is encoded at: ``input_resolution`` (or native) rounded to the patch."""
        p = self.stride
        if self.cfg.input_resolution:
            if len(self.cfg.input_resolution) != 2:
                raise ValueError(f"input_resolution must be [H, W], got {self.cfg.input_resolution}")
            h, w = self.cfg.input_resolution
        return round_to_patch(h, p), round_to_patch(w, p)

    def preprocess(self, rgb: np.ndarray) -> torch.Tensor:
        """``(H, W, 3)`` uint8 RGB → ``(1, 3, H', W')`` float in [0, 1] on the device."""
        if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb must be an (H, W, 3) uint8 array, got {getattr(rgb, 'shape', type(rgb))}")
        if rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8, got {rgb.dtype}")
        x = torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device).permute(2, 0, 1)[None].float() / 255.0
        hh, ww = self.input_size(rgb.shape[0], rgb.shape[1])
        if (hh, ww) != tuple(rgb.shape[:2]):
            x = torch.nn.functional.interpolate(x, size=(hh, ww), mode="bilinear", align_corners=False,
                                                antialias=True).clamp(0, 1)
        return x.to(self.dtype)

    # ---------------------------------------------------------------- encoding
    @torch.inference_mode()
    def forward(self, rgb: np.ndarray, naclip: bool | None = None) -> RadioOutput:
        """RADIO outputs for one ``(H, W, 3)`` uint8 RGB image (NACLIP attention in the last block
        when ``naclip``, default ``cfg.naclip``)."""
        use = self.cfg.naclip if naclip is None else naclip
        return self.model(self.preprocess(rgb), last_block=self.last_block if use else None)

    @torch.inference_mode()
    def align_spatial(self, feat: torch.Tensor) -> torch.Tensor:
        """Head applied token-wise: ``(D, h, w) -> (D_lang, h, w)`` or ``(..., D) -> (..., D_lang)``."""
        if feat.ndim == 3 and feat.shape[0] == self.head.in_dim:
            return self.head(feat.permute(1, 2, 0)).permute(2, 0, 1)
        return self.head(feat)

    @torch.inference_mode()
    def encode_with_global(self, rgb: np.ndarray, labels: np.ndarray | None = None,
                           global_space: str = "language") -> tuple[torch.Tensor, torch.Tensor]:
        """Both outputs from one forward pass: ``((C, h, w), (D_g,))`` float32.

        ``global_space='language'``: the SigLIP-space image vector (``D_g`` = head output);
        ``'features'``: the image vector in the dense features' space (``D_g = C``; see the
        module docstring), which is what the edge puts on the wire."""
        if global_space not in ("language", "features"):
            raise ValueError(f"global_space must be 'language' or 'features', got {global_space!r}")
        out = self.forward(rgb)
        f = out.features[0]
        if self.cfg.output == "language":
            f = self.align_spatial(f)
        cls = out.cls_tokens[0, self.slot]
        if global_space == "features" and self.cfg.output == "radio":
            return f.float(), cls.float()
        return f.float(), self.head(cls).float()

    def encode(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> torch.Tensor:
        """``(C, h, w)`` float32 (labels ignored)."""
        return self.encode_with_global(rgb)[0]

    def encode_global(self, rgb: np.ndarray, labels: np.ndarray | None = None) -> torch.Tensor:
        """SigLIP-space image vector ``(D_lang,)``: the head on the language teacher's class token."""
        return self.encode_with_global(rgb)[1]
