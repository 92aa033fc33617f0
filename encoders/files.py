"""Where model files are looked for (nothing is ever downloaded at run time).

A model directory (``$RAYFRONTS_MODEL_DIR``, default ``~/.cache/rayfronts/models``) holds::

    radio_v2.5-b.safetensors (+ .json)   our flat layout   (rayfronts models convert)
    radio-v2.5-b_half.pth.tar            or the published RADIO file, as downloaded
    siglip_text/                         SigLIP text tower + tokenizer (mapper side)

The torch hub checkpoint cache (``<torch hub dir>/checkpoints``) is searched too, so a
RADIO file fetched earlier by ``torch.hub`` on this machine is found.
"""
from __future__ import annotations

import os
from pathlib import Path

from common.model_files import ModelFileError

#: published RADIO file names per model.
PUBLISHED_NAMES = {"radio_v2.5-b": "radio-v2.5-b_half.pth.tar", "radio_v2.5-l": "radio-v2.5-l_half.pth.tar"}
PUBLISHED_URLS = {m: f"https://huggingface.co/nvidia/RADIO/resolve/main/{n}" for m, n in PUBLISHED_NAMES.items()}
SIGLIP_TEXT_DIR = "siglip_text"


def default_model_dir() -> Path:
    return Path(os.environ.get("RAYFRONTS_MODEL_DIR", Path.home() / ".cache" / "rayfronts" / "models")).expanduser()


def _hub_checkpoints() -> Path | None:
    try:
        import torch.hub
        return Path(torch.hub.get_dir()) / "checkpoints"
    except Exception:  # pragma: no cover
        return None


def radio_candidates(model: str, model_dir: str | Path | None = None) -> list[Path]:
    """Files tried, in order, for RADIO ``model`` (e.g. ``radio_v2.5-b``)."""
    d = Path(model_dir).expanduser() if model_dir else default_model_dir()
    pub = PUBLISHED_NAMES.get(model, f"{model.replace('_', '-')}_half.pth.tar")
    c = [d / f"{model}.safetensors", d / model / "model.safetensors", d / pub, d / f"{model}.pth.tar"]
    hub = _hub_checkpoints()
    if hub is not None:
        c.append(hub / pub)
    return c


def find_radio_checkpoint(model: str, model_dir: str | Path | None = None, checkpoint: str | Path = "") -> Path:
    """The checkpoint file to use; :class:`ModelFileError` naming every path tried."""
    if checkpoint:
        p = Path(checkpoint).expanduser()
        if not p.is_file():
            raise ModelFileError(f"RADIO checkpoint not found: {p}")
        return p
    if model == "auto":
        raise ModelFileError("encoder.model=auto needs an explicit encoder.checkpoint file")
    cands = radio_candidates(model, model_dir)
    for p in cands:
        if p.is_file():
            return p
    raise ModelFileError(f"no RADIO checkpoint for {model}; looked for: " + ", ".join(map(str, cands))
                         + f". Get {PUBLISHED_URLS.get(model, 'the RADIO file')} on a machine with internet "
                           "(see 'rayfronts models download --help') and copy it there.")
