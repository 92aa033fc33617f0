"""``rayfronts edge fit-pca``: fit the PCA basis the edge compresses features with, offline,
over frames of a source (so every edge and the mapper share one fixed feature space)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

if TYPE_CHECKING:
    from common.frame import Frame
    from common.pca import PCA
    from edge.config import EdgeConfig

log = logging.getLogger("rayfronts.edge.fit_pca")


def fit_pca(cfg: EdgeConfig, out: str | Path, frames: int = 50, samples_per_frame: int = 4096,
            source: Iterable[Frame] | None = None) -> PCA:
    """Encode up to ``frames`` frames of ``cfg.source`` (or the iterable ``source``) with
    ``cfg.encoder`` and fit PCA-``cfg.pca.out_dim`` on sampled feature vectors; writes
    ``out`` (.npz, :meth:`common.pca.PCA.save`) and returns the :class:`~common.pca.PCA`."""
    import torch

    from common.pca import OnlinePCAFitter
    from encoders import make_encoder

    names = None
    if source is None:
        from edge.sources import open_source

        source = open_source(cfg.source)
        names = list(getattr(source, "class_names", None) or []) or None
    if cfg.pca.out_dim <= 0:
        raise ValueError("pca.out_dim must be > 0 to fit a basis")
    encoder = make_encoder(cfg.encoder, class_names=names)
    fitter = OnlinePCAFitter(cfg.pca.out_dim, max_frames=max(1, frames), samples_per_frame=samples_per_frame)
    n = 0
    for fr in source:
        with torch.inference_mode():
            feats = encoder.encode(fr.rgb, labels=fr.labels)
        n += 1
        if fitter.add(feats):
            break
    if n == 0:
        raise ValueError("the source yielded no frames")
    pca = fitter.fit()
    path = pca.save(out)
    log.info("PCA %d -> %d from %d frames written to %s (hash %s)", pca.in_dim, pca.out_dim, n, path,
             pca.content_hash)
    print(f"wrote {path} (PCA {pca.in_dim}->{pca.out_dim}, {n} frames, hash {pca.content_hash})")
    return pca
