"""What the mapper process does with its map, kept free of Zenoh: create/load the map,
integrate a decoded frame, answer a query (voxel clusters, rays, search volume), build the
layers. World frame, metres, z up.
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from common.conventions import voxel_center, voxel_index
from common.messages import MessageError, QueryRequest, QueryResult

#: generic phrases a softmax query is normalised against (relevancy-style)
SOFTMAX_NEGATIVES = ("object", "things", "stuff", "texture")
SOFTMAX_TEMPERATURE = 100.0


# ------------------------------------------------------------------- map life
def create_map(cfg, fs):
    """A new RayFrontsMap for feature space ``fs`` with the service config's map section."""
    from mapper.map import RayFrontsMap

    return RayFrontsMap(cfg.map, fs.dim, fs.id, device=cfg.device, occupancy_backend=cfg.occupancy_backend)


def load_map(path, cfg, fs):
    from mapper.map import RayFrontsMap

    m = RayFrontsMap.load(path, device=cfg.device, occupancy_backend=cfg.occupancy_backend)
    got_id = getattr(m, "feature_space", "")
    if got_id and got_id != fs.id:
        raise MessageError(f"snapshot map space {got_id} != its feature_space file {fs.id}")
    return m


def integrate(m, frame, device="cpu") -> None:
    """Fuse one decoded (validated) frame into the map."""
    # decoded arrays are read-only views of the message: hand the map writable copies
    g = None if frame.global_feature is None else np.array(frame.global_feature)
    m.integrate(frame.pose, frame.intrinsics, frame.depth, np.array(frame.rgb), np.array(frame.features), g)


def flush(m) -> None:
    """Process whatever the map holds in its accumulation buffers."""
    m.flush()


def map_stats(m) -> dict:
    s = m.stats()
    return dict(s) if isinstance(s, dict) else {"stats": str(s)}


# --------------------------------------------------------------- map accessors
def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def voxel_arrays(m) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """``(xyz (N,3) float32 centres, features (N,D) tensor, rgb (N,3) uint8)``."""
    v = m.voxels()
    xyz = _np(v.xyz).astype(np.float32, copy=False)
    rgb = np.clip(_np(v.rgb).astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return xyz, v.features, rgb


def ray_arrays(m) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """``(origins (R,3), unit directions (R,3), features (R,D))``."""
    r = m.rays()
    return _np(r.origins).astype(np.float32), _np(r.directions).astype(np.float32), r.features


def frontier_xyz(m) -> np.ndarray:
    return _np(m.frontiers().centres).astype(np.float32).reshape(-1, 3)


def layer_arrays(m, layer: str, lcfg) -> tuple[dict, dict]:
    """Arrays and meta of one map layer, subsampled to the layer limits (seeded, stable)."""
    rng = np.random.default_rng(0)
    if layer == "voxels":
        xyz, _, rgb = voxel_arrays(m)
        n = len(xyz)
        if n > lcfg.max_voxels:
            idx = np.sort(rng.choice(n, lcfg.max_voxels, replace=False))
            xyz, rgb = xyz[idx], rgb[idx]
        return {"xyz": xyz, "rgb": rgb}, {"total": n, "vox_size": float(m.cfg.vox_size)}
    if layer == "frontiers":
        f = frontier_xyz(m)
        return {"xyz": f}, {"total": len(f)}
    if layer == "rays":
        o, d, _ = ray_arrays(m)
        n = len(o)
        if n > lcfg.max_rays:
            idx = np.sort(rng.choice(n, lcfg.max_rays, replace=False))
            o, d = o[idx], d[idx]
        return {"origin": o, "direction": d}, {"total": n}
    if layer == "occupancy":
        return {}, {k: v for k, v in map_stats(m).items() if isinstance(v, (int, float, str, bool))}
    raise MessageError(f"unknown layer {layer!r}")


# ------------------------------------------------------------------- queries
_TEXT_ENCODERS: dict = {}


def text_encoder(name: str, device="cpu", model_dir: str = ""):
    """The text model the feature space names (cached per process)."""
    key = (name, str(device), model_dir)
    if key not in _TEXT_ENCODERS:
        from common.text_encoders import make_text_encoder

        _TEXT_ENCODERS[key] = make_text_encoder(name, model_dir=model_dir or None, device=device)
    return _TEXT_ENCODERS[key]


def embed_request(fs, req: QueryRequest, device="cpu", model_dir: str = "") -> torch.Tensor:
    """(1, lang_dim) query vector in the feature space's language space."""
    if req.embedding is not None:
        e = torch.as_tensor(np.asarray(req.embedding, np.float32))
        if e.shape[-1] != fs.lang_dim:
            raise MessageError(f"embedding has {e.shape[-1]} dims, the map's language space has {fs.lang_dim}")
        return e.reshape(1, -1)
    if req.image is not None:
        raise MessageError(f"image queries need an image encoder on the mapper; feature space {fs.id} "
                           f"({fs.text_model}) has none — send text or an embedding")
    return fs.embed_queries([req.text], text_encoder(fs.text_model, device, model_dir)).reshape(1, -1)


def scores_for(fs, feats: torch.Tensor, q: torch.Tensor, softmax: bool, negatives: torch.Tensor | None,
               device="cpu") -> np.ndarray:
    if feats.shape[0] == 0:
        return np.zeros((0,), np.float32)
    if not softmax:
        return _np(fs.similarity(feats, q, device=device)[0]).astype(np.float32)
    qs = torch.cat([q, negatives]) if negatives is not None else q
    sim = fs.similarity(feats, qs, device=device)
    return _np(torch.softmax(SOFTMAX_TEMPERATURE * sim, dim=0)[0]).astype(np.float32)


_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                        if (i, j, k) > (0, 0, 0)], np.int64)  # 13 half-space offsets


