"""RADIO v2.5 backbone in plain torch, with parameter names that load published checkpoints.

Module tree (names = checkpoint keys)::

    RadioModel
      input_conditioner.norm_mean / norm_std         (3, 1, 1) buffers, CLIP mean/std
      base_model.patch_generator.embedder.weight     Linear(3·p·p -> D, no bias) over (c, y, x)
      base_model.patch_generator.pos_embed           (1, G·G, D)   G = cpe_max_size / p (128)
      base_model.patch_generator.cls_token.token     (T, D)  T = class tokens + registers (8)
      base_model.blocks.N.{norm1, attn.qkv, attn.proj, [ls1.gamma], norm2, mlp.fc1, mlp.fc2, [ls2.gamma]}
      base_model.norm                                LayerNorm only if args.model_norm
      feature_normalizer.{mean, tx}                  optional (``_feature_normalizer.*`` in files)

Conventions: input images are float RGB in [0, 1], (B, 3, H, W) with H, W multiples of the
patch size p; tokens are row-major over the (H/p, W/p) patch grid and preceded by the T
prefix tokens. CPE at inference: the G×G position table is resized bilinearly
(align_corners=False) to (max(h, w))² and its top-left h×w window is used.

Checkpoints: RADIO's ``{'args': Namespace, 'state_dict' | 'state_dict_ema': {...}}`` files
(see :func:`read_checkpoint`), or our flat layout (a safetensors file with the same key
names and the architecture as JSON metadata, written by ``rayfronts models convert``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from common.language_head import load_strict
from common.model_files import ModelFileError

log = logging.getLogger(__name__)

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)

#: timm ViT names -> (embed_dim, depth, num_heads) (what RADIO v2.5 b/l/h are built from).
TIMM_VITS = {
    "vit_base_patch16_224": (768, 12, 12),
    "vit_large_patch16_224": (1024, 24, 16),
    "vit_huge_patch16_224": (1280, 32, 16),
}
#: our model names -> timm arch (RADIO v2.5 b / l; patch 16, cpe_max_size 2048).
PRESETS = {"radio_v2.5-b": "vit_base_patch16_224", "radio_v2.5-l": "vit_large_patch16_224",
           "radio_v2.5-h": "vit_huge_patch16_224"}
FLAT_META_KEY = "rayfronts.radio_config"


@dataclass
class RadioConfig:
    """Architecture of a RADIO ViT; :meth:`preset` for v2.5 b/l, any size for tests."""

    embed_dim: int = 768                #: token width
    depth: int = 12                     #: transformer blocks
    num_heads: int = 12                 #: attention heads per block
    patch_size: int = 16                #: pixels per patch side
    pos_grid: int = 128                 #: side of the CPE table (cpe_max_size / patch)
    num_cls_tokens: int = 4             #: one class token per unique teacher
    num_registers: int = 4
    mlp_hidden: int = 3072
    qkv_bias: bool = True
    layer_scale: bool = False
    model_norm: bool = False
    ln_eps: float = 1e-6
    feature_normalizer: bool = False
    summary_idxs: list[int] = field(default_factory=lambda: [0, 1, 2])
    teacher_names: list[str] = field(default_factory=lambda: ["clip", "siglip", "dino_v2", "sam"])
    teacher_slots: dict[str, int] = field(default_factory=lambda: {"clip": 0, "siglip": 1, "dino_v2": 2, "sam": 3})
    arch: str = "vit_base_patch16_224"

    @property
    def num_prefix(self) -> int:
        return self.num_cls_tokens + self.num_registers

    @classmethod
    def preset(cls, name: str) -> "RadioConfig":
        if name not in PRESETS:
            raise ValueError(f"unknown RADIO model {name!r}; known: {sorted(PRESETS)}")
        arch = PRESETS[name]
        d, depth, heads = TIMM_VITS[arch]
        return cls(embed_dim=d, depth=depth, num_heads=heads, mlp_hidden=4 * d, arch=arch)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "RadioConfig":
        known = set(cls.__dataclass_fields__)
        extra = set(d) - known
        if extra:
            raise ModelFileError(f"RADIO config has unknown fields {sorted(extra)}")
        return cls(**d)

    @classmethod
    def from_args(cls, args: argparse.Namespace | dict, sd: dict[str, torch.Tensor]) -> "RadioConfig":
        """Architecture from a RADIO checkpoint's ``args`` Namespace plus its tensor shapes."""
        a = vars(args) if isinstance(args, argparse.Namespace) else dict(args)
        arch = a.get("model", "vit_base_patch16_224")
        kw = dict(a.get("model_kwargs") or {})
        d0, depth0, heads0 = TIMM_VITS.get(arch, (None, None, None))
        if "base_model.patch_generator.embedder.weight" not in sd:
            raise ModelFileError("checkpoint has no 'base_model.patch_generator.embedder.weight' "
                                 "(not a RADIO checkpoint with CPE)")
        emb = sd["base_model.patch_generator.embedder.weight"]
        D = int(emb.shape[0])
        p = int(round(math.sqrt(emb.shape[1] / 3)))
        depth = 1 + max(int(m.group(1)) for k in sd if (m := re.match(r"base_model\.blocks\.(\d+)\.", k)))
        heads = kw.get("num_heads", heads0 if d0 == D else None)
        if heads is None:
            heads = max(1, D // 64)
            log.warning("RADIO arch %r unknown: assuming %d heads (head dim 64)", arch, heads)
        n_pos = sd["base_model.patch_generator.pos_embed"].shape[1]
        grid = int(round(math.sqrt(n_pos)))
        if grid * grid != n_pos:
            raise ModelFileError(f"pos_embed has {n_pos} positions, not a square grid")
        n_tok = int(sd["base_model.patch_generator.cls_token.token"].shape[0])
        teachers = list(a.get("teachers") or [])
        names = [t.get("name", f"t{i}") for i, t in enumerate(teachers)]
        per_teacher = a.get("cls_token_per_teacher", True)
        if per_teacher and teachers:
            n_cls = len(dict.fromkeys(names))
            first: dict[str, int] = {}
            for i, t in enumerate(teachers):
                if t.get("use_summary", True) and t["name"] not in first:
                    first[t["name"]] = i
            summary_idxs = sorted(first.values())
        else:
            n_cls, summary_idxs = 1, [0]
        slots: dict[str, int] = {}
        for i, t in enumerate(teachers):
            slots.setdefault(names[i], int(t.get("token_slot", i)) if per_teacher else 0)
        if n_cls > n_tok:
            raise ModelFileError(f"args list {n_cls} class tokens but cls_token.token has {n_tok} rows")
        fc1 = "base_model.blocks.0.mlp.fc1.weight"
        mlp_hidden = int(sd[fc1].shape[0]) if fc1 in sd else 4 * D
        return cls(embed_dim=D, depth=depth, num_heads=int(heads), patch_size=p, pos_grid=grid,
                   num_cls_tokens=n_cls, num_registers=n_tok - n_cls, mlp_hidden=mlp_hidden,
                   qkv_bias="base_model.blocks.0.attn.qkv.bias" in sd,
                   layer_scale="base_model.blocks.0.ls1.gamma" in sd,
                   model_norm="base_model.norm.weight" in sd,
                   feature_normalizer="_feature_normalizer.mean" in sd,
                   summary_idxs=summary_idxs, teacher_names=names, teacher_slots=slots, arch=str(arch))


# ------------------------------------------------------------------------------ modules
class InputConditioner(nn.Module):
    """``(x − mean) / std`` on [0, 1] RGB (CLIP statistics by default, from the checkpoint)."""

    norm_mean: torch.Tensor
    norm_std: torch.Tensor

    def __init__(self):
        super().__init__()
        self.register_buffer("norm_mean", torch.tensor(CLIP_MEAN).view(3, 1, 1))
        self.register_buffer("norm_std", torch.tensor(CLIP_STD).view(3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.norm_mean) / self.norm_std


class ClsToken(nn.Module):
    def __init__(self, n: int, dim: int):
        super().__init__()
        self.token = nn.Parameter(torch.zeros(n, dim))


class PatchGenerator(nn.Module):
    """Patchify + linear embed + CPE position table + prefix tokens."""

    def __init__(self, cfg: RadioConfig):
        super().__init__()
        p, D = cfg.patch_size, cfg.embed_dim
        self.patch_size = p
        self.grid = cfg.pos_grid
        self.embedder = nn.Linear(3 * p * p, D, bias=False)
        self.pos_embed = nn.Parameter(torch.zeros(1, cfg.pos_grid ** 2, D))
        self.cls_token = ClsToken(cfg.num_prefix, D)

    def pos_enc(self, h: int, w: int) -> torch.Tensor:
        """CPE position embeddings for an h×w patch grid: ``(1, h·w, D)``."""
        G = self.grid
        if (h, w) == (G, G):
            return self.pos_embed
        if max(h, w) > G:
            log.debug("input grid %dx%d exceeds CPE table %d: upsampling", h, w, G)
        pe = self.pos_embed.reshape(1, G, G, -1).permute(0, 3, 1, 2)
        s = max(h, w)
        pe = torch.nn.functional.interpolate(pe.float(), size=(s, s), mode="bilinear", align_corners=False).to(pe.dtype)
        pe = pe[:, :, :h, :w]
        return pe.flatten(2).transpose(1, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, C, H, W = x.shape
        p = self.patch_size
        h, w = H // p, W // p
        # b c (h y) (w x) -> b (h w) (c y x)
        patches = x.reshape(B, C, h, p, w, p).permute(0, 2, 4, 1, 3, 5).reshape(B, h * w, C * p * p)
        tok = self.embedder(patches) + self.pos_enc(h, w).to(patches.dtype)
        prefix = self.cls_token.token.unsqueeze(0).expand(B, -1, -1).to(tok.dtype)
        return torch.cat([prefix, tok], dim=1)


class Attention(nn.Module):
    """timm-style multi-head self-attention (fused qkv, SDPA)."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"embed dim {dim} not divisible by {num_heads} heads")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.scale = self.head_dim ** -0.5
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def split_qkv(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        return qkv[0], qkv[1], qkv[2]  # (B, heads, N, hd)

    def merge(self, o: torch.Tensor) -> torch.Tensor:
        B, _, N, _ = o.shape
        return self.proj(o.transpose(1, 2).reshape(B, N, -1))

    def forward(self, x: torch.Tensor, **kwargs: Any) -> torch.Tensor:  # extra kwargs (grid size) ignored
        q, k, v = self.split_qkv(x)
        return self.merge(torch.nn.functional.scaled_dot_product_attention(q, k, v))


class LayerScale(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block (timm ViT names); extra attention kwargs are passed through."""

    def __init__(self, cfg: RadioConfig):
        super().__init__()
        D = cfg.embed_dim
        self.norm1 = nn.LayerNorm(D, eps=cfg.ln_eps)
        self.attn: nn.Module = Attention(D, cfg.num_heads, cfg.qkv_bias)
        self.ls1 = LayerScale(D) if cfg.layer_scale else nn.Identity()
        self.norm2 = nn.LayerNorm(D, eps=cfg.ln_eps)
        self.mlp = Mlp(D, cfg.mlp_hidden)
        self.ls2 = LayerScale(D) if cfg.layer_scale else nn.Identity()

    def forward(self, x: torch.Tensor, grid_hw: tuple[int, int] | None = None) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), grid_hw=grid_hw))
        return x + self.ls2(self.mlp(self.norm2(x)))


