"""Centred PCA for feature compression (edge compresses, mapper decompresses).

Convention: a feature ``x`` (in_dim,) is stored as ``y = Vᵀ(x − m)`` (out_dim,) and restored
as ``x̂ = V·y + m``, with ``m`` the fitted mean and ``V`` (in_dim, out_dim) the orthonormal
top principal directions. The mean is used both ways (the reference drops it — a bug).

Arrays may be numpy or torch; the result has the input's type (numpy in → numpy out).
Shapes: ``(..., in_dim)`` (channel-last: points, tokens) or a ``(in_dim, h, w)`` feature
map (channel-first, as the encoders produce). A 3-D array whose first dimension equals the
input dimension is treated as a map.
"""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

Array = "np.ndarray | torch.Tensor"


class PCAError(ValueError):
    """Wrong dimension, unfitted basis or a bad PCA file."""


def _as_torch(x: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, bool]:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(x)), True
    if isinstance(x, torch.Tensor):
        return x, False
    raise PCAError(f"expected a numpy array or torch tensor, got {type(x).__name__}")


class PCA:
    """A fitted, centred PCA basis. Build with :meth:`fit` or :meth:`load`."""

    def __init__(self, mean: np.ndarray, basis: np.ndarray, explained_variance: np.ndarray | None = None,
                 total_variance: float | None = None, n_samples: int = 0):
        mean = np.asarray(mean, dtype=np.float32).reshape(-1)
        basis = np.asarray(basis, dtype=np.float32)
        if basis.ndim != 2 or basis.shape[0] != mean.shape[0]:
            raise PCAError(f"basis must be (in_dim={mean.shape[0]}, out_dim), got {basis.shape}")
        if basis.shape[1] > basis.shape[0]:
            raise PCAError(f"out_dim {basis.shape[1]} > in_dim {basis.shape[0]}")
        self.mean = mean
        self.basis = np.ascontiguousarray(basis)
        ev = (np.zeros(basis.shape[1], np.float64) if explained_variance is None
              else np.asarray(explained_variance, np.float64))
        if ev.shape != (basis.shape[1],):
            raise PCAError(f"explained_variance must have shape ({basis.shape[1]},), got {ev.shape}")
        self.explained_variance = ev
        self.total_variance = float(total_variance) if total_variance is not None else float(ev.sum())
        self.n_samples = int(n_samples)
        self._torch_cache: dict = {}

    # ---------------------------------------------------------------- properties
    @property
    def in_dim(self) -> int:
        return int(self.basis.shape[0])

    @property
    def out_dim(self) -> int:
        return int(self.basis.shape[1])

    @property
    def explained_variance_ratio(self) -> np.ndarray:
        """Per-component variance / total variance of the fitted data."""
        return self.explained_variance / self.total_variance if self.total_variance > 0 else self.explained_variance * 0

    @property
    def content_hash(self) -> str:
        """First 12 hex digits of sha256 over (in_dim, out_dim, mean, basis) as float32 LE bytes."""
        h = hashlib.sha256()
        h.update(np.array([self.in_dim, self.out_dim], "<i8").tobytes())
        h.update(self.mean.astype("<f4").tobytes())
        h.update(self.basis.astype("<f4").tobytes())
        return h.hexdigest()[:12]

    def __repr__(self) -> str:
        return (f"PCA({self.in_dim}->{self.out_dim}, var {self.explained_variance_ratio.sum():.3f}, "
                f"hash {self.content_hash})")

    # ---------------------------------------------------------------- fitting
    @classmethod
    def fit(cls, X: np.ndarray | torch.Tensor, out_dim: int, device: str | torch.device = "cpu",
            chunk: int = 65536) -> "PCA":
        """Fit on ``X`` (n, D) (or a (D, h, w) map): mean, then eigh of the covariance (1/(n−1)),
        computed in float64 over chunks of ``chunk`` rows."""
        x, _ = _as_torch(X)
        if x.ndim == 3:
            x = x.reshape(x.shape[0], -1).T
        if x.ndim != 2:
            raise PCAError(f"fit expects (n, D) samples, got shape {tuple(x.shape)}")
        n, d = x.shape
        out_dim = int(out_dim)
        if not 1 <= out_dim <= d:
            raise PCAError(f"out_dim must be in [1, {d}], got {out_dim}")
        if n < 2:
            raise PCAError(f"need at least 2 samples to fit PCA, got {n}")
        dev = torch.device(device)
        s = torch.zeros(d, dtype=torch.float64, device=dev)
        for i in range(0, n, chunk):
            s += x[i:i + chunk].to(dev, torch.float64).sum(0)
        mean = s / n
        cov = torch.zeros(d, d, dtype=torch.float64, device=dev)
        for i in range(0, n, chunk):
            c = x[i:i + chunk].to(dev, torch.float64) - mean
            cov += c.T @ c
        if not torch.isfinite(cov).all():
            raise PCAError("PCA fit: samples contain NaN or inf")
        cov /= (n - 1)
        evals, evecs = torch.linalg.eigh(cov)  # ascending
        evals = evals.flip(0).clamp_min(0)
        evecs = evecs.flip(1)[:, :out_dim]
        # deterministic sign: largest-magnitude entry of each direction positive
        idx = evecs.abs().argmax(0)
        signs = torch.sign(evecs[idx, torch.arange(out_dim, device=dev)])
        signs[signs == 0] = 1
        evecs = evecs * signs
        return cls(mean.cpu().numpy(), evecs.cpu().numpy(), evals[:out_dim].cpu().numpy(),
                   total_variance=float(evals.sum()), n_samples=n)

    # ---------------------------------------------------------------- transforms
    def _mv(self, device, dtype):
        key = (str(device), dtype)
        if key not in self._torch_cache:
            self._torch_cache[key] = (torch.from_numpy(self.mean).to(device, dtype),
                                      torch.from_numpy(self.basis).to(device, dtype))
        return self._torch_cache[key]

    def _apply(self, X, dim_in: int, fn, what: str):
        x, was_np = _as_torch(X)
        dt = x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32
        if x.ndim == 3 and x.shape[0] == dim_in and x.shape[-1] != dim_in:
            c, h, w = x.shape
            y = fn(x.reshape(c, h * w).T.to(dt)).T.reshape(-1, h, w)
        elif x.ndim >= 1 and x.shape[-1] == dim_in:
            y = fn(x.to(dt))
        else:
            raise PCAError(f"PCA {what}: expected (..., {dim_in}) or ({dim_in}, h, w), got shape {tuple(x.shape)}")
        return y.cpu().numpy() if was_np else y

    def compress(self, X: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """``(..., in_dim) -> (..., out_dim)`` or ``(in_dim, h, w) -> (out_dim, h, w)``: ``Vᵀ(x − m)``."""
        def f(x):
            m, v = self._mv(x.device, x.dtype)
            return (x - m) @ v
        return self._apply(X, self.in_dim, f, "compress")

    def decompress(self, Y: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """``(..., out_dim) -> (..., in_dim)`` or ``(out_dim, h, w) -> (in_dim, h, w)``: ``V·y + m``."""
        def f(y):
            m, v = self._mv(y.device, y.dtype)
            return y @ v.T + m
        return self._apply(Y, self.out_dim, f, "decompress")

    def torch_basis(self, device: str | torch.device = "cpu",
                    dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mean (D,), basis (D, k))`` as tensors (cached)."""
        return self._mv(torch.device(device), dtype)

    # ---------------------------------------------------------------- I/O
    def to_arrays(self) -> dict:
        """The fields :meth:`save` writes and :meth:`from_arrays` reads (numpy scalars and arrays)."""
        return {"in_dim": np.int64(self.in_dim), "out_dim": np.int64(self.out_dim), "mean": self.mean,
                "basis": self.basis, "explained_variance": self.explained_variance,
                "total_variance": np.float64(self.total_variance), "n_samples": np.int64(self.n_samples)}

    @classmethod
    def from_arrays(cls, d: dict, source: str = "arrays") -> "PCA":
        """Inverse of :meth:`to_arrays` (``source`` names the origin in errors)."""
        try:
            mean, basis = np.asarray(d["mean"]), np.asarray(d["basis"])
            in_dim, out_dim = int(d["in_dim"]), int(d["out_dim"])
        except KeyError as e:
            raise PCAError(f"PCA {source}: missing field {e}") from None
        if mean.shape != (in_dim,) or basis.shape != (in_dim, out_dim):
            raise PCAError(f"PCA {source}: in_dim={in_dim}, out_dim={out_dim} but mean {mean.shape}, "
                           f"basis {basis.shape}")
        ev = d.get("explained_variance")
        tv = d.get("total_variance")
        return cls(mean, basis, None if ev is None else np.asarray(ev),
                   None if tv is None else float(tv), int(d.get("n_samples", 0)))

    def save(self, path: str | Path) -> Path:
        """Write an ``.npz`` (in_dim, out_dim, mean, basis, explained_variance, total_variance)."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(p, "wb") as f:
            np.savez(f, **self.to_arrays())
        return p

    @classmethod
    def load(cls, path: str | Path) -> "PCA":
        """Read an ``.npz`` written by :meth:`save`."""
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"PCA basis file not found: {p}")
        try:
            with np.load(p, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except (ValueError, OSError) as e:
            raise PCAError(f"PCA file {p} is not a valid npz: {e}") from None
        return cls.from_arrays(d, source=str(p))


class OnlinePCAFitter:
    """Collects feature maps from the first frames and fits a PCA when enough are in.

    ``add(feat (C, h, w))`` keeps up to ``samples_per_frame`` random tokens of each frame;
    after ``max_frames`` frames :attr:`ready` is true and :meth:`fit` returns the basis.
    Fitting online makes the feature space depend on the first frames seen; a basis fitted
    offline on representative data is preferred, so :meth:`fit` logs a warning.
    """

    def __init__(self, out_dim: int, max_frames: int = 10, samples_per_frame: int = 4096, seed: int = 0):
        if max_frames < 1:
            raise PCAError("max_frames must be >= 1")
        self.out_dim = int(out_dim)
        self.max_frames = int(max_frames)
        self.samples_per_frame = int(samples_per_frame)
        self._gen = torch.Generator().manual_seed(seed)
        self._chunks: list[torch.Tensor] = []

    @property
    def frames(self) -> int:
        return len(self._chunks)

    @property
    def ready(self) -> bool:
        return self.frames >= self.max_frames

    def add(self, feat: np.ndarray | torch.Tensor) -> bool:
        """Add one ``(C, h, w)`` map (or ``(n, C)`` tokens); returns :attr:`ready`."""
        x, _ = _as_torch(feat)
        x = x.detach().float().cpu()
        if x.ndim == 3:
            x = x.reshape(x.shape[0], -1).T
        if x.ndim != 2:
            raise PCAError(f"OnlinePCAFitter.add expects (C, h, w) or (n, C), got {tuple(x.shape)}")
        if self._chunks and x.shape[1] != self._chunks[0].shape[1]:
            raise PCAError(f"feature dim changed from {self._chunks[0].shape[1]} to {x.shape[1]}")
        x = x[torch.isfinite(x).all(1)]
        if x.shape[0] > self.samples_per_frame:
            x = x[torch.randperm(x.shape[0], generator=self._gen)[: self.samples_per_frame]]
        if not self.ready:
            self._chunks.append(x)
        return self.ready

    def fit(self) -> PCA:
        """The PCA of the collected samples (output dimension at most the feature dimension)."""
        if not self._chunks:
            raise PCAError("OnlinePCAFitter.fit: no frames were added")
        X = torch.cat(self._chunks)
        k = min(self.out_dim, X.shape[1])
        log.warning("fitting PCA(%d) online on %d samples from %d frame(s); the feature space then "
                    "depends on these first frames - prefer a basis fitted offline (pca.path)",
                    k, X.shape[0], self.frames)
        return PCA.fit(X, k)
