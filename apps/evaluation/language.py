"""Class-name embeddings and feature similarity for the benchmarks, for any encoder.

* Label encoder (MiniLM space, no head): class texts are its own table (or MiniLM
  embeddings), similarity = cosine.
* Encoders with a language head (NARADIO: RADIO-space features, SigLIP head): class texts
  are embedded by the feature space's text model (SigLIP text tower from
  ``text_model_dir``, default ``<encoder.model_dir or $RAYFRONTS_MODEL_DIR>/siglip_text``),
  and map features are compared through
  :meth:`common.feature_space.FeatureSpace.similarity` — the head is applied to the
  *averaged* voxel / ray features at query time (docs/method.md#language-head), exactly as the mapper does.
  Image-level (global) features are already language-space (``encode_global`` applies the
  head): Semantic Poses maps them directly and uses cosine.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import torch

from common.feature_space import FeatureSpace, FeatureSpaceError

if TYPE_CHECKING:
    from encoders import ImageEncoder

Similarity = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class EvalLanguage:
    text: torch.Tensor                  # (K, D) class embeddings in the language space, rows unit norm
    similarity: Similarity | None       # (N, C) map features, (Q, D) queries -> (Q, N); None = cosine
    feature_space: FeatureSpace
    text_model: str

    @property
    def lang_dim(self) -> int:
        return int(self.text.shape[1])


def text_model_dir(enc: ImageEncoder, configured: str = "") -> str | None:
    """Directory of the encoder's text model: ``configured``, else for SigLIP
    ``<encoder model_dir or default model dir>/siglip_text``, else None (MiniLM: the package's)."""
    if configured:
        return configured
    if getattr(enc, "text_model", "minilm-l6") == "siglip":
        from encoders.files import SIGLIP_TEXT_DIR, default_model_dir
        md = getattr(getattr(enc, "cfg", None), "model_dir", "") or ""
        return str((Path(md).expanduser() if md else default_model_dir()) / SIGLIP_TEXT_DIR)
    return None


def use_templates(setting: bool | str, enc: ImageEncoder) -> bool:
    """Resolve a ``templates`` setting (true / false / "auto") for encoder ``enc``: auto = the
    paper's 80 prompt templates for language encoders (class texts from a text tower aligned
    with an image model: a language head or the SigLIP text model), raw names for the label
    and sim encoders (their features are the raw name embeddings themselves)."""
    if isinstance(setting, bool):
        return setting
    if setting != "auto":
        raise ValueError(f"templates must be true, false or 'auto', got {setting!r}")
    return getattr(enc, "language_head", None) is not None or getattr(enc, "text_model", "") == "siglip"


def eval_language(enc: ImageEncoder, class_names: Sequence[str], templates: bool = False, model_dir: str = "",
                  device: str | torch.device = "cpu") -> EvalLanguage:
    """Class embeddings and similarity for the encoder ``enc`` (see module doc);
    ``templates``: mean of the 80 ImageNet prompt embeddings instead of the raw names."""
    names = list(class_names)
    fs = FeatureSpace.for_encoder(enc)
    table = getattr(enc, "table", None)
    if (not templates and table is not None and fs.head_config is None
            and list(getattr(enc, "class_names", []) or []) == names):
        text = table.to(torch.float32)
    else:
        te = getattr(enc, "text", None)
        if te is None or getattr(te, "name", None) != fs.text_model:
            from encoders.text import make_text_encoder
            te = make_text_encoder(fs.text_model, model_dir=text_model_dir(enc, model_dir), device=device)
        text = te.encode_labels(names, templates="imagenet80" if templates else "none").to(torch.float32)
    if text.shape[1] != fs.lang_dim:
        raise FeatureSpaceError(f"the {fs.text_model} text model gives {text.shape[1]}-d embeddings but the "
                                f"encoder's language space is {fs.lang_dim}-d (wrong text model directory?)")
    sim = None
    if fs.head_config is not None:
        dev = torch.device(device)

        def sim(feats: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
            return fs.similarity(feats, queries, device=dev)
    return EvalLanguage(text.to(device), sim, fs, fs.text_model)
