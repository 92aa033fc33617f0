"""The language side: text encoders (MiniLM, SigLIP) and prompt templates (the language head
the mapper applies is part of the feature space: :mod:`common.language_head`).

Shared by the edge (label encoder, NARADIO's SigLIP head) and the mapper (query text).
Heavy imports (transformers) happen only when an encoder is constructed.
"""
from __future__ import annotations

from pathlib import Path

import torch

from common.model_files import ModelFileError
from encoders.text.base import CachedTextEncoder, TextEncoder
from encoders.text.templates import IMAGENET_TEMPLATES, SINGLE_TEMPLATE

TEXT_MODELS = ("minilm-l6", "siglip")


def make_text_encoder(name: str, model_dir: str | Path | None = None,
                      device: str | torch.device = "cpu") -> CachedTextEncoder:
    """``"minilm-l6"`` → :class:`MiniLMText`; ``"siglip"`` → :class:`SiglipText` (needs ``model_dir``)."""
    if name == "minilm-l6":
        from encoders.text.minilm import MiniLMText
        return MiniLMText(device=device, model_dir=model_dir)
    if name == "siglip":
        from encoders.text.siglip import SiglipText
        if not model_dir:
            raise ModelFileError("SigLIP text model: no model directory given (set the text model dir)")
        return SiglipText(model_dir, device=device)
    raise ValueError(f"unknown text model {name!r}; choose one of {TEXT_MODELS}")


def __getattr__(name: str) -> type:  # lazy: MiniLMText / SiglipText import transformers only on use
    if name == "MiniLMText":
        from encoders.text.minilm import MiniLMText
        return MiniLMText
    if name == "SiglipText":
        from encoders.text.siglip import SiglipText
        return SiglipText
    raise AttributeError(name)


__all__ = ["TextEncoder", "CachedTextEncoder", "IMAGENET_TEMPLATES", "SINGLE_TEMPLATE", "TEXT_MODELS",
           "make_text_encoder", "MiniLMText", "SiglipText"]
