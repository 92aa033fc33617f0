"""Occupancy backends side by side: update / query / frontier / prune / ray timings.

``run_occupancy_bench(n_frames)`` builds synthetic depth-camera frames in a box room with
pillars (free voxels along each ray, occupied voxel at each hit, +occ_inc / -1), feeds
the same frames to every available backend in one run, times each operation and checks
that the backends end with identical maps, queries and frontier sets. Timings are
medians over frames, in milliseconds (``time.perf_counter``). Pure computation, no I/O.
"""
from __future__ import annotations

import math
import statistics
import time
from functools import partial
from typing import Any

import numpy as np
import torch

from common.conventions import voxel_index
from semantic_map.occupancy import make_occupancy, vdb_available


def _room_hits(o: np.ndarray, d: np.ndarray, half: np.ndarray, pillars: np.ndarray,
               pillar_r: float) -> np.ndarray:
    """Distance from o along unit rays d to the room's inner walls (axis-aligned box
    [-half, half], floor z=0, ceiling 2*half_z) or the first vertical pillar."""
    lo = np.array([-half[0], -half[1], 0.0])
    hi = np.array([half[0], half[1], 2 * half[2]])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf)).min(1)
    t = t_wall
    for cx, cy in pillars:  # infinite vertical cylinders: solve in xy
        px, py = o[:, 0] - cx, o[:, 1] - cy
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = 2 * (px * d[:, 0] + py * d[:, 1])
        c = px ** 2 + py ** 2 - pillar_r ** 2
        disc = b * b - 4 * a * c
        ok = (disc > 0) & (a > 1e-12)
        with np.errstate(invalid="ignore", divide="ignore"):
            tc = (-b - np.sqrt(np.where(ok, disc, 0))) / (2 * np.where(ok, a, 1))
        t = np.where(ok & (tc > 0) & (tc < t), tc, t)
    return t