def cluster_voxels(ijk: np.ndarray) -> np.ndarray:
    """26-connected components of a set of voxel indices → (M,) component label per voxel."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(ijk)
    if m == 0:
        return np.zeros((0,), np.int64)
    base = ijk.min(0) - 1
    span = ijk.max(0) - base + 2
    def pack(a):
        a = a - base
        return (a[:, 0] * span[1] + a[:, 1]) * span[2] + a[:, 2]
    keys = pack(ijk)
    order = np.argsort(keys)
    sk = keys[order]
    rows, cols = [], []
    for off in _NEIGHBOURS:
        nk = pack(ijk + off)
        pos = np.clip(np.searchsorted(sk, nk), 0, m - 1)
        hit = sk[pos] == nk
        rows.append(np.nonzero(hit)[0])
        cols.append(order[pos[hit]])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(m, m))
    _, labels = connected_components(g, directed=False)
    return labels.astype(np.int64)


def cone_union_volume(origins: np.ndarray, dirs: np.ndarray, half_angle_deg: float, range_m: float,
                      cell_m: float, max_cells: int = 400_000) -> float:
    """Volume (m³) of the union of cones (apex ``origins``, unit axes ``dirs``, half-angle,
    cut at axial distance ``range_m``), measured on a grid (cell centres inside count)."""
    if len(origins) == 0 or range_m <= 0:
        return 0.0
    th = math.radians(min(max(half_angle_deg, 0.1), 89.0))
    if len(origins) == 1:  # exact
        return float(math.pi * range_m ** 3 * math.tan(th) ** 2 / 3.0)
    r_base = range_m * math.tan(th)
    ends = origins + dirs * range_m
    lo = np.minimum(origins, ends).min(0) - r_base
    hi = np.maximum(origins, ends).max(0) + r_base
    vol_box = float(np.prod(hi - lo))
    cell = max(cell_m, (vol_box / max_cells) ** (1 / 3))
    axes = [np.arange(lo[i] + cell / 2, hi[i], cell, dtype=np.float32) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.zeros(len(pts), bool)
    cos_t = math.cos(th)
    for o, d in zip(origins.astype(np.float32), dirs.astype(np.float32)):
        v = pts - o
        t = v @ d
        nrm = np.linalg.norm(v, axis=1)
        inside |= (t > 0) & (t <= range_m) & (t >= nrm * cos_t)
    return float(inside.sum() * cell ** 3)


def answer_query(m, fs, req: QueryRequest, qcfg, device="cpu", model_dir: str = "") -> QueryResult:
    """Run ``req`` on map ``m``: voxel clusters, top voxels, top rays, search volume."""
    timings: dict[str, float] = {}
    t = time.perf_counter()
    q = embed_request(fs, req, device, model_dir)
    neg = None
    if req.softmax:
        neg = fs.embed_queries(list(SOFTMAX_NEGATIVES), text_encoder(fs.text_model, device, model_dir))
    timings["encode"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    xyz, feats, _ = voxel_arrays(m)
    vs = scores_for(fs, feats, q, req.softmax, neg, device)
    o, d, rf = ray_arrays(m)
    rs = scores_for(fs, rf, q, req.softmax, neg, device)
    timings["similarity"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    res = QueryResult(id=req.id, query=req.label)
    k = req.top_k
    if len(vs):
        top = np.argsort(-vs, kind="stable")[:k]
        res.voxel_xyz, res.voxel_score = xyz[top], vs[top]
        # clusters: the best candidates (relative to the map's score range), 26-connected
        cand = np.argsort(-vs, kind="stable")[:max(qcfg.cluster_candidates, k)]
        lo, hi = float(vs.min()), float(vs[cand[0]])
        keep = cand[vs[cand] >= lo + qcfg.cluster_rel_score * (hi - lo)] if hi > lo else cand[:1]
        vox = float(m.cfg.vox_size)
        ijk = voxel_index(xyz[keep].astype(np.float64), vox)
        lab = cluster_voxels(ijk)
        n_cl = int(lab.max()) + 1 if len(lab) else 0
        best = np.full(n_cl, -np.inf, np.float32)
        np.maximum.at(best, lab, vs[keep])
        order = np.argsort(-best, kind="stable")[:k]
        cx, cs, ce = [], [], []
        for c in order:
            sel = lab == c
            centres = voxel_center(ijk[sel], vox)
            cx.append(centres.mean(0))
            cs.append(int(sel.sum()))
            ce.append(centres.max(0) - centres.min(0) + vox)
        res.cluster_xyz = np.asarray(cx, np.float32).reshape(-1, 3)
        res.cluster_size = np.asarray(cs, np.int32)
        res.cluster_extent = np.asarray(ce, np.float32).reshape(-1, 3)
        res.cluster_score = best[order].astype(np.float32)
    if len(rs):
        top = np.argsort(-rs, kind="stable")[:k]
        res.ray_origin, res.ray_direction, res.ray_score = o[top], d[top], rs[top]
        ns = min(qcfg.search_rays, len(top))
        half = float(m.cone_half_angle())
        res.search_volume_m3 = cone_union_volume(o[top[:ns]], d[top[:ns]], half, qcfg.search_range_m,
                                                 qcfg.search_cell_m)
    timings["postprocess"] = (time.perf_counter() - t) * 1e3
    res.timings = timings
    return res