class RadioViT(nn.Module):
    def __init__(self, cfg: RadioConfig):
        super().__init__()
        self.cfg = cfg
        self.patch_generator = PatchGenerator(cfg)
        self.blocks = nn.ModuleList([Block(cfg) for _ in range(cfg.depth)])
        self.norm = nn.LayerNorm(cfg.embed_dim, eps=cfg.ln_eps) if cfg.model_norm else nn.Identity()

    def forward(self, x: torch.Tensor, last_block: nn.Module | None = None) -> torch.Tensor:
        """Tokens ``(B, T + h·w, D)``; ``last_block`` replaces the final block if given."""
        p = self.cfg.patch_size
        hw = (x.shape[-2] // p, x.shape[-1] // p)
        t = self.patch_generator(x)
        n = len(self.blocks)
        for i, blk in enumerate(self.blocks):
            t = (last_block if (i == n - 1 and last_block is not None) else blk)(t, grid_hw=hw)
        return self.norm(t)


class FeatureNormalizer(nn.Module):
    """Optional RADIO feature normaliser: ``(x − mean) · txᵀ``."""

    mean: torch.Tensor
    tx: torch.Tensor

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("tx", torch.eye(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) @ self.tx.T


@dataclass
class RadioOutput:
    summary: torch.Tensor      #: (B, len(summary_idxs)·D) concatenated teacher class tokens
    cls_tokens: torch.Tensor   #: (B, num_cls_tokens, D) all class tokens (registers excluded)
    features: torch.Tensor     #: (B, D, h, w) spatial features (registers/class tokens removed)


class RadioModel(nn.Module):
    """Input conditioner + ViT (+ feature normaliser); ``forward(x in [0,1]) -> RadioOutput``."""

    def __init__(self, cfg: RadioConfig):
        super().__init__()
        self.cfg = cfg
        self.input_conditioner = InputConditioner()
        self.base_model = RadioViT(cfg)
        self.feature_normalizer = FeatureNormalizer(cfg.embed_dim) if cfg.feature_normalizer else None
        self.normalize_input = True

    @property
    def patch_size(self) -> int:
        return self.cfg.patch_size

    def split(self, tokens: torch.Tensor, hw: tuple[int, int]) -> RadioOutput:
        c = self.cfg
        cls = tokens[:, : c.num_cls_tokens]
        summary = cls[:, c.summary_idxs].flatten(1)
        feat = tokens[:, c.num_prefix:]
        if self.feature_normalizer is not None:
            feat = self.feature_normalizer(feat)
        B, N, D = feat.shape
        if N != hw[0] * hw[1]:
            raise RuntimeError(f"token count {N} != grid {hw}")
        return RadioOutput(summary, cls, feat.transpose(1, 2).reshape(B, D, hw[0], hw[1]))

    def forward(self, x: torch.Tensor, last_block: nn.Module | None = None) -> RadioOutput:
        p = self.cfg.patch_size
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"RADIO expects (B, 3, H, W), got {tuple(x.shape)}")
        if x.shape[-2] % p or x.shape[-1] % p:
            raise ValueError(f"input H, W {tuple(x.shape[-2:])} must be multiples of the patch size {p}")
        if self.normalize_input:
            x = self.input_conditioner(x)
        tokens = self.base_model(x, last_block=last_block)
        return self.split(tokens, (x.shape[-2] // p, x.shape[-1] // p))


# ------------------------------------------------------------------------------ loading
@dataclass
class RadioCheckpoint:
    """What a checkpoint file holds, with spectral re-parametrisation already realised."""

    config: RadioConfig
    model_state: dict[str, torch.Tensor]           #: keys of :class:`RadioModel`
    heads: dict[str, dict[str, torch.Tensor]]      #: '_heads.<idx|name>' -> MLP2 state dict
    feature_projections: dict[str, dict[str, torch.Tensor]]
    path: str = ""

    def head_for(self, adaptor: str) -> dict[str, torch.Tensor]:
        """State dict of the summary head of teacher ``adaptor`` (by name, else by its index)."""
        if adaptor in self.heads:
            return self.heads[adaptor]
        names = self.config.teacher_names
        if adaptor in names and str(names.index(adaptor)) in self.heads:
            return self.heads[str(names.index(adaptor))]
        raise ModelFileError(f"checkpoint {self.path} has no summary head for adaptor {adaptor!r}; "
                             f"heads present: {sorted(self.heads)} (teachers {names})")

    def weights_hash(self) -> str:
        """Short content hash (names, shapes, a strided sample of every tensor) for versioning."""
        h = hashlib.sha256(json.dumps(self.config.to_dict(), sort_keys=True).encode())
        for k in sorted(self.model_state):
            t = self.model_state[k]
            h.update(f"{k}{tuple(t.shape)}".encode())
            flat = t.detach().reshape(-1)
            step = max(1, flat.numel() // 64)
            h.update(flat[::step][:64].float().cpu().numpy().tobytes())
        return h.hexdigest()[:8]


def realize_spectral_reparam(sd: dict[str, torch.Tensor], eps: float = 1e-6) -> dict[str, torch.Tensor]:
    """Replace spectral re-parametrisations by plain weights.

    For ``X.parametrizations.weight.original`` = W with ``_u``, ``_v``, ``scale`` (and
    ``_sn_version``) under ``X.parametrizations.weight.0.`` (or ``.0.parts.{i}.`` per row-chunk
    for fused ``qkv``; a chunk without entries is left unscaled):
    ``W' = W · s' / (uᵀ W v + eps)`` with ``s' = softplus(scale) + 0.05`` (version 2) or
    ``s' = scale`` (version 1, also when ``_sn_version`` is absent).
    """
    out: dict[str, torch.Tensor] = {}
    done = set()
    for k, w in sd.items():
        m = re.match(r"^(.*)\.parametrizations\.weight\.original$", k)
        if not m:
            continue
        base = m.group(1)
        pre = f"{base}.parametrizations.weight.0."
        W = w.float()

        def reweight(Wc: torch.Tensor, p: str) -> torch.Tensor:
            if p + "_u" not in sd:
                return Wc
            u, v, s = sd[p + "_u"].float(), sd[p + "_v"].float(), sd[p + "scale"].float().reshape(-1)[0]
            ver = int(sd[p + "_sn_version"]) if p + "_sn_version" in sd else 1
            sigma = torch.dot(u, Wc.reshape(Wc.shape[0], -1) @ v) + eps
            scale = (torch.nn.functional.softplus(s) + 0.05) if ver == 2 else s
            return Wc * (scale / sigma)

        parts = sorted({int(mm.group(1)) for kk in sd if (mm := re.match(re.escape(pre) + r"parts\.(\d+)\.", kk))})
        if parts:
            n_chunks = 3 if base.endswith("qkv") else max(parts) + 1
            chunks = W.split(W.shape[0] // n_chunks, dim=0)
            W2 = torch.cat([reweight(c, f"{pre}parts.{i}.") for i, c in enumerate(chunks)], 0)
        else:
            W2 = reweight(W, pre)
        out[f"{base}.weight"] = W2.to(w.dtype)
        done.add(base)
    for k, v in sd.items():
        if ".parametrizations." in k:
            b = k.split(".parametrizations.")[0]
            if b in done:
                continue
            raise ModelFileError(f"spectral parametrisation entry {k} has no '.original' weight")
        out[k] = v
    return out


def _torch_load(path: Path):
    """Load a RADIO ``.pth.tar``: first with ``weights_only=True`` allowing ``argparse.Namespace``;
    if the file pickles more than that, fall back to ``weights_only=False`` (the file is one the
    user configured explicitly)."""
    try:
        with torch.serialization.safe_globals([argparse.Namespace]):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as e:  # UnpicklingError for other globals, or mmap unsupported
        log.warning("checkpoint %s needs full unpickling (%s); loading with weights_only=False", path,
                    str(e).splitlines()[0][:120])
        return torch.load(path, map_location="cpu", weights_only=False)


def read_checkpoint(path: str | Path) -> RadioCheckpoint:
    """Read a RADIO checkpoint (published layout, flat safetensors, or flat .pt + json)."""
    p = Path(path)
    if not p.is_file():
        raise ModelFileError(f"RADIO checkpoint not found: {p}")
    args: Any = None                     # the published layout's argparse Namespace (or dict)
    cfg: RadioConfig | None
    if p.suffix == ".safetensors":
        sd, cfg = _read_safetensors(p)
    else:
        sd, cfg, args = _read_torch_checkpoint(p)
    sd = realize_spectral_reparam(dict(sd))
    sd = {re.sub(r"\.(ls[12])\.grandma$", r".\1.gamma", k): v for k, v in sd.items()}
    if cfg is None:
        cfg = RadioConfig.from_args(args, sd)
    model_state, heads, projs = _split_state(sd)
    return RadioCheckpoint(cfg, model_state, heads, projs, str(p))


def _read_safetensors(p: Path) -> tuple[dict[str, torch.Tensor], RadioConfig]:
    """Our flat safetensors layout: tensors, and the architecture from the metadata or the side json."""
    from safetensors import safe_open
    from safetensors.torch import load_file
    with safe_open(str(p), "pt") as f:
        meta = f.metadata() or {}
    sd = load_file(str(p))
    cfg_json = meta.get(FLAT_META_KEY)
    side = p.with_suffix(".json")
    if cfg_json is None and side.is_file():
        cfg_json = side.read_text()
    if cfg_json is None:
        raise ModelFileError(f"{p} has no '{FLAT_META_KEY}' metadata and no {side}")
    return sd, RadioConfig.from_dict(json.loads(cfg_json))


def _read_torch_checkpoint(p: Path) -> tuple[dict[str, torch.Tensor], RadioConfig | None, Any]:
    """A torch checkpoint: ``(state dict, config, None)`` for a flat .pt with its side json, or
    ``(state dict, None, args)`` for the published layout (the config comes from its ``args``)."""
    try:
        obj = _torch_load(p)
    except Exception as e:
        raise ModelFileError(f"cannot read RADIO checkpoint {p}: {e}") from e
    if not isinstance(obj, dict):
        raise ModelFileError(f"{p}: expected a dict checkpoint, got {type(obj).__name__}")
    if "state_dict_ema" in obj or "state_dict" in obj:
        args = obj.get("args")
        sd = obj.get("state_dict_ema") or obj["state_dict"]
        if args is None:
            raise ModelFileError(f"{p}: checkpoint has a state dict but no 'args'")
        return sd, None, args
    # flat .pt of our own layout with a side json
    side = p.with_suffix(".json")
    if not side.is_file():
        raise ModelFileError(f"{p} is a plain state dict; its architecture file {side} is missing")
    return obj, RadioConfig.from_dict(json.loads(side.read_text())), None


def _split_state(sd: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], dict[str, dict], dict[str, dict]]:
    """``(model state, heads, feature projections)`` of a checkpoint's (renamed) state dict."""
    model_state: dict[str, torch.Tensor] = {}
    heads: dict[str, dict] = {}
    projs: dict[str, dict] = {}
    for k, v in sd.items():
        if k.startswith(("base_model.", "input_conditioner.")):
            model_state[k] = v
        elif k.startswith("_feature_normalizer."):
            model_state["feature_normalizer." + k[len("_feature_normalizer."):]] = v
        elif k.startswith("feature_normalizer."):
            model_state[k] = v
        elif (m := re.match(r"^_heads\.([^.]+)\.(.*)$", k)):
            heads.setdefault(m.group(1), {})[m.group(2)] = v
        elif (m := re.match(r"^_feature_projections\.([^.]+)\.(.*)$", k)):
            projs.setdefault(m.group(1), {})[m.group(2)] = v
    return model_state, heads, projs


def build_radio(ckpt: RadioCheckpoint, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                expect: RadioConfig | None = None) -> RadioModel:
    """Build :class:`RadioModel` for ``ckpt.config`` and load its tensors strictly.

    ``expect`` (e.g. a preset): raise if the checkpoint's architecture differs from it."""
    cfg = ckpt.config
    if expect is not None:
        diffs = [f"{f}: file {getattr(cfg, f)} vs expected {getattr(expect, f)}"
                 for f in ("embed_dim", "depth", "num_heads", "patch_size")
                 if getattr(cfg, f) != getattr(expect, f)]
        if diffs:
            raise ModelFileError(f"checkpoint {ckpt.path} is not the configured model: " + "; ".join(diffs))
    with torch.device("meta"):
        model = RadioModel(cfg)
    # uninitialised CPU storage for every meta tensor, as ``to_empty`` — but ``to_empty``'s
    # ``empty_like`` on meta tensors imports torch's meta decompositions (sympy): ~2 s per process
    model = model._apply(lambda t: torch.empty(t.shape, dtype=t.dtype, device="cpu"))
    load_strict(model, ckpt.model_state, what="RADIO checkpoint", source=ckpt.path)
    return model.to(device=device, dtype=dtype).eval()


def save_flat(ckpt: RadioCheckpoint, path: str | Path, dtype: torch.dtype | None = None) -> Path:
    """Write our flat layout: one safetensors file (model tensors + ``_heads.*`` +
    ``_feature_projections.*``) with the architecture JSON in its metadata and beside it."""
    from safetensors.torch import save_file

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tensors = {}
    for k, v in ckpt.model_state.items():
        tensors[k if not k.startswith("feature_normalizer.") else "_" + k] = v
    for name, sd in ckpt.heads.items():
        tensors.update({f"_heads.{name}.{k}": v for k, v in sd.items()})
    for name, sd in ckpt.feature_projections.items():
        tensors.update({f"_feature_projections.{name}.{k}": v for k, v in sd.items()})
    tensors = {k: (v.to(dtype) if dtype is not None and v.is_floating_point() else v).contiguous()
               for k, v in tensors.items()}
    cfg_json = json.dumps(ckpt.config.to_dict(), sort_keys=True)
    save_file(tensors, str(p), metadata={FLAT_META_KEY: cfg_json})
    p.with_suffix(".json").write_text(json.dumps(ckpt.config.to_dict(), indent=2, sort_keys=True) + "\n")
    return p
