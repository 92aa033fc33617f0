"""The feature space a map's features live in, and exact similarity against queries in it.

A :class:`FeatureSpace` describes what the edge stores in each voxel/ray feature and what
the mapper needs to compare text/image queries with it:

* ``encoder_name``/``encoder_version``: which encoder made the features;
* ``in_dim``: the encoder's feature dimension (RADIO 768/1024, MiniLM 384);
* ``pca`` (optional): the centred PCA that compresses ``in_dim -> dim``;
* ``head`` (optional): the language head (RADIO's SigLIP MLP2) that maps encoder features
  to the text model's space; applied at query time *after* averaging (docs/method.md#language-head);
* ``text_model``: "minilm-l6" | "siglip" — which text encoder embeds queries;
* ``encoder_config`` (optional): the encoder settings the mapper needs to embed *image*
  queries with the same encoder (``EncoderConfig`` keys; not part of the id, which already
  names the encoder version).

Its id is ``f"{encoder_name}-{encoder_version}-{pca.content_hash or 'raw'}-{dim}"``; maps
never mix ids. :meth:`to_body`/:meth:`from_body` give a flat dict of str/int/float/numpy
values for the wire (``common.wire``).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from common.language_head import MLP2, MLP2Config
from common.pca import PCA

BODY_VERSION = 1


class FeatureSpaceError(ValueError):
    """A feature-space body or query does not fit (shapes, dims, missing fields)."""


def _body_get(body: dict, k: str, types: type | tuple[type, ...]) -> Any:
    """Field ``k`` of a feature-space body (numpy scalars as Python values), type-checked."""
    if k not in body:
        raise FeatureSpaceError(f"feature-space body lacks field '{k}'")
    v = body[k]
    if isinstance(v, np.generic):
        v = v.item()
    if not isinstance(v, types) or isinstance(v, bool) and types is not bool:
        raise FeatureSpaceError(f"feature-space field '{k}' has type {type(v).__name__}")
    return v


def _pca_from_body(body: dict, in_dim: int, dim: int) -> PCA:
    """The ``pca.*`` fields of a feature-space body as a :class:`PCA` ``in_dim -> dim`` (validated)."""
    # decoded arrays are read-only views of the message: own writable copies, so torch
    # can wrap them (torch.from_numpy warns on non-writable arrays)
    mean = np.array(_body_get(body, "pca.mean", np.ndarray), dtype=np.float32)
    basis = np.array(_body_get(body, "pca.basis", np.ndarray), dtype=np.float32)
    ev = np.array(body.get("pca.explained_variance", np.zeros(dim)), dtype=np.float64)
    if mean.shape != (in_dim,) or basis.shape != (in_dim, dim) or ev.shape != (dim,):
        raise FeatureSpaceError(f"PCA shapes in body: mean {mean.shape}, basis {basis.shape}, "
                                f"explained_variance {ev.shape}; "
                                f"expected ({in_dim},), ({in_dim}, {dim}), ({dim},)")
    if not (np.isfinite(mean).all() and np.isfinite(basis).all()):
        raise FeatureSpaceError("PCA mean/basis in body contain NaN or inf")
    return PCA(mean, basis, ev, float(body.get("pca.total_variance", ev.sum())),
               int(body.get("pca.n_samples", 0)))


def _head_from_body(body: dict) -> tuple[MLP2Config, dict[str, np.ndarray]]:
    """The ``head.cfg.*`` / ``head.sd.*`` fields of a feature-space body: the language head's
    config and state dict, checked against each other."""
    cfg = {k[len("head.cfg."):]: (v.item() if isinstance(v, np.generic) else v)
           for k, v in body.items() if k.startswith("head.cfg.")}
    try:
        hc = MLP2Config.from_dict(cfg)
    except (ValueError, TypeError) as e:
        raise FeatureSpaceError(f"bad language head config in body: {e}") from None
    hs = {k[len("head.sd."):]: np.array(v) for k, v in body.items() if k.startswith("head.sd.")}
    expect = {k: tuple(v.shape) for k, v in MLP2(hc, device="meta").state_dict().items()}
    got = {k: tuple(v.shape) for k, v in hs.items()}
    if expect != got:
        missing = sorted(set(expect) - set(got))
        extra = sorted(set(got) - set(expect))
        wrong = sorted(k for k in set(expect) & set(got) if expect[k] != got[k])
        raise FeatureSpaceError(f"language head tensors do not match its config: missing {missing}, "
                                f"unexpected {extra}, wrong shapes {wrong}")
    return hc, hs


@dataclass
class FeatureSpace:
    encoder_name: str
    encoder_version: str
    in_dim: int
    text_model: str = "minilm-l6"
    pca: PCA | None = None
    head_config: MLP2Config | None = None
    head_state: dict[str, np.ndarray] | None = None
    encoder_config: dict | None = None
    _head_cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        if self.pca is not None and self.pca.in_dim != self.in_dim:
            raise FeatureSpaceError(f"PCA input dim {self.pca.in_dim} != encoder dim {self.in_dim}")
        if (self.head_config is None) != (self.head_state is None):
            raise FeatureSpaceError("language head needs both a config and a state dict")
        if self.head_config is not None and self.head_config.in_dim != self.in_dim:
            raise FeatureSpaceError(f"language head input dim {self.head_config.in_dim} != encoder dim {self.in_dim}")
        for s in (self.encoder_name, self.encoder_version):
            if not s or any(c.isspace() for c in s):
                raise FeatureSpaceError(f"encoder name/version must be non-empty without spaces, got {s!r}")

    # ------------------------------------------------------------------ identity
    @property
    def dim(self) -> int:
        """Stored (wire/map) feature dimension."""
        return self.pca.out_dim if self.pca is not None else self.in_dim

    @property
    def lang_dim(self) -> int:
        """Dimension of the language space queries live in."""
        return self.head_config.out_dim if self.head_config is not None else self.in_dim

    @property
    def id(self) -> str:
        h = self.pca.content_hash if self.pca is not None else "raw"
        return f"{self.encoder_name}-{self.encoder_version}-{h}-{self.dim}"

    @classmethod
    def for_encoder(cls, encoder: Any, pca: PCA | None = None) -> "FeatureSpace":
        """Describe an encoder's output (duck-typed: ``name``, ``version``, ``feature_dim``,
        ``text_model``, optional ``language_head`` MLP2)."""
        head = getattr(encoder, "language_head", None)
        hc = hs = None
        if head is not None:
            hc = head.cfg
            hs = {k: v.detach().float().cpu().numpy() for k, v in head.state_dict().items()}
        qc = getattr(encoder, "query_config", None)
        return cls(encoder.name, str(encoder.version), int(encoder.feature_dim),
                   getattr(encoder, "text_model", "minilm-l6"), pca, hc, hs, dict(qc) if qc else None)

    # ------------------------------------------------------------------ wire body
    def to_body(self) -> dict:
        """Flat dict: str/int/float values and numpy arrays (``pca.*``, ``head.*`` prefixes)."""
        b: dict = {"fs_version": BODY_VERSION, "id": self.id, "encoder_name": self.encoder_name,
                   "encoder_version": self.encoder_version, "in_dim": int(self.in_dim), "dim": int(self.dim),
                   "text_model": self.text_model, "has_pca": int(self.pca is not None),
                   "has_head": int(self.head_config is not None)}
        if self.pca is not None:
            b["pca.mean"] = self.pca.mean.astype(np.float32)
            b["pca.basis"] = self.pca.basis.astype(np.float32)
            b["pca.explained_variance"] = self.pca.explained_variance.astype(np.float64)
            b["pca.total_variance"] = float(self.pca.total_variance)
            b["pca.n_samples"] = int(self.pca.n_samples)
        if self.encoder_config:
            b["encoder_config"] = dict(self.encoder_config)
        if self.head_config is not None and self.head_state is not None:   # both or neither (__post_init__)
            for k, v in self.head_config.to_dict().items():
                b[f"head.cfg.{k}"] = int(v) if isinstance(v, bool) else v
            for k, v in self.head_state.items():
                b[f"head.sd.{k}"] = np.ascontiguousarray(v, dtype=np.float32)
        return b

    @classmethod
    def from_body(cls, body: dict) -> "FeatureSpace":
        """Inverse of :meth:`to_body`; validates every shape and the id."""
        ver = _body_get(body, "fs_version", int)
        if ver != BODY_VERSION:
            raise FeatureSpaceError(f"feature-space body version {ver} not supported (expected {BODY_VERSION})")
        in_dim, dim = _body_get(body, "in_dim", int), _body_get(body, "dim", int)
        if in_dim <= 0 or dim <= 0 or dim > in_dim:
            raise FeatureSpaceError(f"bad dims in feature-space body: in_dim={in_dim}, dim={dim}")
        pca = None
        if _body_get(body, "has_pca", int):
            pca = _pca_from_body(body, in_dim, dim)
        elif dim != in_dim:
            raise FeatureSpaceError(f"body has no PCA but dim {dim} != in_dim {in_dim}")
        hc = hs = None
        if _body_get(body, "has_head", int):
            hc, hs = _head_from_body(body)
        ec = body.get("encoder_config")
        if ec is not None and not (isinstance(ec, dict) and len(ec) <= 64 and all(
                isinstance(k, str) and (v is None or isinstance(v, (str, int, float, bool, list)))
                for k, v in ec.items())):
            raise FeatureSpaceError("feature-space field 'encoder_config' must be a map of str to plain values")
        fs = cls(_body_get(body, "encoder_name", str), _body_get(body, "encoder_version", str), in_dim,
                 _body_get(body, "text_model", str), pca, hc, hs, dict(ec) if ec else None)
        if fs.dim != dim:
            raise FeatureSpaceError(f"body dim {dim} != PCA output dim {fs.dim}")
        if "id" in body and body["id"] != fs.id:
            raise FeatureSpaceError(f"feature-space id in body {body['id']!r} does not match its content ({fs.id!r})")
        return fs

    # ------------------------------------------------------------------ transforms
    def compress(self, x: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """Encoder-space features → stored features (identity without PCA)."""
        return self.pca.compress(x) if self.pca is not None else x

    def decompress(self, y: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """Stored features → encoder-space features (identity without PCA)."""
        return self.pca.decompress(y) if self.pca is not None else y

    def language_head(self, device: str | torch.device = "cpu") -> MLP2 | None:
        """The head as a module on ``device`` (cached), or None."""
        if self.head_config is None or self.head_state is None:   # both or neither (__post_init__)
            return None
        key = str(device)
        if key not in self._head_cache:
            # built outside inference mode so the module also works in autograd-tracked code
            with torch.inference_mode(False), torch.no_grad():
                sd = {k: torch.from_numpy(np.array(v, np.float32)) for k, v in self.head_state.items()}
                head = MLP2.from_state_dict(sd, device=device, cfg=self.head_config)
            self._head_cache[key] = head.requires_grad_(False)
        return self._head_cache[key]

    @torch.inference_mode()
    def to_language(self, y: torch.Tensor, device: str | torch.device = "cpu") -> torch.Tensor:
        """Stored features ``(N, dim)`` → language space ``(N, lang_dim)`` (decompress, then head)."""
        x = torch.as_tensor(self.decompress(torch.as_tensor(y, device=device).float()))
        head = self.language_head(device)
        return head(x) if head is not None else x

    def check_queries(self, queries: np.ndarray | torch.Tensor, device: str | torch.device = "cpu") -> torch.Tensor:
        """Language-space ``queries`` as a float32 ``(Q, lang_dim)`` tensor on ``device`` (a single
        ``(lang_dim,)`` row is accepted); :class:`FeatureSpaceError` for any other shape."""
        q = torch.as_tensor(queries).to(device, torch.float32)
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2 or q.shape[1] != self.lang_dim:
            raise FeatureSpaceError(f"queries must be (Q, {self.lang_dim}) in {self.text_model} space, "
                                    f"got {tuple(q.shape)}")
        return q

    def project_queries(self, queries: np.ndarray | torch.Tensor, device: str | torch.device = "cpu",
                        pca: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The cosine's query side in stored-feature space: ``(Vᵀq̂ (Q, k), q̂ᵀm (Q,))`` for unit
        queries ``q̂`` and the PCA basis ``V``, mean ``m`` (computed in float64, returned float32);
        ``(q̂, None)`` without PCA or with ``pca=False``. The cosine with a stored row ``y`` is
        then ``(yᵀ(Vᵀq̂) + q̂ᵀm) / |V·y + m|``."""
        qn = torch.nn.functional.normalize(self.check_queries(queries, device), dim=1)
        if not pca or self.pca is None:
            return qn, None
        m, v = self.pca.torch_basis(torch.device(device), torch.float32)
        q64 = qn.double()
        return (q64 @ v.double()).float(), (q64 @ m.double()).float()

    @torch.inference_mode()
    def similarity(self, map_feats: np.ndarray | torch.Tensor, queries: np.ndarray | torch.Tensor, chunk: int = 65536,
                   device: str | torch.device = "cpu") -> torch.Tensor:
        """Exact cosine similarity ``(Q, N)`` between language-space ``queries`` ``(Q, lang_dim)``
        and stored map features ``(N, dim)`` mapped to language space.

        Without a nonlinear head and with PCA, the cosine is computed in PCA space: with
        ``x = V·y + m``, ``qᵀx = (Vᵀq)ᵀy + qᵀm`` and ``|x|² = |y|² + 2·yᵀ(Vᵀm) + |m|²``
        (V orthonormal), so no ``N × in_dim`` decompression happens. Rows of zero norm give 0.
        """
        dev = torch.device(device)
        y = torch.as_tensor(map_feats).to(dev, torch.float32)
        if y.ndim != 2 or y.shape[1] != self.dim:
            raise FeatureSpaceError(f"map features must be (N, {self.dim}), got {tuple(y.shape)}")
        if self.head_config is None and self.pca is not None:
            qv, qm = self.project_queries(queries, dev)   # (Q, k), (Q,)
            assert qm is not None                          # with the PCA, q̂ᵀm is always there
            out = torch.empty(qv.shape[0], y.shape[0], device=dev)
            m, v = self.pca.torch_basis(dev, torch.float32)
            m64, v64 = m.double(), v.double()
            vm = (v64.T @ m64).float()                # (k,)
            mm = float(m64 @ m64)
            for i in range(0, y.shape[0], chunk):
                yc = y[i:i + chunk]
                n2 = (yc * yc).sum(1) + 2.0 * (yc @ vm) + mm
                inv = torch.where(n2 > 1e-20, n2.clamp_min(1e-20).rsqrt(), torch.zeros_like(n2))
                out[:, i:i + chunk] = (yc @ qv.T + qm).T * inv
            return out
        qn, _ = self.project_queries(queries, dev, pca=False)
        out = torch.empty(qn.shape[0], y.shape[0], device=dev)
        for i in range(0, y.shape[0], chunk):
            x = self.to_language(y[i:i + chunk], device=dev)
            out[:, i:i + chunk] = qn @ torch.nn.functional.normalize(x, dim=1).T
        return out

    @torch.inference_mode()
    def prepare(self, map_feats: np.ndarray | torch.Tensor, device: str | torch.device = "cpu", chunk: int = 65536,
                workspace: torch.Tensor | None = None,
                max_cache_bytes: int = 1 << 28) -> "PreparedFeatures":
        """Map features ``(N, dim)`` prepared for many queries: what does not depend on the
        query is computed once, so :meth:`PreparedFeatures.similarity` equals
        :meth:`similarity` (same cosine, float32) at the cost of one ``(N×dim)·(dim×Q)``
        matmul and two passes over the ``(N, Q)`` result.

        * no language head: ``Y`` = the features as float32 (row-major ``(N, dim)``,
          ``4·dim·N`` bytes: ``map_feats`` itself when it already is contiguous float32 on
          ``device`` — it must then not change while the result is used —, else a copy into
          ``workspace``, a flat float32 tensor from an earlier :meth:`PreparedFeatures.storage`,
          when big enough) and ``s = 1/|x|``
          (0 for zero rows) with ``|x|² = |y|² + 2·yᵀ(Vᵀm) + |m|²``; a query is
          ``(Y·(Vᵀq̂) + q̂ᵀm)·s``.
        * with a head: the normalised language-space features are cached when they take at
          most ``max_cache_bytes``, else each query maps the stored features in chunks.
        """
        dev = torch.device(device)
        y = torch.as_tensor(map_feats)
        if y.ndim != 2 or y.shape[1] != self.dim:
            raise FeatureSpaceError(f"map features must be (N, {self.dim}), got {tuple(y.shape)}")
        n = y.shape[0]
        if self.head_config is None:
            need = n * self.dim
            if y.dtype == torch.float32 and y.device == dev and y.is_contiguous() and workspace is None:
                flat = y.view(-1)
            elif workspace is not None and workspace.dtype == torch.float32 and workspace.device == dev \
                    and workspace.numel() >= need:
                flat = workspace
            else:
                flat = torch.empty(max(need, 1), dtype=torch.float32, device=dev)
            y32 = flat[:need].view(n, self.dim)
            if y32.data_ptr() != y.data_ptr() or y.dtype != torch.float32:
                y32.copy_(y)
            n2 = torch.linalg.vector_norm(y32, dim=1).square_()
            if self.pca is not None:
                m, v = self.pca.torch_basis(dev, torch.float32)
                vm = (v.double().T @ m.double()).float()       # (k,)  Vᵀm
                n2.addmv_(y32, vm, alpha=2.0)                   # |V·y + m|² (V orthonormal)
                n2 += float(m.double() @ m.double())
            inv = torch.where(n2 > 1e-20, n2.clamp_min(1e-20).rsqrt(), torch.zeros_like(n2))
            return PreparedFeatures(self, dev, n, y32, inv, flat)
        if n * self.lang_dim * 4 <= max_cache_bytes:
            lang = torch.empty((n, self.lang_dim), dtype=torch.float32, device=dev)
            for i in range(0, n, chunk):
                x = self.to_language(y[i:i + chunk], device=dev)
                lang[i:i + chunk] = torch.nn.functional.normalize(x, dim=1)
            return PreparedFeatures(self, dev, n, lang, None, None)
        return PreparedFeatures(self, dev, n, None, None, None, raw=y)

    def embed_queries(self, texts: Sequence[str], text_encoder: Any, templates: str = "none") -> torch.Tensor:
        """Embed query strings with ``text_encoder`` (must match :attr:`text_model`): ``(Q, lang_dim)``."""
        name = getattr(text_encoder, "name", None)
        if name != self.text_model:
            raise FeatureSpaceError(f"feature space {self.id} expects '{self.text_model}' text embeddings, "
                                    f"got a '{name}' text encoder")
        q = text_encoder.encode_labels(list(texts), templates=templates)
        if q.shape[-1] != self.lang_dim:
            raise FeatureSpaceError(f"text encoder gives {q.shape[-1]}-d embeddings, space needs {self.lang_dim}")
        return q


