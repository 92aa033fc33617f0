"""Merge the answers of several mapper shards to one query into one answer.

Each shard owns part of the world (``shard.*`` in the mapper config) and answers
``mapper/query`` from its own map; one Zenoh ``get`` reaches all of them and the client
merges (:func:`merge_results`), as one mapper holding the whole map would answer:

* **top voxels**: all shards' top lists, re-ranked by score (stable: ties keep the order of
  the replies), the same voxel (centre within half a voxel) from two shards kept once with
  its best score, cut to ``top_k``;
* **clusters**: a shard keeps the clusters of its voxels scoring at least
  ``lo + rel·(hi − lo)`` of *its* map; merged, the threshold is recomputed over all shards
  (``lo`` = the lowest shard minimum, ``hi`` the best cluster) and clusters of different
  shards whose boxes touch (within one voxel) are one cluster (the same object seen by the
  frames of two shards near a border): size-weighted centroid, box union, best score;
* **rays**: the rays of every shard (none is lost: a frame near a border may be mapped by a
  shard whose region does not hold its frontier), de-duplicated by (origin voxel, direction
  bin of ``RAY_DIR_BIN`` per unit-vector component) keeping the best score, re-ranked, cut
  to ``top_k``. A shard's frontiers at its region's border (where only the neighbour's frames
  explored) are kept too: they are still unexplored in that shard's map;
* **search volume**: the union of the cones of the ``search_rays`` best rays over all
  shards, with the shards' cone half-angle and range (``common.cones``), not a sum.

Shards report what the merge needs in their reply's attachment (``common.robot_messages``); a reply
without it (an older mapper) is merged with ``rel = 0.9`` and the largest shard volume.
"""
from __future__ import annotations

import numpy as np

from common.cones import cone_union_volume
from common.messages import QueryResult


def touching_groups(lo: np.ndarray, hi: np.ndarray, part: np.ndarray, tol: float) -> list[list[int]]:
    """Groups (lists of row indices, in row order) of boxes ``[lo, hi]`` (N, 3) joined where
    boxes of different ``part`` (N,) touch within ``tol`` (union-find over pairs)."""
    n = len(lo)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if part[i] != part[j] and np.all(lo[i] <= hi[j] + tol) and np.all(lo[j] <= hi[i] + tol):
                a, b = find(i), find(j)
                if a != b:
                    parent[b] = a
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return list(groups.values())


def _merge_clusters(xyz, size, extent, score, shard, vox: float):
    """Union clusters of different shards whose boxes touch (within ``vox``)."""
    lo, hi = xyz - extent / 2, xyz + extent / 2
    out = []
    for members in touching_groups(lo, hi, shard, vox * 0.51):
        m = np.array(members)
        w = size[m].astype(np.float64)
        c = (xyz[m] * w[:, None]).sum(0) / max(w.sum(), 1.0)
        blo, bhi = lo[m].min(0), hi[m].max(0)
        out.append((c, int(size[m].sum()), bhi - blo, float(score[m].max())))
    return out


#: ray de-duplication: bin of each unit-direction component (0.05 ~ 3 degrees)
RAY_DIR_BIN = 0.05


def half_voxel_key(xyz: np.ndarray, vox: float) -> np.ndarray:
    """Integer key per row of ``xyz`` (m): half-voxel bins, so voxel centres at ``(i + 0.5)·vox``
    or ``i·vox`` map to one key each despite float32 rounding; ``vox`` 0 = millimetres."""
    step = vox / 2 if vox > 0 else 1e-3
    return np.round(np.asarray(xyz, np.float64).reshape(-1, 3) / step).astype(np.int64)


