"""Centred PCA: round-trip error = discarded variance, map shapes, I/O, hashing, errors."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.pca import PCA, OnlinePCAFitter, PCAError


def low_rank_data(n=4000, d=24, r=5, noise=0.05, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(r, d)) * np.linspace(3, 1, r)[:, None]
    return rng.normal(size=(n, r)) @ A + noise * rng.normal(size=(n, d)) + rng.normal(size=d) * 5


def test_roundtrip_error_equals_discarded_variance():
    X = low_rank_data()
    n = X.shape[0]
    for k in (3, 5, 10):
        p = PCA.fit(X, k)
        Xr = p.decompress(p.compress(X))
        err = ((X.astype(np.float64) - Xr) ** 2).sum(1).mean()
        ev = np.sort(np.linalg.eigvalsh(np.cov(X.T)))[::-1]       # independent: numpy, 1/(n-1)
        discarded = ev[k:].sum() * (n - 1) / n                      # mean squared error uses 1/n
        assert err == pytest.approx(discarded, rel=2e-3)
        np.testing.assert_allclose(p.explained_variance, ev[:k], rtol=1e-4)
        assert p.explained_variance_ratio.sum() == pytest.approx(ev[:k].sum() / ev.sum(), rel=1e-4)
        np.testing.assert_allclose(p.basis.T @ p.basis, np.eye(k), atol=1e-5)


def test_mean_is_used():
    X = low_rank_data(r=2) + 100.0
    p = PCA.fit(X, 2)
    # reconstruction of the mean itself is exact only with a centred PCA
    np.testing.assert_allclose(p.decompress(p.compress(p.mean[None]))[0], p.mean, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(p.compress(X).mean(0), 0, atol=1e-2)


def test_map_and_torch_shapes():
    X = low_rank_data(d=16)
    p = PCA.fit(torch.from_numpy(X).float(), 4)
    fmap = torch.from_numpy(X[:30].T.reshape(16, 5, 6)).float()
    y = p.compress(fmap)
    assert isinstance(y, torch.Tensor) and y.shape == (4, 5, 6)
    torch.testing.assert_close(y[:, 1, 2], p.compress(fmap[:, 1, 2]))
    assert p.decompress(y).shape == (16, 5, 6)
    assert p.compress(X[:7]).shape == (7, 4) and isinstance(p.compress(X[:7]), np.ndarray)
    with pytest.raises(PCAError, match=r"\(\.\.\., 16\)"):
        p.compress(np.zeros((3, 15)))
    with pytest.raises(PCAError, match=r"\(\.\.\., 4\)"):
        p.decompress(np.zeros((3, 5)))
    with pytest.raises(PCAError, match="out_dim"):
        PCA.fit(X, 17)


def test_save_load_hash(tmp_path):
    p = PCA.fit(low_rank_data(), 6)
    f = p.save(tmp_path / "pca.npz")
    q = PCA.load(f)
    assert q.content_hash == p.content_hash and len(p.content_hash) == 12
    np.testing.assert_array_equal(q.basis, p.basis)
    np.testing.assert_array_equal(q.mean, p.mean)
    assert q.total_variance == pytest.approx(p.total_variance)
    p2 = PCA.fit(low_rank_data(seed=1), 6)
    assert p2.content_hash != p.content_hash
    with pytest.raises(FileNotFoundError):
        PCA.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "bad.npz", in_dim=24, out_dim=6, mean=np.zeros(23), basis=np.zeros((24, 6)))
    with pytest.raises(PCAError, match="mean"):
        PCA.load(tmp_path / "bad.npz")


def test_online_fitter(caplog):
    X = low_rank_data(n=3000, d=12)
    f = OnlinePCAFitter(out_dim=3, max_frames=3, samples_per_frame=500)
    for i in range(3):
        f.add(torch.from_numpy(X[i * 1000:(i + 1) * 1000].T.reshape(12, 25, 40)).float())
    assert f.ready and f.frames == 3
    with caplog.at_level("WARNING"):
        p = f.fit()
    assert "online" in caplog.text
    assert p.in_dim == 12 and p.out_dim == 3 and p.n_samples == 1500
    full = PCA.fit(X, 3)
    # same dominant subspace
    s = np.linalg.svd(full.basis.T @ p.basis, compute_uv=False)
    assert s.min() > 0.95
    with pytest.raises(PCAError, match="changed"):
        f.add(torch.zeros(11, 2, 2))
