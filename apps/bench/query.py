"""``rayfronts bench query``: text-query latency on big maps, in process and over Zenoh.

For each map size (``--voxels 100k,1M,5M``) a map is filled with that many semantic voxels
(random features in a PCA-``--dim`` label feature space, keys on a dense block) and
``--rays`` semantic rays, then:

* **in process** (what the mapper does per query, without Zenoh): the query copy is synced
  under a lock (:meth:`mapper.query_answer.QueryCopy.sync`) and the query answered
  (:func:`mapper.query_answer.answer_snapshot`); ``steady`` = repeated queries on an
  unchanged map (the texts' scores are cached per copy and updated for changed rows, so this
  is the repeated / standing query), ``cold`` = a query vector never seen before (a full pass
  over the copy), ``after_change`` = the first query after each map change (one frame's worth
  of fused points, a few hundred new voxels), p50 / p95 of each and their ratio, the process
  CPU per query (``*_cpu_ms``: the load-robust figure on a shared machine), the stages' p50
  and the one-off cost of embedding a text the mapper has not seen (``encode_new_text_ms``;
  embeddings are cached per text, so ``steady`` measures the map side).
* **client** (``--client``, default on): the same map served by an in-process
  :class:`mapper.service.MapperService` on loopback, queried with ``query_client.Client``
  (one session for all queries); round trip vs the mapper's own ``timings.total``, the reply
  size, and the overhead = round trip − mapper time at p50.

The map is built directly (no frames), so the figures isolate the query path.
"""
from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from mapper.service_config import MapperConfig
    from semantic_map.map import RayFrontsMap

HELP = "query latency on 100k..5M-voxel maps: in process (steady, first after a change) and client round trip"

TEXTS = ("car", "tree", "building", "road", "person", "grass", "sky", "window", "door", "bench")


def _count(s: str) -> int:
    s = s.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(s[-1:], 1)
    return int(float(s[:-1] if mult > 1 else s) * mult)