class PreparedFeatures:
    """Map features of one :class:`FeatureSpace` prepared for repeated queries (see
    :meth:`FeatureSpace.prepare`). Read-only after construction; ``len()`` = N."""

    def __init__(self, space: FeatureSpace, device: torch.device, n: int, feats: torch.Tensor | None,
                 inv_norm: torch.Tensor | None, storage: torch.Tensor | None, raw: torch.Tensor | None = None):
        self.space, self.device, self.n = space, device, int(n)
        self._y, self._inv, self._storage, self._raw = feats, inv_norm, storage, raw

    def __len__(self) -> int:
        return self.n

    def storage(self) -> torch.Tensor | None:
        """The flat float32 buffer behind the prepared features (pass as ``workspace``)."""
        return self._storage

    @torch.inference_mode()
    def similarity(self, queries: np.ndarray | torch.Tensor) -> torch.Tensor:
        """``(Q, N)`` float32 cosine of language-space ``queries`` ``(Q, lang_dim)`` with the
        prepared features (equal to :meth:`FeatureSpace.similarity` up to float32 rounding;
        may be a transposed view)."""
        fs = self.space
        if self._y is None:
            assert self._raw is not None                   # prepared without a cache keeps the raw features
            return fs.similarity(self._raw, fs.check_queries(queries, self.device), device=self.device)
        qn, qm = fs.project_queries(queries, self.device, pca=self._inv is not None)
        if self.n == 0:
            return torch.zeros((qn.shape[0], 0), dtype=torch.float32, device=self.device)
        if qn.shape[0] == 1:
            out = torch.mv(self._y, qn[0])[:, None]                           # (N, 1)
        else:
            out = self._y @ qn.T                                              # (N, Q)
        if qm is not None:
            out += qm
        if self._inv is not None:
            out *= self._inv[:, None]
        return out.T


