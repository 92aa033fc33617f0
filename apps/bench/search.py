"""``rayfronts bench search``: planner-search and occupancy-query latency, in process.

For each map size (``--voxels 100k,1M,5M``) the query benchmark's map
(:func:`apps.bench.query.build_map`: that many semantic voxels with random features in a
PCA-``--dim`` label space and ``--rays`` semantic rays) also gets occupancy, frontiers and
real rays from ``--frames`` synthetic-world frames (random features of the same dimension,
so look-next has frontiers to score). Then, as the mapper answers a search
(:func:`mapper.search_answer.answer_search` on the query copy, the map read directly for
look-next):

* ``search_ms``: wall p50 / p95 of ``--queries`` searches for one target against the
  default background (the text embeddings cached after the first search, as in the
  mapper; the background's per-voxel log-sum-exp and each target's scores cached per
  copy of the map), ``search_cpu_ms`` the process CPU per search, and the stages' p50
  (``encode``, ``similarity``, ``instances``, ``look_next``, ``beyond``);
  ``search_cold_ms``: searches for a target vector never searched before (its scores a
  full pass over the copy, a new tracker);
* ``standing_ms``: standing searches refreshed after a map update (one more synthetic frame
  integrated and the copy synced, not timed; ``--standing-rounds`` updates of each kind,
  default :data:`STANDING_ROUNDS`), as the mapper's standing loop answers them:
  ``one`` the search of one robot, ``three`` those of three robots (the same target from
  three places) on one map version, ``ratio`` three / one (p50s);
* ``occupancy_ms``: the three occupancy queries the planners use (a 40 m × 40 m × 6 m box at
  the map's voxel size, a 2D costmap slice over 80 m × 80 m, 1000 points with a 1 m
  distance radius, after such queries until the occupied-cell index is current — at least
  :data:`WARM_POINT_QUERIES`, at most :data:`WARM_POINT_QUERIES_MAX` —, whose latencies are
  ``points_1000_r1m_first``: the index is built once they have read a share of the grid,
  :func:`planning.occupancy_queries.point_states`).

After the first search the objects made so far are frozen out of the garbage collector, as
the mapper process does after its start (:func:`mapper.service_config.freeze_startup_objects`).

Random features make the found instances a stress case (about one voxel in six above the
threshold, in one dense block), not a typical map.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from apps.bench.query import _count, _pct, _space, build_map, map_size_arguments

HELP = "search (found / look-next / beyond) and occupancy-query latency on 100k..5M-voxel maps, in process"

TARGETS = ("car", "tree", "bench", "person", "window")
#: map updates of each kind (one robot's, three robots' searches) in ``standing_ms``
STANDING_ROUNDS = 5
#: untimed point queries before the timed ones (``points_1000_r1m_first``: their latencies):
#: at least this many, more until the occupied-cell index is current (at most the second)
WARM_POINT_QUERIES = 10
WARM_POINT_QUERIES_MAX = 60


def add_arguments(parser: argparse.ArgumentParser) -> None:
    map_size_arguments(parser)
    parser.add_argument("--frames", type=int, default=12, help="synthetic-world frames for occupancy and frontiers")
    parser.add_argument("--queries", type=int, default=10, help="searches per map size")
    parser.add_argument("--standing-rounds", type=int, default=STANDING_ROUNDS,
                        help="map updates of each kind (one robot's, three robots' standing searches)")


def _add_frames(m, dim: int, n_frames: int, first: int = 0, total: int = 0) -> None:
    """Integrate ground frames ``first .. first + n_frames`` of a ``total``-pose (default
    ``n_frames``) trajectory of synthetic world 0 (random ``dim`` features)."""
    import torch

    from synthetic_world import World

    w = World.generate(0)
    hw = (60, 80)
    K = w.camera(hw, 90.0)
    g = torch.Generator().manual_seed(2 + first)
    for p in w.trajectory("ground", max(total, n_frames, 1), seed=0)[first:first + n_frames]:
        r = w.render(p, K, hw)
        m.integrate(p, K, r.depth.astype(np.float32), r.rgb, torch.randn((dim, 15, 20), generator=g))
    m.flush()


def _occupancy_latency(m, n: int) -> dict:
    from planning.occupancy_queries import costmap_slice, index_current, point_states, state_grid

    vox = float(m.cfg.vox_size)
    rng = np.random.default_rng(0)
    box, sl, pts = [], [], []
    first: list[float] = []
    while len(first) < WARM_POINT_QUERIES or (len(first) < WARM_POINT_QUERIES_MAX
                                               and not index_current(m.occupancy_view())):
        q = rng.uniform([-30, -30, 0], [30, 30, 4], (1000, 3))   # a planner's first steps: the index
        t = time.perf_counter()                                   # is built on the way
        point_states(m.occupancy_view(), vox, q, 1.0)
        first.append((time.perf_counter() - t) * 1e3)
    for _ in range(n):
        t = time.perf_counter()
        state_grid(m.occupancy_view(), vox, [-20, -20, 0], [20, 20, 6])
        box.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        costmap_slice(m.occupancy_view(), vox, [-40, -40], [40, 40], [0.2, 2.0])
        sl.append((time.perf_counter() - t) * 1e3)
        q = rng.uniform([-30, -30, 0], [30, 30, 4], (1000, 3))
        t = time.perf_counter()
        point_states(m.occupancy_view(), vox, q, 1.0)
        pts.append((time.perf_counter() - t) * 1e3)
    return {"box_40x40x6m": _pct(box), "slice_80x80m": _pct(sl), "points_1000_r1m": _pct(pts),
            "points_1000_r1m_first": _pct(first)}


ROBOTS = ([0.0, 0.0, 1.5], [6.0, -4.0, 1.5], [-8.0, 5.0, 1.5])


def standing_latency(cfg, m, fs, snap, trackers, dim: int, frames: int, rounds: int) -> dict:
    """Standing searches after map updates: one robot's, then three robots' (module docstring)."""
    from common.search_messages import SearchRequest
    from mapper.search_answer import answer_search

    one_ms: list[float] = []
    three_ms: list[float] = []
    for i in range(2 * rounds):
        _add_frames(m, dim, 1, frames + i, frames + 2 * rounds)
        snap.sync(m, 2 + i, 2 + i)
        reqs = [SearchRequest(targets=[TARGETS[0]], from_xyz=xyz).validate() for xyz in ROBOTS[:1 + 2 * (i % 2)]]
        t = time.perf_counter()
        for req in reqs:                              # as the standing loop: one after the other
            answer_search(snap, fs, req, cfg, trackers, lambda fn: fn(m), map_version=2 + i)
        (three_ms if i % 2 else one_ms).append((time.perf_counter() - t) * 1e3)
    return {"one": _pct(one_ms), "three": _pct(three_ms),
            "ratio": float(np.median(three_ms) / max(1e-9, np.median(one_ms)))}


def search_latency(cfg, m, fs, queries: int, dim: int = 0, frames: int = 0,
                   standing_rounds: int = STANDING_ROUNDS) -> dict:
    """Searches answered as the mapper does (query copy, cached embeddings)."""
    from common.search_messages import SearchRequest
    from mapper.search_answer import TrackerStore, answer_search
    from mapper.service_config import freeze_startup_objects
    from semantic_map.query_copy import QueryCopy

    snap = QueryCopy()
    snap.reserve(m)
    snap.sync(m, 1, 1)
    trackers = TrackerStore(cfg.search.max_trackers)

    def one(target: str):
        req = SearchRequest(targets=[target], from_xyz=[0.0, 0.0, 1.5]).validate()
        return answer_search(snap, fs, req, cfg, trackers, lambda fn: fn(m), map_version=1)

    t = time.perf_counter()
    first = one(TARGETS[0])                     # loads the text model, builds the prepared terms
    first_ms = (time.perf_counter() - t) * 1e3
    freeze_startup_objects()                    # as the mapper process after its start
    for tg in TARGETS[1:]:                      # each target embedded once (then cached, as in the mapper)
        one(tg)
    wall, cpu, stages = [], [], []
    for i in range(queries):
        t, c = time.perf_counter(), time.process_time()
        rep = one(TARGETS[i % len(TARGETS)])
        wall.append((time.perf_counter() - t) * 1e3)
        cpu.append((time.process_time() - c) * 1e3)
        stages.append(rep.timings_ms)
    names = sorted({k for s in stages for k in s})
    rng = np.random.default_rng(7)                # cold: a target vector never searched before
    cold = []
    for _ in range(max(3, queries // 2)):
        req = SearchRequest(targets=["x"], embeddings=rng.standard_normal((1, fs.lang_dim)).astype(np.float32),
                            from_xyz=[0.0, 0.0, 1.5]).validate()
        t = time.perf_counter()
        answer_search(snap, fs, req, cfg, trackers, lambda fn: fn(m), map_version=1)
        cold.append((time.perf_counter() - t) * 1e3)
    standing = standing_latency(cfg, m, fs, snap, trackers, dim, frames, max(1, standing_rounds)) if dim else {}
    return {"standing_ms": standing,"first_search_ms": first_ms, "search_ms": _pct(wall), "search_cold_ms": _pct(cold),
            "search_cpu_ms": _pct(cpu),
            "stage_p50_ms": {k: float(np.median([s.get(k, 0.0) for s in stages])) for k in names},
            "found": len(first.found), "look_next": len(first.look_next),
            "beyond_rays": len(first.beyond.get("rays", [])), "estimates": len(first.beyond.get("estimates", []))}


def run(args: argparse.Namespace) -> dict:
    import torch

    from apps.bench import meta
    from mapper.service_config import resolve_query_threads

    n_threads = args.threads or resolve_query_threads(0)
    torch.set_num_threads(n_threads)
    fs = _space(args.dim)
    out = {"dim": args.dim, "rays": args.rays, "frames": args.frames, "query_threads": n_threads, "sizes": {}}
    for spec in args.voxels.split(","):
        n = _count(spec)
        t = time.perf_counter()
        cfg, m = build_map(n, args.dim, args.rays, fs)
        _add_frames(m, args.dim, args.frames)
        row: dict = {"build_s": time.perf_counter() - t, "voxels": m.n_voxels(), "rays": m.n_rays(),
                     "frontiers": int(m.frontiers().centres.shape[0])}
        with meta.timed(f"search_{spec}"):
            row.update(search_latency(cfg, m, fs, args.queries, args.dim, args.frames, args.standing_rounds))
        with meta.timed(f"occupancy_{spec}"):          # after the standing searches' updates
            row["occupancy_ms"] = _occupancy_latency(m, max(3, args.queries // 2))
        out["sizes"][spec] = row
        del m
    return out