def map_size_arguments(parser: argparse.ArgumentParser) -> None:
    """``--voxels``, ``--dim``, ``--rays``, ``--threads``: the benchmark map and its query threads."""
    parser.add_argument("--voxels", default="100k,1M,5M", help="map sizes, comma separated (k / M suffixes)")
    parser.add_argument("--dim", type=int, default=100, help="feature dimension (PCA output) of the map")
    parser.add_argument("--rays", type=int, default=5000, help="semantic rays in the map")
    parser.add_argument("--threads", type=int, default=0, help="torch threads for queries (0 = the mapper's auto)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    map_size_arguments(parser)
    parser.add_argument("--queries", type=int, default=20, help="queries per measurement")
    parser.add_argument("--changes", type=int, default=10, help="map changes for the first-query-after-change figure")
    parser.add_argument("--no-client", dest="client", action="store_false", help="skip the Zenoh round trip")


def _space(dim: int):
    import torch

    from common.feature_space import FeatureSpace
    from common.pca import PCA

    g = torch.Generator().manual_seed(0)
    in_dim = 384                                  # the label encoder's MiniLM width
    q, _ = torch.linalg.qr(torch.randn(in_dim, dim, generator=g, dtype=torch.float64))
    pca = PCA(np.zeros(in_dim, np.float32), q.numpy().astype(np.float32))
    return FeatureSpace("label", "bench", in_dim, pca=pca)


def build_map(n: int, dim: int, n_rays: int, fs: FeatureSpace, seed: int = 0) -> tuple[MapperConfig, RayFrontsMap]:
    """A RayFrontsMap (default mapper config) holding ``n`` voxels and ``n_rays`` rays."""
    import torch

    from mapper.service_config import MapperConfig
    from mapper.service_map import create_map
    from semantic_map import cell_keys

    cfg = MapperConfig()
    m = create_map(cfg, fs)
    g = torch.Generator().manual_seed(seed)
    side = int(np.ceil(n ** (1 / 3)))
    chunk = 500_000
    for s0 in range(0, n, chunk):
        idx = torch.arange(s0, min(n, s0 + chunk), dtype=torch.int64)
        ijk = torch.stack([idx % side, (idx // side) % side, idx // (side * side)], 1)
        k = idx.numel()
        m.fuse_sums(cell_keys.pack(ijk), torch.rand((k, 3), generator=g), torch.randn((k, dim), generator=g),
                    torch.ones(k))
    cell = torch.randperm(200 ** 3, generator=g)[:n_rays]          # distinct frontier cells (one ray each)
    fk = cell_keys.pack(torch.stack([cell % 200, (cell // 200) % 200, cell // 40_000], 1))
    d = torch.nn.functional.normalize(torch.randn((n_rays, 3), generator=g), dim=1)
    m.replace_ray_bins({"fkey": torch.sort(fk).values, "tbin": torch.zeros(n_rays, dtype=torch.int64),
                        "pbin": torch.zeros(n_rays, dtype=torch.int64), "feat": torch.randn((n_rays, dim), generator=g),
                        "weight": torch.ones(n_rays), "dsum": d})
    return cfg, m


def _change(m, dim: int, g, side_hint: int) -> None:
    """One frame's worth of fusion: 3000 points, most on existing voxels, a few hundred new."""
    import torch

    from semantic_map import cell_keys

    ijk = torch.randint(0, side_hint + 2, (3000, 3), generator=g)
    m.fuse_sums(cell_keys.pack(ijk), torch.rand((3000, 3), generator=g), torch.randn((3000, dim), generator=g),
                torch.ones(3000))


def _pct(a) -> dict:
    a = np.asarray(a, float)
    return {"n": int(a.size), "p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
            "max": float(a.max())}


def in_process(cfg: MapperConfig, m: RayFrontsMap, fs: FeatureSpace, args: argparse.Namespace, n: int) -> dict:
    import threading

    import torch

    from common.messages import QueryRequest
    from mapper.query_answer import answer_snapshot
    from mapper.service_config import resolve_query_threads
    from semantic_map.query_copy import QueryCopy

    # as the mapper does per query: a MapperService run before (client_round_trip) leaves
    # this thread's torch thread count at its map thread's
    torch.set_num_threads(args.threads or resolve_query_threads(0))
    lock = threading.Lock()
    snap = QueryCopy()
    gen = [1]

    cpu = []

    def one(text):
        t0 = time.perf_counter()
        c0 = time.process_time()
        sync_ms = 0.0
        if snap.gen != gen[0]:                    # as the mapper: sync only when the map changed
            snap.reserve(m)
            with lock:
                snap.sync(m, gen[0])
            sync_ms = snap.take_ms
        res = answer_snapshot(snap, fs, QueryRequest(text=text, top_k=10), cfg.query, device="cpu")
        cpu.append((time.process_time() - c0) * 1e3)
        return (time.perf_counter() - t0) * 1e3, sync_ms, res.timings

    first_ms, _, _ = one(TEXTS[0])                # builds the copy and the prepared terms
    enc = [one(t)[2].get("encode", 0.0) for t in TEXTS[1:]]   # each text embedded once (then cached)
    cpu.clear()
    steady, steady_sync, steady_timings = [], [], []
    for i in range(args.queries):
        t, s, tim = one(TEXTS[i % len(TEXTS)])
        steady.append(t)
        steady_sync.append(s)
        steady_timings.append(tim)
    steady_cpu = list(cpu)
    cpu.clear()
    g = torch.Generator().manual_seed(1)
    side = int(np.ceil(n ** (1 / 3)))
    after, after_sync, after_timings = [], [], []
    for i in range(args.changes):
        with lock:
            _change(m, fs.dim, g, side)
            gen[0] += 1
        t, s, tim = one(TEXTS[i % len(TEXTS)])
        after.append(t)
        after_sync.append(s)
        after_timings.append(tim)
    after_cpu = list(cpu)
    # cold (last: its queries take places in the score cache): an embedding never queried
    # before, so no cached scores: a full pass over the copy
    rng = np.random.default_rng(7)
    cold = []
    for _ in range(max(3, args.queries // 2)):
        e = rng.standard_normal(fs.lang_dim).astype(np.float32)
        t0 = time.perf_counter()
        answer_snapshot(snap, fs, QueryRequest(embedding=e, top_k=10), cfg.query, device="cpu")
        cold.append((time.perf_counter() - t0) * 1e3)
    st, af = _pct(steady), _pct(after)
    stages = sorted({k for t in steady_timings for k in t})
    return {"initial_copy_ms": first_ms, "steady_ms": st, "cold_ms": _pct(cold),
            "steady_lock_held_ms": _pct(steady_sync),
            "steady_cpu_ms": _pct(steady_cpu), "after_change_cpu_ms": _pct(after_cpu),
            "steady_stage_p50_ms": {k: float(np.median([t.get(k, 0.0) for t in steady_timings])) for k in stages},
            "encode_new_text_ms": _pct(enc),
            "after_change_ms": af, "after_change_lock_held_ms": _pct(after_sync),
            "after_change_over_steady_p50": af["p50"] / max(st["p50"], 1e-9),
            "after_change_prepare_ms": _pct([t.get("prepare", 0.0) for t in after_timings]),
            "voxels": m.n_voxels(), "rays": m.n_rays()}


def client_round_trip(cfg: MapperConfig, m: RayFrontsMap, fs: FeatureSpace, args: argparse.Namespace) -> dict:
    from common.messages import encode_feature_space, encode_query_result
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from mapper.service import MapperService
    from query_client import Client

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    cfg.zenoh = ZenohConfig(mode="router", listen=[ep])
    cfg.layers.rate_hz = 0
    svc = MapperService(cfg).start()
    try:
        with svc.lock:
            svc.map, svc.space, svc.space_reply = m, fs, encode_feature_space("bench", fs.to_body())
            svc.map_gen += 1
            svc.mapped = 1
        rtt, inside, size = [], [], []
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=30_000), timeout=60.0) as c:
            for t in TEXTS:                          # warm: the copy, the text model, each text
                c.query(t, top_k=10)
            for i in range(args.queries):
                t0 = time.perf_counter()
                r = c.query(TEXTS[i % len(TEXTS)], top_k=10)
                rtt.append((time.perf_counter() - t0) * 1e3)
                inside.append(float(r.timings.get("total", 0.0)))
                size.append(len(encode_query_result(r)))       # what went over the wire (re-encoded)
        over = np.asarray(rtt) - np.asarray(inside)
        return {"round_trip_ms": _pct(rtt), "mapper_total_ms": _pct(inside), "overhead_ms": _pct(over),
                "overhead_p50_ms": float(np.percentile(over, 50)),
                "reply_bytes": int(np.median(size))}
    finally:
        svc.close()


def run(args: argparse.Namespace) -> dict:
    import torch

    from apps.bench import meta
    from mapper.service_config import resolve_query_threads

    n_threads = args.threads or resolve_query_threads(0)
    torch.set_num_threads(n_threads)
    fs = _space(args.dim)
    out = {"dim": args.dim, "rays": args.rays, "query_threads": n_threads, "sizes": {}}
    for spec in args.voxels.split(","):
        n = _count(spec)
        t = time.perf_counter()
        cfg, m = build_map(n, args.dim, args.rays, fs)
        row: dict = {"build_s": time.perf_counter() - t}
        with meta.timed(f"in_process_{spec}"):
            row["in_process"] = in_process(cfg, m, fs, args, n)
        if args.client:
            with meta.timed(f"client_{spec}"):
                row["client"] = client_round_trip(cfg, m, fs, args)
        out["sizes"][spec] = row
        del m
    return out
