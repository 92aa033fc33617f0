"""The text-encoder interface shared by the label encoder (edge) and the query side (mapper)."""
from __future__ import annotations

from typing import Protocol, Sequence

import torch

from common.text.templates import IMAGENET_TEMPLATES, SINGLE_TEMPLATE, fill


class TextEncoder(Protocol):
    """Embeds strings into an L2-normalised ``(Q, dim)`` float32 tensor on ``device``."""

    name: str  #: "minilm-l6" | "siglip"
    dim: int

    def encode(self, texts: Sequence[str]) -> torch.Tensor: ...

    def encode_labels(self, labels: Sequence[str], templates: str = "none") -> torch.Tensor: ...


class CachedTextEncoder:
    """Base with a per-string embedding cache and template averaging.

    Subclasses implement ``_embed(list[str]) -> (n, dim)`` (L2-normalised rows).
    """

    name = "text"
    dim = 0

    def __init__(self, device: str | torch.device = "cpu", cache_size: int = 4096):
        self.device = torch.device(device)
        self._cache: dict[str, torch.Tensor] = {}
        self._cache_size = int(cache_size)

    def _embed(self, texts: list[str]) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    @torch.inference_mode()
    def encode(self, texts: Sequence[str]) -> torch.Tensor:
        """Embed each string as is: ``(Q, dim)`` float32, rows L2-normalised (cached)."""
        if isinstance(texts, str):
            raise TypeError("encode() takes a sequence of strings, not a single string")
        texts = [str(t) for t in texts]
        todo = sorted({t for t in texts if t not in self._cache})
        if todo:
            emb = self._embed(todo).float()
            if len(self._cache) + len(todo) > self._cache_size:
                self._cache.clear()
            for t, e in zip(todo, emb):
                self._cache[t] = e.detach()
        if not texts:
            return torch.zeros(0, self.dim, device=self.device)
        return torch.stack([self._cache[t] for t in texts]).to(self.device)

    def encode_labels(self, labels: Sequence[str], templates: str = "none") -> torch.Tensor:
        """Embed class labels: ``templates`` = "none" (raw label), "single" ("a photo of a {}.")
        or "imagenet80" (80 prompts averaged, then re-normalised)."""
        if templates == "none":
            return self.encode(labels)
        tl = {"single": SINGLE_TEMPLATE, "imagenet80": IMAGENET_TEMPLATES}.get(templates)
        if tl is None:
            raise ValueError(f"templates must be 'none', 'single' or 'imagenet80', got {templates!r}")
        out = []
        for lab in labels:
            e = self.encode(fill(lab, tl)).mean(0)
            out.append(torch.nn.functional.normalize(e, dim=-1))
        return torch.stack(out) if out else torch.zeros(0, self.dim, device=self.device)
