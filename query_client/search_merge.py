"""Merge several mapper shards' answers to one search or occupancy request into one answer
(the planners' side of ``query_client.merge``; docs/key_space.md#shards).

Each reply carries its shard's info as the Zenoh attachment (``common.robot_messages``: name, region,
tiles, voxel size, search-volume parameters). Merged, as one mapper holding the whole map
would answer:

* **instance ids** are unique across the site: an instance of shard ``east`` with the shard's
  own id 7 is ``"east:7"`` (``<shard>:<n>``; a mapper without ``shard.name`` keeps its integer
  ids), in ``found`` and in ``events`` (``id``, ``parent``, ``merged``); each instance and event
  names its ``shard``;
* **found**: instances of the same target from different shards whose boxes touch (within
  one voxel) are one object seen from both sides of a border: it keeps the id of the part
  whose centroid lies in its own shard's region (else of the largest part), lists every part's
  id in ``parts``, and has the union box, the voxel-weighted centroid, the best confidence
  and the parts' voxels summed; ranked as a mapper ranks (confidence to 3 decimals, size), cut
  to ``max_instances``;
* **look_next**: every shard's goals ranked by score, goals within one voxel of a better one
  dropped, cut to ``max_goals``; each names its ``shard``; equal scores rank by shard name
  (the same order whatever order the replies arrived in);
* **beyond**: rays de-duplicated by (target, origin voxel, direction bin) keeping the best,
  estimates ranked, the search volume recomputed as one union of the best rays' cones;
* **occupancy** (box, slice, points on the same grid): each cell from the shards whose region
  holds its centre (occupied if one says occupied, else free if one says free); where those
  know nothing, from the others the same way; ``dist`` the nearest over all shards. A request
  that lies in no known shard's region raises :class:`NoShardOwns`.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from common.cones import cone_union_volume
from common.search_messages import OccupancyReply, OccupancyRequest, SearchReply, SearchRequest
from common.shard_routing import ShardRegion
from query_client.merge import RAY_DIR_BIN, best_unique, half_voxel_key, touching_groups


class NoShardOwns(ValueError):
    """A request for an area no shard owns (one line, naming the shards' regions)."""


def qualify(shard: str, local_id) -> int | str:
    """Site-wide instance id: ``"<shard>:<n>"`` for a named shard, the mapper's own id otherwise."""
    return f"{shard}:{int(local_id)}" if shard else int(local_id)


def _regions(infos: Sequence[dict]) -> list[ShardRegion]:
    return [ShardRegion.from_info(i) for i in infos]


def no_owner(what: str, lo: Sequence[float], hi: Sequence[float], regions: Sequence[ShardRegion]) -> NoShardOwns:
    """The one-line error of a request for ``[lo, hi]`` that none of ``regions`` owns."""
    lo_s = ", ".join(f"{v:g}" for v in lo)
    hi_s = ", ".join(f"{v:g}" for v in hi)
    return NoShardOwns(f"{what} [{lo_s}]..[{hi_s}] lies in no shard's region ("
                       f"{'; '.join(r.describe() for r in regions)}): ask inside one, or run a shard owning it "
                       "(shard.region / shard.tiles)")


def check_owned(what: str, lo: Sequence[float], hi: Sequence[float], regions: Sequence[ShardRegion]) -> None:
    """Raise :class:`NoShardOwns` when the x/y box ``[lo, hi]`` meets none of ``regions``."""
    if regions and not any(r.intersects_box(lo, hi) for r in regions):
        raise no_owner(what, lo, hi, regions)


# ------------------------------------------------------------------ search
def _found(parts: list[tuple[list[dict], str, ShardRegion, float]], limit: int) -> list[dict]:
    rows: list[tuple[dict, int, ShardRegion]] = []
    for k, (found, name, reg, _) in enumerate(parts):
        for f in found:
            g = dict(f, id=qualify(name, f["id"]), shard=name)
            rows.append((g, k, reg))
    vox = max((p[3] for p in parts), default=0.0)
    out = []
    for target in dict.fromkeys(r[0]["target"] for r in rows):
        sel = [r for r in rows if r[0]["target"] == target]
        lo = np.array([r[0]["box_min"] for r in sel], np.float64).reshape(-1, 3)
        hi = np.array([r[0]["box_max"] for r in sel], np.float64).reshape(-1, 3)
        for members in touching_groups(lo, hi, np.array([r[1] for r in sel]), vox * 0.51 + 1e-9):
            ms = [sel[i] for i in members]
            if len(ms) == 1:
                out.append(ms[0][0])
                continue
            own = [m for m in ms if m[2].owns_xyz(np.asarray(m[0]["centroid"]))[0]] or ms
            rep = max(own, key=lambda m: (m[0]["voxels"], -m[1]))[0]
            w = np.array([m[0]["voxels"] for m in ms], np.float64)
            c = np.array([m[0]["centroid"] for m in ms], np.float64)
            g = dict(rep, centroid=[float(v) for v in (c * w[:, None]).sum(0) / max(w.sum(), 1.0)],
                     box_min=[float(v) for v in lo[members].min(0)], box_max=[float(v) for v in hi[members].max(0)],
                     confidence=max(float(m[0]["confidence"]) for m in ms), voxels=int(w.sum()),
                     observations=max(int(m[0]["observations"]) for m in ms),
                     parts=[rep["id"], *sorted((m[0]["id"] for m in ms if m[0] is not rep), key=str)])
            out.append(g)
    out.sort(key=lambda i: (-round(float(i["confidence"]), 3), -int(i["voxels"]), str(i["id"])))
    return out[:limit]


def _goals(parts: list[tuple[list[dict], str, ShardRegion, float]], limit: int) -> list[dict]:
    goals = sorted((dict(g, shard=name) for gs, name, _, _ in parts for g in gs), key=lambda g: g["shard"])
    if not goals:
        return []
    vox = max((p[3] for p in parts), default=0.0)
    pos = np.array([g["position"] for g in goals], np.float64).reshape(-1, 3)
    keep = best_unique(np.array([g["score"] for g in goals], np.float64), half_voxel_key(pos, 2 * vox), limit)
    return [goals[i] for i in keep]


def _beyond(replies: list[SearchReply], infos: list[dict], names: list[str], n_targets: int) -> dict:
    rays = [dict(r, shard=n) for rep, n in zip(replies, names, strict=True) for r in rep.beyond.get("rays", [])]
    ests = sorted((dict(e, shard=n) for rep, n in zip(replies, names, strict=True)
                   for e in rep.beyond.get("estimates", [])), key=lambda e: -float(e["score"]))
    vols = [float(rep.beyond.get("search_volume_m3", 0.0)) for rep in replies]
    if not rays:
        return dict(rays=[], estimates=ests[:10], search_volume_m3=max(vols, default=0.0))
    vox = float(next((i["vox_size"] for i in infos if "vox_size" in i), 0.0))
    o = np.array([r["origin"] for r in rays], np.float64).reshape(-1, 3)
    d = np.array([r["direction"] for r in rays], np.float64).reshape(-1, 3)
    s = np.array([r["score"] for r in rays], np.float64)
    tgt = np.unique([str(r.get("target", "")) for r in rays], return_inverse=True)[1].reshape(-1, 1)
    dbin = np.round(d / RAY_DIR_BIN).astype(np.int64)
    keep = best_unique(s, np.concatenate([tgt, half_voxel_key(o, vox), dbin], axis=1), max(10, 2 * n_targets))
    info = next((i for i in infos if "half_angle_deg" in i and "search_range_m" in i), None)
    vol = max(vols, default=0.0)
    if info is not None:
        best = best_unique(s, np.concatenate([half_voxel_key(o, vox), dbin], axis=1), int(info.get("search_rays", 10)))
        vol = float(cone_union_volume(o[best], d[best], float(info["half_angle_deg"]), float(info["search_range_m"]),
                                      float(info.get("search_cell_m", 2.0)),
                                      max_cells=int(info.get("search_samples", 100_000))))
    return dict(rays=[rays[i] for i in keep], estimates=ests[:10], search_volume_m3=vol)


def _events(rep: SearchReply, name: str) -> list[dict]:
    out = []
    for e in rep.events:
        g = dict(e, id=qualify(name, e["id"]), shard=name)
        if "parent" in e:
            g["parent"] = qualify(name, e["parent"])
        if "merged" in e:
            g["merged"] = [qualify(name, i) for i in e["merged"]]
        out.append(g)
    return out


def merge_search_replies(replies: list[tuple[SearchReply, dict]], req: SearchRequest) -> SearchReply:
    """One reply from the ``(reply, shard info)`` of several shards (module doc). A lone
    reply of a mapper without a shard name is returned as it is."""
    if not replies:
        raise ValueError("nothing to merge")
    infos = [i or {} for _, i in replies]
    names = [str(i.get("shard", "")) for i in infos]
    reps = [r for r, _ in replies]
    if len(replies) == 1 and not names[0]:
        return reps[0]
    regions = _regions(infos)
    parts = [(r.found, n, g, float(i.get("vox_size", 0.0))) for r, n, g, i in zip(reps, names, regions, infos,
                                                                                   strict=True)]
    goal_parts = [(r.look_next, n, g, float(i.get("vox_size", 0.0))) for r, n, g, i in zip(reps, names, regions,
                                                                                          infos, strict=True)]
    return SearchReply(
        id=reps[0].id, found=_found(parts, req.max_instances), look_next=_goals(goal_parts, req.max_goals),
        beyond=_beyond(reps, infos, names, len(req.targets)),
        events=[e for r, n in zip(reps, names, strict=True) for e in _events(r, n)],
        frames_mapped=int(sum(r.frames_mapped for r in reps)), map_version=int(sum(r.map_version for r in reps)),
        timings_ms={"total": max(float(r.timings_ms.get("total", 0.0)) for r in reps), "shards": float(len(reps))})


# ------------------------------------------------------------------ occupancy
def _cell_centres(rep: OccupancyReply, req: OccupancyRequest) -> np.ndarray:
    """(M, 3) centres of the reply's cells, in the order of ``states.reshape(-1)``."""
    if rep.kind == "points":
        return np.asarray(req.points, np.float64).reshape(-1, 3)
    shape = np.shape(rep.states)
    axes = [float(rep.origin[k]) + (np.arange(shape[k]) + 0.5) * float(rep.cell_m) for k in range(len(shape))]
    if rep.kind == "slice":
        axes.append(np.array([0.5 * (req.z_band[0] + req.z_band[1])]) if req.z_band else np.zeros(1))
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([a.reshape(-1) for a in g], axis=1)


def _combine(states: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per column of (K, M) ``states`` over rows where ``mask``: 1 if any occupied, else 0 if any
    free, else -1."""
    occ = np.any((states == 1) & mask, axis=0)
    free = np.any((states == 0) & mask, axis=0)
    return np.where(occ, 1, np.where(free, 0, -1)).astype(np.int8)


def request_extent(req: OccupancyRequest) -> tuple[list[float], list[float]]:
    """The x/y box an occupancy request covers (points: their bounding box)."""
    if req.kind == "points":
        p = np.asarray(req.points, np.float64).reshape(-1, 3)
        if not len(p):
            return [0.0, 0.0], [0.0, 0.0]
        return p[:, :2].min(0).tolist(), p[:, :2].max(0).tolist()
    return list(req.box_min or [])[:2], list(req.box_max or [])[:2]


def merge_occupancy(replies: list[tuple[OccupancyReply, dict]], req: OccupancyRequest,
                    others: Sequence[dict] = ()) -> OccupancyReply:
    """One occupancy reply from several shards' (module doc). ``others``: shard infos of known
    shards that did not answer (their regions count as owned). Raises :class:`NoShardOwns` when
    no cell lies in a known shard's region, ``ValueError`` when the shards' grids differ."""
    if not replies:
        raise ValueError("nothing to merge")
    reps = [r for r, _ in replies]
    regions = _regions([i or {} for _, i in replies])
    base = reps[0]
    for r in reps[1:]:
        if (r.kind != base.kind or np.shape(r.states) != np.shape(base.states)
                or not np.allclose(r.origin, base.origin) or abs(r.cell_m - base.cell_m) > 1e-9):
            raise ValueError(f"shards answered different {base.kind} grids ({np.shape(base.states)} at {base.origin} "
                             f"vs {np.shape(r.states)} at {r.origin}); give every shard the same map.vox_size")
    centres = _cell_centres(base, req)
    own = np.stack([g.owns_xyz(centres) for g in regions]) if len(centres) else np.zeros((len(reps), 0), bool)
    known = [*regions, *_regions(list(others))]
    if len(centres) and not any(g.owns_xyz(centres).any() for g in known):
        lo, hi = request_extent(req)
        raise no_owner(f"occupancy {req.kind}", lo, hi, known)
    if len(reps) == 1:
        return dataclasses.replace(base)
    st = np.stack([np.asarray(r.states, np.int8).reshape(-1) for r in reps])
    by_owner = _combine(st, own)
    merged = np.where(by_owner != -1, by_owner, _combine(st, ~own)).astype(np.int8)
    dist = None
    if base.dist is not None:
        dist = np.min(np.stack([np.asarray(r.dist, np.float64) for r in reps]), axis=0)
    return OccupancyReply(kind=base.kind, states=merged.reshape(np.shape(base.states)), origin=list(base.origin),
                          cell_m=base.cell_m, dist=dist, frames_mapped=int(sum(r.frames_mapped for r in reps)),
                          map_version=int(sum(r.map_version for r in reps)))
