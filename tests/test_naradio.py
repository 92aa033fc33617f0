"""NARADIO: RADIO backbone loading/forward, CPE, NACLIP attention, heads, spectral reparam.

Checkpoints are tiny random state dicts written here in the *published* RADIO layout (key
names typed out literally, not taken from our modules), and outputs are compared with an
independent functional forward written below from the architecture description.
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from common.model_files import ModelFileError
from encoders import EncoderConfig, make_encoder
from encoders.naclip import NaclipAttention, gaussian_bias
from encoders.radio import (
    RadioConfig,
    RadioModel,
    build_radio,
    read_checkpoint,
    realize_spectral_reparam,
    save_flat,
)

D, DEPTH, HEADS, GRID, NTOK, P = 64, 2, 4, 32, 8, 16
HID, OUT = 96, 48
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


def _args(**kw):
    teachers = [dict(name="clip", type="open_clip", use_summary=True),
                dict(name="siglip", type="open_clip", use_summary=True),
                dict(name="dino_v2", type="dino_v2", use_summary=True),
                dict(name="sam", type="sam", use_summary=False)]
    a = dict(model="vit_base_patch16_224", model_kwargs=dict(embed_dim=D, depth=DEPTH, num_heads=HEADS),
             model_norm=False, cpe_max_size=GRID * P, register_multiple=8, cls_token_per_teacher=True,
             teachers=teachers, mlp_version="v2", spectral_reparam=False, dtype=torch.float32)
    a.update(kw)
    return argparse.Namespace(**a)


def published_state_dict(seed=0, layer_scale=None) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)

    def r(*s, std=0.05):
        return torch.randn(*s, generator=g) * std

    sd = {
        "base_model.patch_generator.embedder.weight": r(D, 3 * P * P),
        "base_model.patch_generator.pos_embed": r(1, GRID * GRID, D, std=0.5),
        "base_model.patch_generator.cls_token.token": r(NTOK, D, std=0.5),
        "input_conditioner.norm_mean": torch.tensor(CLIP_MEAN).view(3, 1, 1),
        "input_conditioner.norm_std": torch.tensor(CLIP_STD).view(3, 1, 1),
    }
    for i in range(DEPTH):
        b = f"base_model.blocks.{i}."
        sd.update({
            b + "norm1.weight": 1 + r(D), b + "norm1.bias": r(D),
            b + "attn.qkv.weight": r(3 * D, D, std=0.2), b + "attn.qkv.bias": r(3 * D),
            b + "attn.proj.weight": r(D, D, std=0.1), b + "attn.proj.bias": r(D),
            b + "norm2.weight": 1 + r(D), b + "norm2.bias": r(D),
            b + "mlp.fc1.weight": r(4 * D, D, std=0.1), b + "mlp.fc1.bias": r(4 * D),
            b + "mlp.fc2.weight": r(D, 4 * D, std=0.1), b + "mlp.fc2.bias": r(D),
        })
        if layer_scale:
            sd[b + f"ls1.{layer_scale}"] = 0.5 + r(D)
            sd[b + f"ls2.{layer_scale}"] = 0.5 + r(D)
    for t in ("1", "0"):  # siglip (teacher 1) and clip heads: MLP2 with one inner block
        h = f"_heads.{t}."
        sd.update({h + "fc1.weight": r(HID, D, std=0.1), h + "fc1.bias": r(HID),
                   h + "blocks.0.0.weight": 1 + r(HID), h + "blocks.0.0.bias": r(HID),
                   h + "blocks.0.2.weight": r(HID, HID, std=0.1), h + "blocks.0.2.bias": r(HID),
                   h + "final.0.weight": 1 + r(HID), h + "final.0.bias": r(HID),
                   h + "final.2.weight": r(OUT, HID, std=0.1), h + "final.2.bias": r(OUT)})
    sd["_feature_projections.1.fc1.weight"] = r(HID, D)
    sd["teacher_stats.clip.mean"] = r(D)  # unrelated training state: ignored
    return sd


def write_ckpt(path, sd=None, key="state_dict", **args_kw):
    torch.save({"args": _args(**args_kw), key: published_state_dict() if sd is None else sd}, path)
    return path


# ----------------------------------------------------------------- independent reference
def ref_forward(sd, x01, naclip_sigma=None, normalize=True, reduced=False, ls=None):
    """Functional RADIO forward from raw state-dict tensors; returns all tokens (B, T+N, D)."""
    x = x01
    if normalize:
        x = (x - sd["input_conditioner.norm_mean"]) / sd["input_conditioner.norm_std"]
    B, _, H, W = x.shape
    h, w = H // P, W // P
    patches = torch.stack([x[:, :, i * P:(i + 1) * P, j * P:(j + 1) * P].reshape(B, -1)
                           for i in range(h) for j in range(w)], 1)        # (B, N, c·y·x)
    tok = patches @ sd["base_model.patch_generator.embedder.weight"].T
    pe = torch.from_numpy(hand_cpe(sd["base_model.patch_generator.pos_embed"].numpy(), h, w)).float()
    tok = tok + pe
    t = torch.cat([sd["base_model.patch_generator.cls_token.token"].expand(B, -1, -1), tok], 1)
    hd = D // HEADS
    for i in range(DEPTH):
        b = f"base_model.blocks.{i}."
        last = i == DEPTH - 1
        y = F.layer_norm(t, (D,), sd[b + "norm1.weight"], sd[b + "norm1.bias"], eps=1e-6)
        qkv = y @ sd[b + "attn.qkv.weight"].T + sd[b + "attn.qkv.bias"]
        q, k, v = qkv.split(D, -1)
        heads_out = []
        for hh in range(HEADS):
            qh, kh, vh = (z[..., hh * hd:(hh + 1) * hd] for z in (q, k, v))
            if last and naclip_sigma is not None:
                logits = kh @ kh.transpose(1, 2) / math.sqrt(hd) + brute_bias(h, w, naclip_sigma, NTOK)
            else:
                logits = qh @ kh.transpose(1, 2) / math.sqrt(hd)
            heads_out.append(torch.softmax(logits, -1) @ vh)
        a = torch.cat(heads_out, -1) @ sd[b + "attn.proj.weight"].T + sd[b + "attn.proj.bias"]
        if ls:
            a = a * sd[b + f"ls1.{ls}"]
        if last and reduced:
            t = a
            break
        t = t + a
        y = F.layer_norm(t, (D,), sd[b + "norm2.weight"], sd[b + "norm2.bias"], eps=1e-6)
        m = (F.gelu(y @ sd[b + "mlp.fc1.weight"].T + sd[b + "mlp.fc1.bias"]) @ sd[b + "mlp.fc2.weight"].T
             + sd[b + "mlp.fc2.bias"])
        if ls:
            m = m * sd[b + f"ls2.{ls}"]
        t = t + m
    return t


def hand_cpe(pos, h, w):
    """Bilinear (align_corners=False) resize of the G×G table to S×S, S=max(h,w), top-left crop."""
    G = int(math.isqrt(pos.shape[1]))
    tab = pos[0].reshape(G, G, -1).astype(np.float64)
    S = max(h, w)

    def src(i):
        s = max((i + 0.5) * G / S - 0.5, 0.0)
        i0 = min(int(math.floor(s)), G - 1)
        return i0, min(i0 + 1, G - 1), s - i0

    out = np.zeros((h, w, tab.shape[-1]))
    for r in range(h):
        r0, r1, lr = src(r)
        for c in range(w):
            c0, c1, lc = src(c)
            out[r, c] = ((1 - lr) * (1 - lc) * tab[r0, c0] + (1 - lr) * lc * tab[r0, c1]
                         + lr * (1 - lc) * tab[r1, c0] + lr * lc * tab[r1, c1])
    return out.reshape(h * w, -1)


def brute_bias(h, w, sigma, n_prefix):
    n = n_prefix + h * w
    out = torch.zeros(n, n, dtype=torch.float64)
    for a in range(h * w):
        ra, ca = divmod(a, w)        # tokens are row-major over (h, w)
        for b in range(h * w):
            rb, cb = divmod(b, w)
            out[n_prefix + a, n_prefix + b] = math.exp(-((ra - rb) ** 2 + (ca - cb) ** 2) / (2 * sigma ** 2))
    return out.float()


def ref_mlp2(sd, prefix, x):
    def ln(z, k):
        return F.layer_norm(z, (z.shape[-1],), sd[k + ".weight"], sd[k + ".bias"], eps=1e-5)
    y = x @ sd[prefix + "fc1.weight"].T + sd[prefix + "fc1.bias"]
    y = y + F.gelu(ln(y, prefix + "blocks.0.0")) @ sd[prefix + "blocks.0.2.weight"].T + sd[prefix + "blocks.0.2.bias"]
    return F.gelu(ln(y, prefix + "final.0")) @ sd[prefix + "final.2.weight"].T + sd[prefix + "final.2.bias"]


def _cfg(path, **kw):
    return EncoderConfig(kind="naradio", model="auto", checkpoint=str(path), **kw)


@pytest.fixture(scope="module")
def ckpt_path(tmp_path_factory):
    return write_ckpt(tmp_path_factory.mktemp("radio") / "tiny.pth.tar")


# ----------------------------------------------------------------- loading
def test_config_inferred_from_args_and_shapes(ckpt_path):
    ck = read_checkpoint(ckpt_path)
    c = ck.config
    assert (c.embed_dim, c.depth, c.num_heads, c.patch_size, c.pos_grid) == (D, DEPTH, HEADS, P, GRID)
    assert (c.num_cls_tokens, c.num_registers) == (4, 4)
    assert c.summary_idxs == [0, 1, 2] and c.teacher_slots["siglip"] == 1
    assert set(ck.heads) == {"0", "1"} and "1" in ck.feature_projections


def test_preset_dims():
    b, lg = RadioConfig.preset("radio_v2.5-b"), RadioConfig.preset("radio_v2.5-l")
    assert (b.embed_dim, b.depth, b.num_heads, b.num_prefix) == (768, 12, 12, 8)
    assert (lg.embed_dim, lg.depth, lg.num_heads, lg.pos_grid) == (1024, 24, 16, 128)


def test_forward_matches_independent_reference(ckpt_path):
    sd = published_state_dict()
    enc = make_encoder(_cfg(ckpt_path, naclip=False))
    rgb = np.random.default_rng(0).integers(0, 256, (48, 80, 3), dtype=np.uint8)
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    ref = ref_forward(sd, x)
    out = enc.forward(rgb)
    assert out.features.shape == (1, D, 3, 5)
    torch.testing.assert_close(out.features[0].flatten(1).T, ref[0, NTOK:], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.summary[0], ref[0, :3].reshape(-1), rtol=1e-4, atol=1e-4)


def test_naclip_forward_matches_reference_non_square(ckpt_path):
    sd = published_state_dict()
    rgb = np.random.default_rng(1).integers(0, 256, (48, 80, 3), dtype=np.uint8)
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    for reduced in (False, True):
        enc = make_encoder(_cfg(ckpt_path, gauss_std=1.5, reduced_block=reduced))
        ref = ref_forward(sd, x, naclip_sigma=1.5, reduced=reduced)
        got = enc.encode(rgb)
        assert got.shape == (D, 3, 5)
        torch.testing.assert_close(got.flatten(1).T, ref[0, NTOK:], rtol=1e-4, atol=1e-4)
    plain = make_encoder(_cfg(ckpt_path, naclip=False)).encode(rgb)
    assert not torch.allclose(plain, got, atol=1e-3)


def test_normalize_input_switch(ckpt_path):
    sd = published_state_dict()
    rgb = np.random.default_rng(2).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    enc = make_encoder(_cfg(ckpt_path, naclip=False, normalize_input=False))
    ref = ref_forward(sd, x, normalize=False)
    torch.testing.assert_close(enc.encode(rgb).flatten(1).T, ref[0, NTOK:], rtol=1e-4, atol=1e-4)
    assert not torch.allclose(ref, ref_forward(sd, x, normalize=True))


def test_output_resolution_and_rounding(ckpt_path):
    enc = make_encoder(_cfg(ckpt_path))
    assert enc.stride == 16 and enc.feature_dim == D
    assert enc.encode(np.zeros((224, 224, 3), np.uint8)).shape == (D, 14, 14)
    assert enc.encode(np.zeros((100, 130, 3), np.uint8)).shape == (D, 6, 8)  # 96 x 128
    enc2 = make_encoder(_cfg(ckpt_path, input_resolution=[64, 96]))
    assert enc2.encode(np.zeros((480, 640, 3), np.uint8)).shape == (D, 4, 6)
    with pytest.raises(ValueError, match="uint8"):
        enc.encode(np.zeros((32, 32, 3), np.float32))


def test_head_projection_and_global(ckpt_path):
    sd = published_state_dict()
    enc = make_encoder(_cfg(ckpt_path))
    rgb = np.random.default_rng(3).integers(0, 256, (32, 48, 3), dtype=np.uint8)
    f = enc.encode(rgb)
    lang = enc.align_spatial(f)
    assert lang.shape == (OUT, 2, 3)
    torch.testing.assert_close(lang.flatten(1).T, ref_mlp2(sd, "_heads.1.", f.flatten(1).T), rtol=1e-4, atol=1e-5)
    g = enc.encode_global(rgb)
    cls1 = enc.forward(rgb).cls_tokens[0, 1]
    assert g.shape == (OUT,)
    torch.testing.assert_close(g, ref_mlp2(sd, "_heads.1.", cls1), rtol=1e-4, atol=1e-5)
    assert enc.language_head is not None and enc.language_head.out_dim == OUT
    enc_l = make_encoder(_cfg(ckpt_path, output="language"))
    assert enc_l.feature_dim == OUT and enc_l.encode(rgb).shape == (OUT, 2, 3) and enc_l.language_head is None


def test_prefix_split():
    rc = RadioConfig(embed_dim=4, depth=1, num_heads=1, pos_grid=4, mlp_hidden=8)
    m = RadioModel(rc)
    tokens = torch.arange(1 * (8 + 6) * 4, dtype=torch.float32).reshape(1, 14, 4)
    out = m.split(tokens, (2, 3))
    torch.testing.assert_close(out.summary[0], tokens[0, :3].reshape(-1))
    torch.testing.assert_close(out.cls_tokens[0], tokens[0, :4])
    # features (D, h, w): token 8 + r*3 + c at [:, r, c]
    for r in range(2):
        for c in range(3):
            torch.testing.assert_close(out.features[0, :, r, c], tokens[0, 8 + r * 3 + c])


def test_cpe_crop_matches_hand_computation():
    rc = RadioConfig(embed_dim=3, depth=1, num_heads=1, pos_grid=7, mlp_hidden=4)
    m = RadioModel(rc)
    torch.nn.init.normal_(m.base_model.patch_generator.pos_embed)
    pos = m.base_model.patch_generator.pos_embed.detach()
    for h, w in [(3, 5), (5, 3), (4, 4), (7, 7), (2, 9)]:
        got = m.base_model.patch_generator.pos_enc(h, w)[0].detach().numpy()
        np.testing.assert_allclose(got, hand_cpe(pos.numpy(), h, w), rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------- NACLIP
@pytest.mark.parametrize("h,w,npre", [(3, 5, 8), (5, 3, 2), (4, 4, 0)])
def test_gaussian_bias_brute_force(h, w, npre):
    got = gaussian_bias(h, w, 2.0, npre)
    torch.testing.assert_close(got, brute_bias(h, w, 2.0, npre))
    e1 = math.exp(-1 / 8)
    # orientation: token (0, 0) neighbours (0, 1) and (1, 0); (0, w-1) is w-1 columns away
    assert got[npre, npre + 1] == pytest.approx(e1, rel=1e-6)
    assert got[npre, npre + w] == pytest.approx(e1, rel=1e-6)
    assert got[npre, npre + w - 1] == pytest.approx(math.exp(-((w - 1) ** 2) / 8), rel=1e-6)
    assert torch.all(got[:npre] == 0) and torch.all(got[:, :npre] == 0)
    assert torch.all(got.diagonal()[npre:] == 1)


def test_naclip_attention_hand_reference():
    from encoders.radio import Attention
    torch.manual_seed(0)
    attn = Attention(16, 2)
    na = NaclipAttention(attn, n_prefix=2, gauss_std=1.0)
    h, w = 2, 3
    x = torch.randn(1, 2 + h * w, 16)
    got = na(x, grid_hw=(h, w), extra="ignored")
    qkv = x[0] @ attn.qkv.weight.T + attn.qkv.bias
    k, v = qkv[:, 16:32], qkv[:, 32:]
    bias = brute_bias(h, w, 1.0, 2)
    outs = []
    for hh in range(2):
        kh, vh = k[:, hh * 8:(hh + 1) * 8], v[:, hh * 8:(hh + 1) * 8]
        logits = kh @ kh.T / math.sqrt(8) + bias
        outs.append(torch.softmax(logits, -1) @ vh)
    ref = torch.cat(outs, -1) @ attn.proj.weight.T + attn.proj.bias
    torch.testing.assert_close(got[0], ref, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="prefix"):
        na(x, grid_hw=(3, 3))


# ----------------------------------------------------------------- errors
def test_missing_file(tmp_path):
    p = tmp_path / "nope.pth.tar"
    with pytest.raises(ModelFileError, match="nope.pth.tar"):
        make_encoder(_cfg(p))
    with pytest.raises(ModelFileError, match=str(tmp_path / "radio_v2.5-b.safetensors")):
        make_encoder(EncoderConfig(kind="naradio", model="radio_v2.5-b", model_dir=str(tmp_path)))


def test_mismatched_checkpoint_errors(tmp_path):
    sd = published_state_dict()
    del sd["base_model.blocks.1.mlp.fc2.bias"]
    with pytest.raises(ModelFileError, match=r"missing keys.*blocks\.1\.mlp\.fc2\.bias"):
        make_encoder(_cfg(write_ckpt(tmp_path / "a.pth.tar", sd)))
    sd = published_state_dict()
    sd["base_model.blocks.0.attn.extra"] = torch.zeros(3)
    with pytest.raises(ModelFileError, match=r"unexpected keys.*blocks\.0\.attn\.extra"):
        make_encoder(_cfg(write_ckpt(tmp_path / "b.pth.tar", sd)))
    sd = published_state_dict()
    sd["base_model.blocks.0.attn.proj.weight"] = torch.zeros(D, D + 1)
    with pytest.raises(ModelFileError, match=r"wrong shapes.*attn\.proj\.weight"):
        make_encoder(_cfg(write_ckpt(tmp_path / "c.pth.tar", sd)))
    # a ViT-B preset against the tiny file
    p = write_ckpt(tmp_path / "d.pth.tar")
    with pytest.raises(ModelFileError, match="embed_dim: file 64 vs expected 768"):
        make_encoder(EncoderConfig(kind="naradio", model="radio_v2.5-b", checkpoint=str(p)))
    sd = published_state_dict()
    del sd["_heads.1.fc1.weight"], sd["_heads.1.fc1.bias"]
    with pytest.raises(ModelFileError):
        make_encoder(_cfg(write_ckpt(tmp_path / "e.pth.tar", sd)))


# ----------------------------------------------------------------- reparam, EMA, layer scale, flat
def test_spectral_reparam_realisation(tmp_path):
    g = torch.Generator().manual_seed(5)
    W = torch.randn(3 * D, D, generator=g)
    Wp = torch.randn(D, D, generator=g)
    sd = published_state_dict()
    base = "base_model.blocks.0.attn."
    del sd[base + "qkv.weight"], sd[base + "proj.weight"]
    sd[base + "qkv.parametrizations.weight.original"] = W
    expected_chunks = []
    for i, ch in enumerate(W.split(D)):
        u, v, s = torch.randn(D, generator=g), torch.randn(D, generator=g), torch.randn(1, 1, generator=g)
        pre = base + f"qkv.parametrizations.weight.0.parts.{i}."
        if i < 2:
            sd.update({pre + "_u": u, pre + "_v": v, pre + "scale": s, pre + "_sn_version": torch.tensor(2)})
            sigma = float(u @ ch @ v) + 1e-6
            expected_chunks.append(ch * (math.log1p(math.exp(float(s))) + 0.05) / sigma)
        else:  # values chunk not renormalised (Identity parametrisation: no entries)
            expected_chunks.append(ch)
    u, v, s = torch.randn(D, generator=g), torch.randn(D, generator=g), torch.randn(1, 1, generator=g)
    sd[base + "proj.parametrizations.weight.original"] = Wp
    sd.update({base + "proj.parametrizations.weight.0._u": u, base + "proj.parametrizations.weight.0._v": v,
               base + "proj.parametrizations.weight.0.scale": s})  # no _sn_version -> version 1
    real = realize_spectral_reparam(sd)
    torch.testing.assert_close(real[base + "qkv.weight"], torch.cat(expected_chunks), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(real[base + "proj.weight"], Wp * float(s) / (float(u @ Wp @ v) + 1e-6),
                               rtol=1e-5, atol=1e-6)
    assert not any(".parametrizations." in k for k in real)
    enc = make_encoder(_cfg(write_ckpt(tmp_path / "sn.pth.tar", sd), naclip=False))
    torch.testing.assert_close(enc.model.base_model.blocks[0].attn.proj.weight, real[base + "proj.weight"])


def test_ema_state_dict_preferred(tmp_path):
    sd, ema = published_state_dict(0), published_state_dict(1)
    p = tmp_path / "ema.pth.tar"
    torch.save({"args": _args(), "state_dict": sd, "state_dict_ema": ema}, p)
    m = build_radio(read_checkpoint(p))
    torch.testing.assert_close(m.base_model.patch_generator.pos_embed, ema["base_model.patch_generator.pos_embed"])


def test_layer_scale_grandma(tmp_path):
    sd = published_state_dict(layer_scale="grandma")
    enc = make_encoder(_cfg(write_ckpt(tmp_path / "ls.pth.tar", sd), naclip=False))
    rgb = np.random.default_rng(4).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    ref = ref_forward(sd, x, ls="grandma")
    torch.testing.assert_close(enc.encode(rgb).flatten(1).T, ref[0, NTOK:], rtol=1e-4, atol=1e-4)


def test_flat_conversion_roundtrip(tmp_path, ckpt_path):
    ck = read_checkpoint(ckpt_path)
    flat = save_flat(ck, tmp_path / "m" / "radio_v2.5-x.safetensors")
    assert flat.with_suffix(".json").is_file()
    a = make_encoder(_cfg(ckpt_path))
    b = make_encoder(_cfg(flat))
    rgb = np.random.default_rng(5).integers(0, 256, (32, 48, 3), dtype=np.uint8)
    torch.testing.assert_close(a.encode(rgb), b.encode(rgb))
    torch.testing.assert_close(a.encode_global(rgb), b.encode_global(rgb))
    assert a.version == b.version


def test_models_cli_convert_and_check(tmp_path, ckpt_path, capsys):
    from edge import models_cli
    parser = argparse.ArgumentParser()
    models_cli.add_arguments(parser)
    dst = tmp_path / "md" / "radio_v2.5-b.safetensors"
    assert models_cli.run(parser.parse_args(["convert", str(ckpt_path), str(dst)])) == 0
    assert dst.is_file() and dst.with_suffix(".json").is_file()
    rep = models_cli.check_dir(tmp_path / "md", ["radio_v2.5-b"], load=True)
    assert rep["radio_v2.5-b"]["ok"] and rep["_missing"] == []
    assert models_cli.run(parser.parse_args(["check", str(tmp_path / "md"), "--need", "siglip"])) == 1
    assert "siglip_text" in capsys.readouterr().out
    assert models_cli.run(parser.parse_args(["download", str(tmp_path / "md")])) == 0
    assert "radio-v2.5-b_half.pth.tar" in capsys.readouterr().out
