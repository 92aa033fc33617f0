"""Simulated ViT-like encoder (``encoder.kind=sim``): the label encoder's class embeddings
degraded the way a real patch-based vision-language encoder degrades them, so the
benchmarks measure open-vocabulary mapping and not only geometry.

Pipeline per image (all random draws from one ``torch.Generator`` seeded with
``sim_seed`` at construction, so a run that encodes the same frames in the same order is
reproducible bit for bit):

1. **Patch grid.** The image is seen as a ViT sees its resized input: ``sim_input_width /
   sim_patch`` patch columns (default 640 / 16 = 40, the paper's NARADIO setting) and as
   many rows as the aspect ratio gives (at least one; ``sim_input_width = 0`` = the native
   width). Each patch holds the area fractions of the classes under it.
2. **Confusion between related classes.** Every class ``c`` has a related class ``r(c)``:
   the pairs in ``sim_related`` ("tree/bush", both names present), else its nearest other
   class in the text space (e.g. building/chimney, water tower/radio tower), never class 0.
   Systematic part: class ``c``'s embedding is ``normalise((1 - sim_bias) e_c + sim_bias
   e_r(c))`` (the model's bias toward the related concept). Per patch and image, with
   probability ``sim_confusion`` the patch's dominant class is replaced by its related
   class (a misclassified patch).
3. **Boundary bleeding.** Attention mixes neighbouring patches: each patch feature becomes
   ``(1 - sim_bleed) f + sim_bleed · mean(8-neighbourhood f)`` (edge patches use the
   neighbours they have).
4. **Upsampling** like a real ViT's output: bilinear (``align_corners=False``) from the patch
   grid to ``sim_upsample`` cells per patch per axis, capped at the image size — features
   blend across patch boundaries.
5. **Noise.** Per output cell, isotropic Gaussian noise at ``sim_snr_db``: the noise
   variance per channel is ``|f|² / (C · 10^(snr/10))`` (cell signal power over noise
   power = the SNR).

Class 0 (the world's "sky", no object) takes part like any class. ``encode_global`` is the
mean of the dense output (as the label encoder's mean pooling). Features live in the MiniLM
space (384-d) of the label encoder, so the class texts of the queries are the *undistorted*
name embeddings (``table``).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from encoders.text.minilm import MiniLMText


class SimEncoder:
    name = "sim"
    version = "sim-vit.1"
    text_model = "minilm-l6"
    language_head = None

    def __init__(self, class_names: Sequence[str], *, patch: int = 16, input_width: int = 640,
                 upsample: int = 4, bleed: float = 0.3, bias: float = 0.2, confusion: float = 0.1,
                 snr_db: float = 0.0, related: Sequence[str] = (), seed: int = 0,
                 device: str | torch.device = "cpu", text_encoder: MiniLMText | None = None,
                 text_model_dir: str | None = None):
        names = [str(c) for c in class_names or []]
        if not names:
            raise ValueError("sim encoder needs the class names (e.g. the world's classes)")
        if patch < 1 or input_width < 0 or upsample < 1:
            raise ValueError(f"sim encoder needs patch >= 1, input_width >= 0, upsample >= 1, "
                             f"got {patch}, {input_width}, {upsample}")
        for k, v in (("bleed", bleed), ("bias", bias), ("confusion", confusion)):
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"sim {k} must be in [0, 1], got {v}")
        if not np.isfinite(snr_db):
            raise ValueError(f"sim snr_db must be finite, got {snr_db}")
        self.device = torch.device(device)
        self.class_names = names
        self.patch, self.input_width, self.upsample = int(patch), int(input_width), int(upsample)
        self.bleed, self.bias, self.confusion, self.snr_db = float(bleed), float(bias), float(confusion), float(snr_db)
        self.seed = int(seed)
        self.text = text_encoder or MiniLMText(device=self.device, model_dir=text_model_dir or None)
        self.table = self.text.encode(names).to(self.device).float()      # (K, C) true name embeddings
        self.feature_dim = int(self.table.shape[1])
        self.stride = 1
        self.related = self._related(list(related))
        mixed = (1.0 - self.bias) * self.table + self.bias * self.table[self.related]
        self.emb = mixed / mixed.norm(dim=1, keepdim=True).clamp_min(1e-12)  # (K, C) biased class features
        self.generator = torch.Generator().manual_seed(self.seed)

    # ------------------------------------------------------------------ structure
    def _related(self, pairs: list[str]) -> torch.Tensor:
        """(K,) related class of each class (see module docstring, step 2)."""
        K = len(self.class_names)
        idx = {n: i for i, n in enumerate(self.class_names)}
        sim = self.table @ self.table.T
        sim.fill_diagonal_(-2.0)
        if K > 1:
            sim[:, 0] = -2.0                      # nothing turns into "no object"
        rel = sim.argmax(1) if K > 1 else torch.zeros(1, dtype=torch.int64)
        for p in pairs:
            a, sep, b = p.partition("/")
            if not sep:
                raise ValueError(f"sim related pair must be 'a/b', got {p!r}")
            a, b = a.strip(), b.strip()
            if a in idx and b in idx:
                rel[idx[a]], rel[idx[b]] = idx[b], idx[a]
        return rel.to(self.device)

    def patch_grid(self, H: int, W: int) -> tuple[int, int]:
        """(rows, columns) of the patch grid for an (H, W) image."""
        iw = self.input_width or W
        gw = max(1, round(iw / self.patch))
        gh = max(1, round(gw * H / W))
        return min(gh, H), min(gw, W)

    def _check(self, rgb, labels) -> torch.Tensor:
        if labels is None:
            raise ValueError("the sim encoder needs per-pixel labels (the source provides none)")
        lab = np.asarray(labels)
        if lab.ndim != 2 or not np.issubdtype(lab.dtype, np.integer) or lab.size == 0:
            raise ValueError(f"labels must be a non-empty (H, W) integer array, got {lab.shape} {lab.dtype}")
        if rgb is not None and tuple(np.shape(rgb)[:2]) != lab.shape:
            raise ValueError(f"labels {lab.shape} and rgb {np.shape(rgb)[:2]} differ in size")
        if lab.min() < 0 or lab.max() >= len(self.class_names):
            raise ValueError(f"labels must lie in [0, {len(self.class_names)}), got [{lab.min()}, {lab.max()}]")
        return torch.from_numpy(lab.astype(np.int64)).to(self.device)

    # ------------------------------------------------------------------ encode
    @torch.inference_mode()
    def encode(self, rgb: np.ndarray | None, labels: np.ndarray | None = None) -> torch.Tensor:
        lab = self._check(rgb, labels)
        H, W = lab.shape
        K = len(self.class_names)
        gh, gw = self.patch_grid(H, W)
        onehot = torch.nn.functional.one_hot(lab, K).permute(2, 0, 1).float()[None]  # (1, K, H, W)
        frac = torch.nn.functional.adaptive_avg_pool2d(onehot, (gh, gw))[0]          # (K, gh, gw)
        if self.confusion > 0:
            dom = frac.argmax(0)                                            # (gh, gw)
            flip = torch.rand((gh, gw), generator=self.generator) < self.confusion
            flip = flip.to(self.device) & (dom > 0)
            if bool(flip.any()):
                ys, xs = torch.nonzero(flip, as_tuple=True)
                d = dom[ys, xs]
                r = self.related[d]
                moved = frac[d, ys, xs].clone()
                frac[d, ys, xs] = 0.0
                frac[r, ys, xs] += moved
        f = torch.einsum("kc,khw->chw", self.emb, frac)                     # (C, gh, gw)
        if self.bleed > 0 and (gh > 1 or gw > 1):
            ones = torch.ones((1, 1, gh, gw), device=self.device)
            ker = torch.ones((1, 1, 3, 3), device=self.device)
            ker[0, 0, 1, 1] = 0.0
            n = torch.nn.functional.conv2d(ones, ker, padding=1)              # neighbours per patch
            s = torch.nn.functional.conv2d(f[:, None], ker, padding=1)[:, 0]  # (C, gh, gw)
            f = (1.0 - self.bleed) * f + self.bleed * s / n[0, 0].clamp_min(1.0)
        oh, ow = min(H, gh * self.upsample), min(W, gw * self.upsample)
        out = torch.nn.functional.interpolate(f[None], size=(oh, ow), mode="bilinear", align_corners=False)[0]
        p_sig = (out * out).sum(0, keepdim=True)                           # (1, oh, ow)
        std = torch.sqrt(p_sig / (self.feature_dim * 10.0 ** (self.snr_db / 10.0)))
        noise = torch.randn(out.shape, generator=self.generator).to(self.device)
        return (out + noise * std).contiguous()

    @torch.inference_mode()
    def encode_global(self, rgb: np.ndarray | None, labels: np.ndarray | None = None) -> torch.Tensor:
        return self.encode(rgb, labels).mean((1, 2))

    def encode_with_global(self, rgb: np.ndarray | None, labels: np.ndarray | None = None,
                           global_space: str = "language") -> tuple[torch.Tensor, torch.Tensor]:
        """``(dense, its mean)`` from one draw (dense and global share the MiniLM space)."""
        if global_space not in ("language", "features"):
            raise ValueError(f"global_space must be 'language' or 'features', got {global_space!r}")
        dense = self.encode(rgb, labels)
        return dense, dense.mean((1, 2))
