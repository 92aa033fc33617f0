"""The text-encoder interface shared by the label encoder (edge) and the query side (mapper)."""
from __future__ import annotations

import threading
from typing import Protocol, Sequence

import torch

from encoders.text.templates import IMAGENET_TEMPLATES, SINGLE_TEMPLATE, fill

#: one import of transformers at a time: its lazy module is not thread-safe (a mapper's first
#: search and its text warm-up thread importing at once saw "cannot import name 'AutoModel'")
TRANSFORMERS_LOCK = threading.RLock()


def transformers_names(*names: str) -> tuple:
    """``names`` from the transformers package, imported under :data:`TRANSFORMERS_LOCK`."""
    with TRANSFORMERS_LOCK:
        import transformers

        return tuple(getattr(transformers, n) for n in names)


class TextEncoder(Protocol):
    """Embeds strings into an L2-normalised ``(Q, dim)`` float32 tensor on ``device``."""

    name: str  #: "minilm-l6" | "siglip"
    dim: int

    def encode(self, texts: Sequence[str]) -> torch.Tensor: ...

    def encode_labels(self, labels: Sequence[str], templates: str = "none") -> torch.Tensor: ...


#: environment variable naming a directory of text embeddings shared between processes
#: (see :class:`CachedTextEncoder`); unset or empty = no disk cache
ENV_TEXT_CACHE = "RAYFRONTS_TEXT_CACHE"
#: at most this many embeddings per model in the disk cache (beyond it nothing new is written)
DISK_CACHE_MAX = 20_000


class CachedTextEncoder:
    """Base with a per-string embedding cache and template averaging.

    Subclasses implement ``_embed(list[str]) -> (n, dim)`` (L2-normalised rows).

    Disk cache (opt-in): with ``RAYFRONTS_TEXT_CACHE=DIR`` and a subclass that names its
    model's identity in ``cache_id`` (name + the weight file's size and mtime), each string's
    embedding is also kept in ``DIR/<cache_id>/<sha1 of the string>.npy`` (float32, written
    atomically, at most :data:`DISK_CACHE_MAX` per model), so processes that start often
    (edges embedding their class names, mappers embedding queries, the test suite) read
    them back instead of loading the model; a subclass may then load its model lazily, on
    the first string the cache does not hold. Reads are exact (the stored float32 row).
    """

    #: model identity for the disk cache; None = this encoder is never disk-cached
    cache_id: str | None = None

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
            found = self._disk_get(todo)
            if len(self._cache) + len(todo) > self._cache_size:
                self._cache.clear()
            self._cache.update(found)
            todo = [t for t in todo if t not in found]
        if todo:
            emb = self._embed(todo).float()
            for t, e in zip(todo, emb, strict=False):
                self._cache[t] = e.detach()
            self._disk_put({t: self._cache[t] for t in todo})
        if not texts:
            return torch.zeros(0, self.dim, device=self.device)
        return torch.stack([self._cache[t] for t in texts]).to(self.device)

    def _disk_dir(self):
        import os
        from pathlib import Path

        root = os.environ.get(ENV_TEXT_CACHE, "")
        if not root or not self.cache_id:
            return None
        return Path(root).expanduser() / self.cache_id

    @staticmethod
    def _disk_name(text: str) -> str:
        import hashlib

        return hashlib.sha1(text.encode("utf-8")).hexdigest() + ".npy"

    def _disk_get(self, texts: list[str]) -> dict[str, torch.Tensor]:
        d = self._disk_dir()
        if d is None or not d.is_dir():
            return {}
        import numpy as np

        out = {}
        for t in texts:
            try:
                v = np.load(d / self._disk_name(t), allow_pickle=False)
            except (OSError, ValueError):
                continue
            if v.dtype == np.float32 and v.shape == (self.dim,):
                out[t] = torch.from_numpy(v).to(self.device)
        return out

    def _disk_put(self, rows: dict[str, torch.Tensor]) -> None:
        d = self._disk_dir()
        if d is None or not rows:
            return
        import os

        import numpy as np

        try:
            d.mkdir(parents=True, exist_ok=True)
            if sum(1 for _ in d.iterdir()) + len(rows) > DISK_CACHE_MAX:
                return
            for t, e in rows.items():
                tmp = d / f".{os.getpid()}-{self._disk_name(t)}"
                with open(tmp, "wb") as f:
                    np.save(f, e.detach().float().cpu().numpy(), allow_pickle=False)
                os.replace(tmp, d / self._disk_name(t))
        except OSError:  # a read-only or full cache directory only costs the model load next time
            pass

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
