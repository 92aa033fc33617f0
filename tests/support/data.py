"""Small generators and brute-force oracles shared by several test files."""
from __future__ import annotations

import numpy as np
import torch

from common.feature_space import FeatureSpace
from common.pca import PCA
from semantic_map import cell_keys


def low_rank_pca(d=32, k=8, seed=0, n=2000):
    """(a ``k``-dim PCA basis fitted on them, ``n`` samples of rank-6 data plus noise in ``d`` dims)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 6)) @ rng.normal(size=(6, d)) + 0.1 * rng.normal(size=(n, d)) + rng.normal(size=d)
    return PCA.fit(X, k), X


def bfs_components(ijk):
    """Connected components (26-neighbourhood) of integer voxels ``ijk`` by brute-force BFS: the
    oracle of the clustering tests. One label per row."""
    idx = {tuple(v): i for i, v in enumerate(ijk.tolist())}
    lab = -np.ones(len(ijk), int)
    c = 0
    for i in range(len(ijk)):
        if lab[i] >= 0:
            continue
        stack = [i]
        lab[i] = c
        while stack:
            j = stack.pop()
            x, y, z = ijk[j]
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for dz in (-1, 0, 1):
                        k = idx.get((x + dx, y + dy, z + dz))
                        if k is not None and lab[k] < 0:
                            lab[k] = c
                            stack.append(k)
        c += 1
    return lab


def query_map(n_side=14, n_rays=300, seed=0):
    """(map, feature space, mapper config, PCA inputs): an ``n_side``³ block of voxels with
    low-rank features and ``n_rays`` random frontier rays, for the query tests."""
    from mapper.service_config import load_mapper_config
    from mapper.service_map import create_map

    p, X = low_rank_pca(seed=seed, n=3000)
    fs = FeatureSpace("label", "1", 32, pca=p)
    cfg = load_mapper_config(None, ["preset=throughput", "map.vox_size=0.5"])
    m = create_map(cfg, fs)
    g = torch.Generator().manual_seed(seed)
    ijk = torch.stack(torch.meshgrid(*[torch.arange(n_side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    xyz = (ijk.float() + 0.5) * 0.5
    # two strongly matching blobs so that clusters are non-trivial
    feats = torch.from_numpy(p.compress(X[torch.randint(0, 3000, (len(xyz),), generator=g).numpy()]
                                        .astype(np.float32)))
    m.fuse_samples(xyz, torch.rand((len(xyz), 3), generator=g), feats)
    fk = torch.unique(cell_keys.pack(torch.randint(-50, 50, (n_rays, 3), generator=g)))
    r = fk.numel()
    z = torch.zeros(r, dtype=torch.int64)
    m.replace_ray_bins({"fkey": fk, "tbin": z, "pbin": z.clone(), "feat": torch.randn((r, p.out_dim), generator=g),
                            "weight": torch.ones(r),
                            "dsum": torch.nn.functional.normalize(torch.randn((r, 3), generator=g), dim=1)})
    return m, fs, cfg, X