# ------------------------------------------------------------- sharing one map
def head_digest(fs: FeatureSpace) -> str:
    """sha256 (16 hex) over the language head's config and weights ("" without a head)."""
    if fs.head_config is None or fs.head_state is None:
        return ""
    h = hashlib.sha256()
    h.update(repr(sorted(fs.head_config.to_dict().items())).encode())
    for k in sorted(fs.head_state):
        v = np.ascontiguousarray(fs.head_state[k], dtype="<f4")
        h.update(k.encode())
        h.update(np.array(v.shape, "<i8").tobytes())
        h.update(v.tobytes())
    return h.hexdigest()[:16]


def encoder_family(fs: FeatureSpace) -> str:
    """What must match for two spaces to share one map: encoder name, version, input
    dimension, text model and language head (``name-version-in_dim-text_model-head``)."""
    return f"{fs.encoder_name}-{fs.encoder_version}-{fs.in_dim}-{fs.text_model}-{head_digest(fs) or 'nohead'}"


def compatibility(map_fs: FeatureSpace, robot_fs: FeatureSpace, reproject: bool = True) -> str:
    """"" when frames in ``robot_fs`` can join a map in ``map_fs``, else one line saying why.
    (The feature-space id names encoder, version and basis but not the text model or the
    head, so equal ids are checked like any other pair.)"""
    diffs = []
    for what, a, b in (("encoder", robot_fs.encoder_name, map_fs.encoder_name),
                       ("encoder version", robot_fs.encoder_version, map_fs.encoder_version),
                       ("encoder dimension", robot_fs.in_dim, map_fs.in_dim),
                       ("text model", robot_fs.text_model, map_fs.text_model)):
        if a != b:
            diffs.append(f"{what} {a} (map: {b})")
    if not diffs and head_digest(robot_fs) != head_digest(map_fs):
        diffs.append("language head differs")
    if diffs:
        return "different encoder family: " + ", ".join(diffs)
    if not reproject and robot_fs.id != map_fs.id:
        return "another PCA basis and fleet.reproject=false"
    return ""
