"""Simulated ViT-like encoder (encoders.sim): each degradation checked against an
independent computation on hand-made label images."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from encoders import EncoderConfig, make_encoder
from encoders.sim import SimEncoder
from synthetic_world import CLASS_NAMES

B, T = CLASS_NAMES.index("building"), CLASS_NAMES.index("tree")


@pytest.fixture(scope="module")
def text():
    from encoders.text.minilm import MiniLMText
    return MiniLMText()


def _enc(text, **kw):
    base = dict(patch=16, input_width=0, upsample=1, bleed=0.0, bias=0.0, confusion=0.0, snr_db=200.0)
    base.update(kw)
    return SimEncoder(CLASS_NAMES, text_encoder=text, **base)


def _halves(h=64, w=64):
    lab = np.full((h, w), B, dtype=np.int64)
    lab[:, w // 2:] = T
    return lab


def test_patch_grid_clean_equals_pooled_embeddings(text):
    """No bleed/bias/confusion, ~no noise, one cell per patch: each cell is the area-weighted
    mean of its pixels' name embeddings (computed here by hand, pixel loops)."""
    e = _enc(text)
    lab = _halves()
    lab[5:11, 3:9] = 0                               # a sky blob inside the first patch
    f = e.encode(None, lab)
    assert f.shape == (384, 4, 4)
    tab = text.encode(CLASS_NAMES)
    for i in range(4):
        for j in range(4):
            blk = lab[16 * i:16 * i + 16, 16 * j:16 * j + 16].reshape(-1)
            want = tab[torch.as_tensor(blk)].mean(0)
            assert torch.allclose(f[:, i, j], want, atol=1e-5)


def test_patch_grid_follows_input_width_and_upsamples_bilinearly(text):
    e = _enc(text, input_width=640, upsample=4)
    assert e.patch_grid(480, 640) == (30, 40) and e.patch_grid(96, 96) == (40, 40)
    e2 = _enc(text, upsample=4)                      # native width: 64 px / 16 = 4 patches, 16 cells out
    f = e2.encode(None, _halves())
    assert f.shape == (384, 16, 16)
    tab = text.encode(CLASS_NAMES)
    # bilinear, align_corners=False, x4: columns 0..5 pure building, 6 = 7/8 B + 1/8 T, 7 = 5/8 B + 3/8 T
    assert torch.allclose(f[:, 3, 0], tab[B], atol=1e-5) and torch.allclose(f[:, 3, 5], tab[B], atol=1e-5)
    assert torch.allclose(f[:, 3, 6], 0.875 * tab[B] + 0.125 * tab[T], atol=1e-5)
    assert torch.allclose(f[:, 3, 7], 0.625 * tab[B] + 0.375 * tab[T], atol=1e-5)


def test_boundary_bleeding_mixes_neighbour_patches(text):
    e = _enc(text, bleed=0.4)
    f = e.encode(None, _halves())
    tab = text.encode(CLASS_NAMES)
    # patch (1, 1): 8 neighbours, 3 of them (column 2) tree
    want = 0.6 * tab[B] + 0.4 * (5 * tab[B] + 3 * tab[T]) / 8
    assert torch.allclose(f[:, 1, 1], want, atol=1e-5)
    # corner (0, 0): 3 neighbours, all building
    assert torch.allclose(f[:, 0, 0], tab[B], atol=1e-5)


def test_systematic_bias_toward_related_class(text):
    e = _enc(text, bias=0.3, related=["building/tree"])
    assert int(e.related[B]) == T and int(e.related[T]) == B
    f = e.encode(None, np.full((32, 32), B, dtype=np.int64))
    tab = text.encode(CLASS_NAMES)
    want = F.normalize(0.7 * tab[B] + 0.3 * tab[T], dim=0)
    assert torch.allclose(f[:, 0, 0], want, atol=1e-5)
    # pairs naming absent classes are ignored; nothing is related to class 0
    e2 = _enc(text, related=["tree/bush"])
    assert int(e2.related[T]) != T and 0 not in e2.related.tolist()


def test_confusion_rate_and_target(text):
    e = _enc(text, confusion=0.25, related=["building/tree"], seed=3)
    lab = np.full((16 * 20, 16 * 20), B, dtype=np.int64)       # 400 patches, all building
    f = e.encode(None, lab)
    tab = text.encode(CLASS_NAMES)
    is_t = torch.isclose(f, tab[T][:, None, None], atol=1e-5).all(0)
    is_b = torch.isclose(f, tab[B][:, None, None], atol=1e-5).all(0)
    assert bool((is_t | is_b).all())
    n = int(is_t.sum())
    assert abs(n - 100) < 4 * math.sqrt(400 * 0.25 * 0.75)       # binomial(400, 0.25), 4 sigma


@pytest.mark.parametrize("snr_db", [-3.0, 6.0])
def test_noise_at_the_set_snr(text, snr_db):
    e = _enc(text, snr_db=snr_db, patch=8, upsample=8)
    clean = _enc(text, patch=8, upsample=8).encode(None, _halves())
    f = e.encode(None, _halves())
    noise = f - clean
    ratio = float((clean ** 2).sum() / (noise ** 2).sum())
    assert 10 * math.log10(ratio) == pytest.approx(snr_db, abs=0.1)


def test_seeded_reproducible_and_global_is_mean(text):
    lab = _halves()
    a = _enc(text, snr_db=0.0, confusion=0.2, seed=5)
    b = _enc(text, snr_db=0.0, confusion=0.2, seed=5)
    c = _enc(text, snr_db=0.0, confusion=0.2, seed=6)
    fa, fb, fc = a.encode(None, lab), b.encode(None, lab), c.encode(None, lab)
    assert torch.equal(fa, fb) and not torch.equal(fa, fc)
    d, g = a.encode_with_global(None, lab)
    assert torch.allclose(g, d.mean((1, 2)))


def test_made_from_config_and_bad_input(text):
    enc = make_encoder(EncoderConfig(kind="sim"), CLASS_NAMES)
    assert enc.name == "sim" and enc.feature_dim == 384 and enc.patch_grid(96, 96) == (40, 40)
    with pytest.raises(ValueError, match="labels"):
        enc.encode(np.zeros((8, 8, 3), np.uint8), None)
    with pytest.raises(ValueError, match=r"labels must lie in \[0, 13\)"):
        enc.encode(None, np.full((8, 8), 99))
    with pytest.raises(ValueError, match="bleed"):
        SimEncoder(CLASS_NAMES, bleed=1.5, text_encoder=text)