def make_frames(n_frames: int, rays: int = 20000, vox: float = 0.05, max_range: float = 8.0,
                seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Synthetic frames: list of (free ijk (F, 3) int64 unique, occupied ijk (O, 3) int64
    with duplicates), from a camera circling a 16 x 16 x 3 m room."""
    rng = np.random.default_rng(seed)
    half = np.array([8.0, 8.0, 1.5])
    pillars = rng.uniform(-6, 6, size=(6, 2))
    frames = []
    for f in range(n_frames):
        ang = 2 * math.pi * f / max(n_frames, 8)
        o = np.array([3.5 * math.cos(ang), 3.5 * math.sin(ang), 1.2])
        yaw = ang + math.pi / 2
        # rays within a 90 x 60 degree frustum around the heading
        az = yaw + rng.uniform(-math.pi / 4, math.pi / 4, rays)
        el = rng.uniform(-math.pi / 6, math.pi / 6, rays)
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
        origins = np.broadcast_to(o, d.shape)
        t = _room_hits(origins, d, half, pillars, 0.4)
        hit = t <= max_range
        t = np.minimum(t, max_range)
        occ = voxel_index(origins[hit] + t[hit, None] * d[hit], vox)
        # free samples every half voxel up to one voxel before the hit
        steps = np.arange(0.0, max_range, vox / 2)
        pts = origins[:, None, :] + steps[None, :, None] * d[:, None, :]
        valid = steps[None, :] < (t[:, None] - vox)
        free = np.unique(voxel_index(pts[valid], vox), axis=0)
        frames.append((free, occ))
    return frames


def _ms(fn) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return (time.perf_counter() - t0) * 1e3, out


def run_occupancy_bench(n_frames: int = 10, rays: int = 20000, vox: float = 0.05,
                        lo: int = -5, hi: int = 30, occ_inc: int = 6, prune_every: int = 5,
                        prune_tol: int = 2, n_query: int = 200_000, n_rays: int = 5000,
                        frontier: tuple[int, int, int, int] = (4, 2, 0, 1), backends: list[str] | None = None,
                        seed: int = 0) -> dict:
    """Time both occupancy backends on the same synthetic frames; returns a JSON-able
    dict: per backend median ms for update (free then occupied), query, frontiers (bbox
    of the frame), prune, first_blocked, plus map size, memory and an identity check."""
    if backends is None:
        backends = ["torch"] + (["vdb"] if vdb_available() else [])
    frames = make_frames(n_frames, rays, vox, seed=seed)
    rng = np.random.default_rng(seed + 1)
    out: dict = {"n_frames": n_frames, "rays_per_frame": rays, "vox": vox,
                 "frontier_args": list(frontier), "backends": {}}
    final = {}
    ro = np.tile(np.array([[3.5, 0.0, 1.2]]), (n_rays, 1))   # first camera position (free)
    rd = rng.normal(size=(n_rays, 3))
    for name in backends:
        g = make_occupancy(vox, lo, hi, backend=name)
        times: dict[str, list[float]] = {k: [] for k in
                                         ("update", "query", "frontiers", "prune", "first_blocked")}
        n_front = []
        for f, (free, occ) in enumerate(frames):
            ijk = np.concatenate([free, occ])
            inc = np.concatenate([np.full(len(free), -1), np.full(len(occ), occ_inc)])
            ijk_t = torch.from_numpy(ijk.astype(np.int32))
            inc_t = torch.from_numpy(inc.astype(np.int32))
            times["update"].append(_ms(partial(g.update, ijk_t, inc_t))[0])
            bbox = (tuple(ijk.min(0).tolist()), tuple(ijk.max(0).tolist()))
            ms, fr = _ms(partial(g.frontiers, *frontier, bbox=bbox))
            times["frontiers"].append(ms)
            n_front.append(int(fr.shape[0]))
            if prune_every and (f + 1) % prune_every == 0:
                times["prune"].append(_ms(partial(g.prune, prune_tol))[0])
        act_ijk, act_val = g.active()
        q_rng = np.random.default_rng(seed + 2)
        known = act_ijk[torch.from_numpy(q_rng.integers(0, len(act_ijk), n_query // 2))]
        rand = torch.from_numpy(q_rng.integers(act_ijk.min(0).values.numpy(),
                                               act_ijk.max(0).values.numpy() + 1,
                                               size=(n_query - n_query // 2, 3)))
        q = torch.cat([known, rand]).to(torch.int32)
        for _ in range(3):
            ms, qv = _ms(partial(g.query, q))
            times["query"].append(ms)
        for _ in range(3):
            ms, fb = _ms(partial(g.first_blocked, ro, rd, 8.0))
            times["first_blocked"].append(ms)
        ms_all, fr_all = _ms(partial(g.frontiers, *frontier))
        final[name] = (act_ijk, act_val, qv, fb, fr_all)
        out["backends"][name] = {
            "ms": {k: (statistics.median(v) if v else None) for k, v in times.items()},
            "ms_frontiers_whole_map": ms_all,
            "num_active": g.num_active,
            "memory_bytes": g.memory_bytes(),
            "frontiers_per_frame_median": statistics.median(n_front) if n_front else 0,
            "frontiers_whole_map": int(fr_all.shape[0]),
        }
    if len(final) > 1:
        ref = final[backends[0]]
        out["identical"] = all(
            all(torch.equal(a, b) for a, b in zip(ref, other, strict=True)) for other in final.values())
        t, v = out["backends"].get("torch"), out["backends"].get("vdb")
        if t and v:
            out["speedup_vdb_over_torch"] = {
                k: (t["ms"][k] / v["ms"][k] if t["ms"][k] and v["ms"][k] else None)
                for k in t["ms"]}
    return out


if __name__ == "__main__":  # pragma: no cover - manual run
    import json

    print(json.dumps(run_occupancy_bench(6, rays=10000), indent=1))
