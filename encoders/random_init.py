"""Random-weight RADIO checkpoints (benchmarks and tests; no real weights exist offline)."""
from __future__ import annotations

import torch

from common.language_head import MLP2, MLP2Config
from encoders.radio import RadioCheckpoint, RadioConfig, RadioModel


def random_checkpoint(rc: RadioConfig, head_hidden: int = 1520, head_out: int = 1152, head_inner: int = 1,
                      seed: int = 0, adaptor: str = "siglip") -> RadioCheckpoint:
    """A :class:`RadioCheckpoint` with N(0, 0.02) weights, unit LayerNorms, CLIP conditioner
    and a random MLP2 summary head for ``adaptor`` (default dims: SigLIP-SO400M out 1152,
    hidden 1520 guessed)."""
    g = torch.Generator().manual_seed(seed)
    model = RadioModel(rc)
    sd = {}
    for k, v in model.state_dict().items():
        if k.startswith("input_conditioner.") or k.startswith("feature_normalizer."):
            sd[k] = v.clone()
        elif k.endswith(".weight") and v.ndim == 1 or k.endswith("gamma"):
            sd[k] = torch.ones_like(v)
        elif k.endswith(".bias"):
            sd[k] = torch.zeros_like(v)
        else:
            sd[k] = torch.randn(v.shape, generator=g) * 0.02
    head = MLP2(MLP2Config(rc.embed_dim, head_hidden, head_out, head_inner))
    hsd = {k: (torch.randn(v.shape, generator=g) * 0.02 if v.ndim == 2 else
               (torch.ones_like(v) if "weight" in k else torch.zeros_like(v)))
           for k, v in head.state_dict().items()}
    idx = str(rc.teacher_names.index(adaptor)) if adaptor in rc.teacher_names else adaptor
    return RadioCheckpoint(rc, sd, {idx: hsd}, {}, path=f"<random seed {seed}>")