def best_unique(scores: np.ndarray, keys: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best rows, best first (stable), each distinct key row once."""
    order = np.argsort(-scores, kind="stable")
    if not len(order):
        return order
    _, first = np.unique(keys[order], axis=0, return_index=True)
    return order[np.sort(first)][:max(0, int(k))]


def merge_results(replies: list[tuple[QueryResult, dict]], top_k: int) -> QueryResult:
    """One answer from the ``(result, shard info)`` replies of several shards (see module doc)."""
    if not replies:
        raise ValueError("nothing to merge")
    if len(replies) == 1:
        return replies[0][0]
    results = [r for r, _ in replies]
    infos = [i or {} for _, i in replies]
    k = int(top_k)
    out = QueryResult(id=results[0].id, query=results[0].query)
    out.frames_mapped = int(sum(r.frames_mapped for r in results))
    out.stamp = max(r.stamp for r in results)
    out.timings = {"total": max(float(r.timings.get("total", 0.0)) for r in results), "shards": float(len(results))}
    # top voxels
    vs = np.concatenate([r.voxel_score for r in results]).astype(np.float32)
    vx = np.concatenate([r.voxel_xyz for r in results]).astype(np.float32).reshape(-1, 3)
    vox = float(next((i["vox_size"] for i in infos if "vox_size" in i), 0.0))
    t = best_unique(vs, half_voxel_key(vx, vox), k)
    out.voxel_xyz, out.voxel_score = vx[t], vs[t]
    # clusters
    cs = np.concatenate([r.cluster_score for r in results]).astype(np.float32)
    if len(cs):
        cx = np.concatenate([r.cluster_xyz for r in results]).astype(np.float64).reshape(-1, 3)
        csz = np.concatenate([r.cluster_size for r in results]).astype(np.int64)
        cext = np.concatenate([r.cluster_extent for r in results]).astype(np.float64).reshape(-1, 3)
        shard = np.concatenate([np.full(len(r.cluster_score), i) for i, r in enumerate(results)])
        mins = [m for i in infos if (m := i.get("score_min")) is not None]
        rel = float(next((i["cluster_rel_score"] for i in infos if "cluster_rel_score" in i), 0.9))
        hi = float(cs.max())
        lo = float(min(mins)) if mins else float(cs.min())
        keep = cs >= lo + rel * (hi - lo) if hi > lo else cs >= hi
        merged = _merge_clusters(cx[keep], csz[keep], cext[keep], cs[keep], shard[keep], vox)
        merged.sort(key=lambda c: -c[3])
        merged = merged[:k]
        out.cluster_xyz = np.array([c[0] for c in merged], np.float32).reshape(-1, 3)
        out.cluster_size = np.array([c[1] for c in merged], np.int32)
        out.cluster_extent = np.array([c[2] for c in merged], np.float32).reshape(-1, 3)
        out.cluster_score = np.array([c[3] for c in merged], np.float32)
    # rays and the search volume: every shard's rays, each (origin voxel, direction bin) once
    rs = np.concatenate([r.ray_score for r in results]).astype(np.float32)
    ro = np.concatenate([r.ray_origin for r in results]).astype(np.float32).reshape(-1, 3)
    rd = np.concatenate([r.ray_direction for r in results]).astype(np.float32).reshape(-1, 3)
    dbin = np.round(rd.astype(np.float64) / RAY_DIR_BIN).astype(np.int64)
    t = best_unique(rs, np.concatenate([half_voxel_key(ro, vox), dbin], axis=1), k)
    out.ray_origin, out.ray_direction, out.ray_score = ro[t], rd[t], rs[t]
    info = next((i for i in infos if "half_angle_deg" in i and "search_range_m" in i), None)
    if info is None or not len(t):
        out.search_volume_m3 = max(float(r.search_volume_m3) for r in results)
    else:
        ns = min(int(info.get("search_rays", 10)), len(t))
        out.search_volume_m3 = cone_union_volume(ro[t[:ns]], rd[t[:ns]], float(info["half_angle_deg"]),
                                                 float(info["search_range_m"]), float(info.get("search_cell_m", 2.0)),
                                                 max_cells=int(info.get("search_samples", 100_000)))
    return out.validate()
