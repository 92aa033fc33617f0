"""NACLIP attention for the last ViT block (Hajimiri et al., WACV 2025), as used by NARADIO.

For the last block's tokens, per head::

    logits = K·Kᵀ · head_dim^-½ + Ω          (key-key similarity; queries unused)
    out    = proj(softmax(logits) · V)

with the neighbourhood bias, for patch tokens i, j at (row, col) on the h×w patch grid
(tokens row-major over (h, w), after the ``n_prefix`` prefix tokens)::

    Ω[i, j] = exp(−((r_i − r_j)² + (c_i − c_j)²) / (2σ²))      (peak 1, not normalised)

and Ω = 0 on prefix-token rows and columns. Unlike RayFronts' NARADIO, the grid is built
with the correct (height, width) orientation for non-square inputs, and the patch size is
the model's. The block's residual, layer scale and MLP are kept (RayFronts); NACLIP's own
"reduced" block (attention branch only) is an option.
"""
from __future__ import annotations

from typing import Any, cast

import torch
from torch import nn

from encoders.radio import Attention, Block


def gaussian_bias(h: int, w: int, sigma: float, n_prefix: int = 0, device: str | torch.device = "cpu",
                  dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Ω as an ``(n_prefix + h·w, n_prefix + h·w)`` additive attention bias (see module doc)."""
    if h < 1 or w < 1:
        raise ValueError(f"patch grid must be at least 1x1, got {h}x{w}")
    if not sigma > 0:
        raise ValueError(f"gauss_std must be > 0, got {sigma}")
    idx = torch.arange(h * w, device=device)
    r = (idx // w).to(torch.float64)
    c = (idx % w).to(torch.float64)
    d2 = (r[:, None] - r[None, :]) ** 2 + (c[:, None] - c[None, :]) ** 2
    g = torch.exp(-d2 / (2.0 * float(sigma) ** 2))
    n = n_prefix + h * w
    out = torch.zeros(n, n, dtype=torch.float64, device=device)
    out[n_prefix:, n_prefix:] = g
    return out.to(dtype)


class NaclipAttention(nn.Module):
    """Key-key attention with the Gaussian neighbourhood bias; reuses an :class:`Attention`'s
    ``qkv`` and ``proj`` (shared parameters, not copies). Needs ``grid_hw`` at call time."""

    def __init__(self, attn: Attention, n_prefix: int, gauss_std: float = 7.0, use_gaussian: bool = True):
        super().__init__()
        self.inner = attn
        self.n_prefix = int(n_prefix)
        self.gauss_std = float(gauss_std)
        self.use_gaussian = bool(use_gaussian)
        self._bias_key: tuple | None = None
        self._bias: torch.Tensor | None = None

    def bias(self, hw: tuple[int, int], device: str | torch.device, dtype: torch.dtype) -> torch.Tensor:
        """The Gaussian bias for an ``hw`` patch grid (cached for the last grid, device and dtype)."""
        key = (tuple(hw), str(device), dtype)
        if self._bias_key != key:
            self._bias = gaussian_bias(hw[0], hw[1], self.gauss_std, self.n_prefix, device, dtype)
            self._bias_key = key
        assert self._bias is not None
        return self._bias

    def forward(self, x: torch.Tensor, grid_hw: tuple[int, int] | None = None, **kwargs: Any) -> torch.Tensor:
        a = self.inner
        _, k, v = a.split_qkv(x)
        mask = None
        if self.use_gaussian:
            if grid_hw is None:
                raise ValueError("NACLIP attention needs the patch grid size (grid_hw)")
            if self.n_prefix + grid_hw[0] * grid_hw[1] != x.shape[1]:
                raise ValueError(f"{x.shape[1]} tokens != {self.n_prefix} prefix + grid {grid_hw}")
            mask = self.bias(grid_hw, x.device, k.dtype)
        o = torch.nn.functional.scaled_dot_product_attention(k, k, v, attn_mask=mask)
        return a.merge(o)


class NaclipBlock(nn.Module):
    """A view of a RADIO :class:`Block` whose attention is NACLIP's (parameters shared).

    ``reduced=False`` (RayFronts): ``x + ls1(attn(norm1 x))`` then the usual MLP residual.
    ``reduced=True`` (NACLIP): ``ls1(attn(norm1 x))`` only.
    """

    def __init__(self, block: Block, n_prefix: int, gauss_std: float = 7.0, reduced: bool = False,
                 use_gaussian: bool = True):
        super().__init__()
        self.block = block
        self.attn = NaclipAttention(cast(Attention, block.attn), n_prefix, gauss_std, use_gaussian)
        self.reduced = bool(reduced)

    def forward(self, x: torch.Tensor, grid_hw: tuple[int, int] | None = None) -> torch.Tensor:
        b = self.block
        a = b.ls1(self.attn(b.norm1(x), grid_hw=grid_hw))
        if self.reduced:
            return a
        x = x + a
        return x + b.ls2(b.mlp(b.norm2(x)))
