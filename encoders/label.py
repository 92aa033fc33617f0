"""Label encoder: each pixel's feature is the MiniLM text embedding of its class name.

For sources with exact labels (the synthetic world, labelled datasets), this stands in for
a vision-language model: queries embedded by the same text model find the classes whose
names they resemble ("vehicle" → car). Conventions:

* ``labels`` (H, W) integers in ``[0, len(class_names))``; class 0 is the world's first
  class (e.g. "sky").
* Output ``(384, ceil(H/s), ceil(W/s))`` float32 for stride ``s``; a cell covers pixels
  ``[i·s, (i+1)·s) × [j·s, (j+1)·s)`` clipped to the image.
* ``pooling='mean'``: a cell's feature is the mean of its pixels' class embeddings (not
  re-normalised; cosine similarity is scale-free). ``'majority'``: the embedding of its most
  frequent class (ties → lowest class id).
* ``encode_global``: the mean (or majority-class) embedding over the whole image.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from encoders.text.minilm import MiniLMText


class LabelEncoder:
    name = "label"
    version = "minilm-l6.1"
    text_model = "minilm-l6"
    language_head = None

    def __init__(self, class_names: Sequence[str], stride: int = 8, pooling: str = "mean",
                 device: str | torch.device = "cpu", text_encoder: MiniLMText | None = None,
                 text_model_dir: str | None = None):
        names = [str(c) for c in class_names or []]
        if not names:
            raise ValueError("label encoder needs the class names (e.g. the world's classes)")
        if stride < 1:
            raise ValueError(f"label stride must be >= 1, got {stride}")
        if pooling not in ("mean", "majority"):
            raise ValueError(f"label pooling must be 'mean' or 'majority', got {pooling!r}")
        self.device = torch.device(device)
        self.class_names = names
        self.stride = int(stride)
        self.pooling = pooling
        self.text = text_encoder or MiniLMText(device=self.device, model_dir=text_model_dir or None)
        self.table = self.text.encode(names).to(self.device)        # (K, C), rows unit norm
        self.feature_dim = int(self.table.shape[1])

    def _check(self, rgb, labels) -> torch.Tensor:
        if labels is None:
            raise ValueError("the label encoder needs per-pixel labels (the source provides none)")
        lab = np.asarray(labels)
        if lab.ndim != 2 or not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(f"labels must be an (H, W) integer array, got {lab.shape} {lab.dtype}")
        if rgb is not None and tuple(np.shape(rgb)[:2]) != lab.shape:
            raise ValueError(f"labels {lab.shape} and rgb {np.shape(rgb)[:2]} differ in size")
        if lab.size and (lab.min() < 0 or lab.max() >= len(self.class_names)):
            raise ValueError(f"labels must lie in [0, {len(self.class_names)}), got [{lab.min()}, {lab.max()}]")
        return torch.from_numpy(lab.astype(np.int64)).to(self.device)

    def class_fractions(self, lab: torch.Tensor) -> torch.Tensor:
        """``(K, h, w)``: fraction of each cell's pixels with each class (one bincount)."""
        K, s = len(self.class_names), self.stride
        H, W = lab.shape
        h, w = -(-H // s), -(-W // s)
        rows = torch.arange(H, device=lab.device) // s
        cols = torch.arange(W, device=lab.device) // s
        cell = rows[:, None] * w + cols[None, :]
        counts = torch.bincount((cell * K + lab).reshape(-1), minlength=h * w * K).reshape(h, w, K).float()
        return (counts / counts.sum(-1, keepdim=True).clamp_min(1)).permute(2, 0, 1)

    @torch.inference_mode()
    def encode(self, rgb: np.ndarray | None, labels: np.ndarray | None = None) -> torch.Tensor:
        lab = self._check(rgb, labels)
        frac = self.class_fractions(lab)                              # (K, h, w)
        if self.pooling == "majority":
            frac = torch.nn.functional.one_hot(frac.argmax(0), frac.shape[0]).permute(2, 0, 1).float()
        K, h, w = frac.shape
        return (self.table.T.float() @ frac.reshape(K, h * w)).reshape(-1, h, w)

    @torch.inference_mode()
    def encode_global(self, rgb: np.ndarray | None, labels: np.ndarray | None = None) -> torch.Tensor:
        lab = self._check(rgb, labels)
        hist = torch.bincount(lab.reshape(-1), minlength=len(self.class_names)).float()
        if self.pooling == "majority":
            return self.table[int(hist.argmax())].float().clone()
        return (hist / hist.sum().clamp_min(1)) @ self.table

    def encode_with_global(self, rgb: np.ndarray | None, labels: np.ndarray | None = None,
                           global_space: str = "language") -> tuple[torch.Tensor, torch.Tensor]:
        """``(encode(...), encode_global(...))`` (dense and global features share the MiniLM
        space, so ``global_space`` 'language' and 'features' are the same)."""
        if global_space not in ("language", "features"):
            raise ValueError(f"global_space must be 'language' or 'features', got {global_space!r}")
        return self.encode(rgb, labels), self.encode_global(rgb, labels)
