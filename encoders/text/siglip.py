"""SigLIP text tower (the text side of NARADIO's language space), loaded from local files.

A model directory holds a ``transformers`` ``SiglipTextModel`` (``config.json`` with
``model_type`` ``siglip_text_model`` or a full ``siglip`` config, plus ``model.safetensors``
/ ``pytorch_model.bin``) and the tokenizer files (``tokenizer.json`` or ``spiece.model`` +
``tokenizer_config.json``) in the same directory. Nothing is downloaded.

Text is canonicalised like open_clip's SigLIP tokenizer (lower case, punctuation removed,
whitespace collapsed), padded to ``max_length`` (64: SigLIP pools the *last* token, so it
was trained with fixed-length padding) and the pooled, projected output is L2-normalised.
"""
from __future__ import annotations

import json
import re
import string
from pathlib import Path

import torch

from common.model_files import ModelFileError
from encoders.text.base import CachedTextEncoder, transformers_names
from encoders.text.minilm import _quiet_transformers

_PUNCT = re.compile("[" + re.escape(string.punctuation) + "]")


def canonicalize(text: str) -> str:
    """Lower case, punctuation removed, whitespace collapsed (open_clip ``canonicalize_text``)."""
    text = _PUNCT.sub("", text.replace("_", " "))
    return " ".join(text.lower().split())


def check_siglip_dir(model_dir: str | Path) -> list[str]:
    """Problems with a SigLIP text model directory (empty list = usable)."""
    d = Path(model_dir)
    if not d.is_dir():
        return [f"{d} is not a directory"]
    probs = []
    if not (d / "config.json").is_file():
        probs.append(f"{d / 'config.json'} missing")
    if not any((d / f).is_file() for f in ("model.safetensors", "pytorch_model.bin")):
        probs.append(f"{d / 'model.safetensors'} (or pytorch_model.bin) missing")
    if not any((d / f).is_file() for f in ("tokenizer.json", "spiece.model")):
        probs.append(f"{d / 'tokenizer.json'} (or spiece.model) missing")
    return probs


class SiglipText(CachedTextEncoder):
    """``SiglipText(model_dir, device).encode_labels(["car"], templates="imagenet80") -> (1, D)``."""

    name = "siglip"

    def __init__(self, model_dir: str | Path, device: str | torch.device = "cpu",
                 max_length: int | None = None, batch_size: int = 32, dtype: torch.dtype = torch.float32):
        super().__init__(device)
        probs = check_siglip_dir(model_dir)
        if probs:
            raise ModelFileError("SigLIP text model: " + "; ".join(probs))
        _quiet_transformers()
        AutoTokenizer, SiglipTextConfig, SiglipTextModel = transformers_names(
            "AutoTokenizer", "SiglipTextConfig", "SiglipTextModel")

        d = Path(model_dir)
        raw = json.loads((d / "config.json").read_text())
        if raw.get("model_type") == "siglip":  # a full SigLIP config: take its text part
            tcfg = SiglipTextConfig(**raw.get("text_config", {}))
        else:
            tcfg = SiglipTextConfig.from_pretrained(str(d), local_files_only=True)
        try:
            self.model = SiglipTextModel.from_pretrained(str(d), config=tcfg, local_files_only=True,
                                                         dtype=dtype)
            self.tokenizer = AutoTokenizer.from_pretrained(str(d), local_files_only=True)
        except (OSError, ValueError) as e:
            raise ModelFileError(f"SigLIP text model in {d} could not be loaded: {e}") from e
        self.model = self.model.to(self.device).eval()
        self.dim = int(tcfg.projection_size if getattr(tcfg, "projection_size", None) else tcfg.hidden_size)
        self.max_length = int(max_length or tcfg.max_position_embeddings)
        self.batch_size = int(batch_size)
        self.model_dir = d

    def _embed(self, texts: list[str]) -> torch.Tensor:
        outs = []
        for i in range(0, len(texts), self.batch_size):
            chunk = [canonicalize(t) for t in texts[i:i + self.batch_size]]
            b = self.tokenizer(chunk, padding="max_length", truncation=True, max_length=self.max_length,
                               return_tensors="pt")
            ids = b["input_ids"].to(self.device)
            pooled = self.model(input_ids=ids).pooler_output
            outs.append(torch.nn.functional.normalize(pooled.float(), dim=-1))
        return torch.cat(outs)
