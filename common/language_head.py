"""Language heads: small MLPs that map vision features into a text model's embedding space.

:class:`MLP2` has the parameter names of RADIO's ``mlp_version='v2'`` adaptor heads, so the
``_heads.<teacher>.*`` tensors of a RADIO checkpoint load into it strictly::

    [pre_norm: LayerNorm, GELU]  (optional)
    fc1: Linear(in -> hidden)
    num_inner x residual [LayerNorm, GELU, Linear(hidden -> hidden)]   (blocks.i.{0,2})
    final: [LayerNorm, GELU, Linear(hidden -> out)]                    (final.{0,2})

It works on the last dimension, so it can be applied token-wise to spatial features
(``(..., in)``). It lives in ``common`` because both the edge (which owns the checkpoint)
and the mapper (which applies the head at query time, after averaging) need it.
"""
from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

from common.model_files import ModelFileError


@dataclass(frozen=True)
class MLP2Config:
    """Dimensions of an :class:`MLP2` head (all read from weight shapes)."""

    in_dim: int
    hidden_dim: int
    out_dim: int
    num_inner: int = 0
    pre_norm: bool = False
    ln_eps: float = 1e-5

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "MLP2Config":
        try:
            return cls(in_dim=int(d["in_dim"]), hidden_dim=int(d["hidden_dim"]), out_dim=int(d["out_dim"]),
                       num_inner=int(d.get("num_inner", 0)), pre_norm=bool(d.get("pre_norm", False)),
                       ln_eps=float(d.get("ln_eps", 1e-5)))
        except KeyError as e:
            raise ValueError(f"MLP2 head config lacks {e}; got keys {sorted(d)}") from None

    @classmethod
    def from_state_dict(cls, sd: dict) -> "MLP2Config":
        """Infer the dimensions from the tensors of an MLP2 state dict."""
        need = ["fc1.weight", "final.2.weight"]
        missing = [k for k in need if k not in sd]
        if missing:
            raise ModelFileError(f"not an MLP2 head state dict: missing {missing}; keys: {sorted(sd)[:12]}")
        hidden, in_dim = sd["fc1.weight"].shape
        out_dim = sd["final.2.weight"].shape[0]
        inner = {int(m.group(1)) for k in sd if (m := re.match(r"blocks\.(\d+)\.", k))}
        num_inner = (max(inner) + 1) if inner else 0
        return cls(int(in_dim), int(hidden), int(out_dim), num_inner, "pre_norm.0.weight" in sd)


class MLP2(nn.Module):
    """RADIO v2 MLP head (see module docstring); ``forward`` maps ``(..., in_dim) -> (..., out_dim)``."""

    def __init__(self, cfg: MLP2Config, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32):
        super().__init__()
        self.cfg = cfg
        fk: dict[str, Any] = dict(device=device, dtype=dtype)
        self.pre_norm = (nn.Sequential(nn.LayerNorm(cfg.in_dim, eps=cfg.ln_eps, **fk), nn.GELU())
                         if cfg.pre_norm else nn.Identity())
        self.fc1 = nn.Linear(cfg.in_dim, cfg.hidden_dim, **fk)
        self.blocks = nn.ModuleList([
            nn.Sequential(nn.LayerNorm(cfg.hidden_dim, eps=cfg.ln_eps, **fk), nn.GELU(),
                          nn.Linear(cfg.hidden_dim, cfg.hidden_dim, **fk))
            for _ in range(cfg.num_inner)])
        self.final = nn.Sequential(nn.LayerNorm(cfg.hidden_dim, eps=cfg.ln_eps, **fk), nn.GELU(),
                                   nn.Linear(cfg.hidden_dim, cfg.out_dim, **fk))

    @property
    def in_dim(self) -> int:
        return self.cfg.in_dim

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.cfg.in_dim:
            raise ValueError(f"MLP2 head expects (..., {self.cfg.in_dim}) input, got {tuple(x.shape)}")
        x = self.fc1(self.pre_norm(x))
        for blk in self.blocks:
            x = x + blk(x)
        return self.final(x)

    @classmethod
    def from_state_dict(cls, sd: dict, device: str | torch.device = "cpu",
                        dtype: torch.dtype = torch.float32, cfg: MLP2Config | None = None) -> "MLP2":
        """Build a head whose dimensions come from ``sd`` (or ``cfg``) and load ``sd`` strictly."""
        cfg = cfg or MLP2Config.from_state_dict(sd)
        head = cls(cfg, device=device, dtype=dtype)
        load_strict(head, sd, what="MLP2 language head")
        head.eval()
        return head


def load_strict(module: nn.Module, sd: dict, what: str, source: str = "") -> None:
    """``load_state_dict(strict=True)`` with one clear :class:`ModelFileError` listing missing,
    unexpected and wrongly shaped keys (instead of torch's multi-line RuntimeError)."""
    own = module.state_dict()
    missing = sorted(k for k in own if k not in sd)
    unexpected = sorted(k for k in sd if k not in own)
    wrong = sorted(f"{k}: file {tuple(sd[k].shape)} vs model {tuple(own[k].shape)}"
                   for k in own if k in sd and tuple(sd[k].shape) != tuple(own[k].shape))
    if missing or unexpected or wrong:
        where = f" from {source}" if source else ""
        parts = []
        if missing:
            parts.append(f"missing keys ({len(missing)}): {_short(missing)}")
        if unexpected:
            parts.append(f"unexpected keys ({len(unexpected)}): {_short(unexpected)}")
        if wrong:
            parts.append(f"wrong shapes ({len(wrong)}): {_short(wrong)}")
        raise ModelFileError(f"{what}{where} does not match the model: " + "; ".join(parts))
    module.load_state_dict({k: v for k, v in sd.items()}, strict=True)


def _short(items: list[str], n: int = 8) -> str:
    s = ", ".join(items[:n])
    return s + (f", ... (+{len(items) - n} more)" if len(items) > n else "")
