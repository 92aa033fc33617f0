"""RADIO adaptor heads for language alignment.

The head module itself (:class:`~common.language_head.MLP2`) lives in ``common`` because the
mapper applies it at query time (features are averaged in RADIO/PCA space first, then
projected: docs/method.md#language-head). This module picks a teacher's summary head out of a checkpoint.
"""
from __future__ import annotations

import torch

from common.language_head import MLP2, MLP2Config  # noqa: F401  (re-export)
from encoders.radio import RadioCheckpoint


def summary_head(ckpt: RadioCheckpoint, adaptor: str = "siglip", device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32) -> MLP2:
    """The ``_heads.<adaptor>`` MLP2 of ``ckpt`` (looked up by teacher name, then index)."""
    sd = ckpt.head_for(adaptor)
    head = MLP2.from_state_dict(sd, device="cpu")
    return head.to(device=device, dtype=dtype).eval()


def summary_slot(ckpt: RadioCheckpoint, adaptor: str = "siglip", default: int = 1) -> int:
    """Class-token index of ``adaptor`` (its ``token_slot`` / teacher index), else ``default``."""
    return int(ckpt.config.teacher_slots.get(adaptor, default))
