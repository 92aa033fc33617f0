"""``rayfronts bench mission``: a long mission (12,000 frames by default, ``--frames 36000``
for an hour at 10 Hz) through a city that the route never revisits.

World and route: :class:`synthetic_world.mission.MissionCity` (a staircase of 100 m streets,
lined like the town's, generated lazily), frame ``i`` at ``i · --step`` metres down the route
(default 0.15 m: a 1.5 m/s robot at 10 Hz; 12,000 frames = 1.8 km). Frames are rendered in
chunks of ``--chunk`` (untimed), each with random float16 features at 1/16 resolution drawn
from ``torch.Generator().manual_seed(seed)`` in frame order (as ``bench mapper``), fed to one
map (``throughput`` preset; the two-stage pipeline unless ``--no-pipeline``, as ``bench
mapper``), then dropped: memory stays bounded by one chunk.

Per window (``--window`` frames, default 5 % of ``--frames``): process CPU ms per frame of
the mapping alone (``cpu_ms_per_frame``, all threads; rendering and queries excluded),
wall ms per frame, stage times, current and peak RSS (MiB), semantic voxels, frontiers, ray
bins, the map's own memory estimate (``map_memory_mb`` = :meth:`RayFrontsMap.memory_bytes`
/ 2^20: the semantic layers, with their parts ``semantic_mb`` (voxels), ``rays_mb``,
``frontiers_mb``; the occupancy grid apart, ``occupancy_mb``; ``total_memory_mb`` both) and, at the window end,
the query latency: a persistent :class:`QueryCopy` synced to the live map (unflushed, as
the mapper's query thread sees it; ``query_sync_ms``) and ``--queries`` queries answered by
:func:`mapper.query_answer.answer_snapshot` (the in-process path of ``bench query``; text
queries, embedded once up front, or ``--query-source random`` language-space vectors, which
skip loading the text model).

Summary: CPU ms/frame of the first and last 10 % of the frames and ``flat_cost_ratio`` =
last / first; after a final flush, ``n_voxels``, ``map_memory_mb`` and ``bytes_per_voxel`` =
``memory_bytes / n_voxels``; ``--plot FILE`` draws each per-window quantity against frames.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from apps.bench.meta import add_synthetic_map_arguments, resolution_arg

if TYPE_CHECKING:
    import numpy as np
    import torch

    from apps.bench.mapper import BenchFrame, FeedSide
    from synthetic_world.mission import MissionCity

HELP = "long mission (12,000+ frames, no revisits): per-window CPU-ms/frame, RSS, map size, query latency (JSON, plot)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=12000, help="frames (default 12000; 36000 = 1 h at 10 Hz)")
    parser.add_argument("--window", type=int, default=0, help="frames per reported window (default 5%% of --frames)")
    parser.add_argument("--resolution", type=resolution_arg, default=(224, 224), metavar="HxW",
                        help="rendered image size (default 224x224, as bench mapper's throughput preset)")
    parser.add_argument("--step", type=float, default=0.15, help="metres travelled per frame (default 0.15)")
    parser.add_argument("--chunk", type=int, default=200, help="frames rendered ahead per chunk (default 200)")
    add_synthetic_map_arguments(parser)
    parser.add_argument("--no-pipeline", action="store_true", help="integrate sequentially (same map)")
    parser.add_argument("--queries", type=int, default=5, help="queries sampled at each window end (0: none)")
    parser.add_argument("--query-source", choices=["text", "random"], default="text",
                        help="text queries (loads the label text model once) or random language-space vectors")
    parser.add_argument("--plot", type=Path, default=None, help="write a PNG: each per-window quantity vs frames")


def current_rss_mb() -> float:
    """Resident set size of this process now, MiB (``/proc/self/statm``; peak RSS elsewhere)."""
    import os
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        from apps.bench.mapper import peak_rss_mb
        return peak_rss_mb()


def render_chunk(city: MissionCity, start: int, n: int, step: float, K: np.ndarray, hw: tuple[int, int],
                 dim: int, gen: torch.Generator) -> list[BenchFrame]:
    """Frames ``start … start + n − 1`` of the route (module doc), features drawn from ``gen``."""
    import numpy as np
    import torch

    fh, fw = max(1, hw[0] // 16), max(1, hw[1] // 16)
    out = []
    for p in city.poses(start, n, step):
        r = city.render(p, K, hw)
        out.append((p, r.depth.astype(np.float32), r.rgb, torch.randn(dim, fh, fw, generator=gen).to(torch.float16)))
    return out


class _Queries:
    """The in-process query path of ``bench query``, sampled on the live map."""

    def __init__(self, args: argparse.Namespace) -> None:
        import numpy as np
        import torch

        from apps.bench.query import TEXTS, _space
        from common.messages import QueryRequest
        from mapper.service_config import MapperConfig, resolve_query_threads
        from semantic_map.query_copy import QueryCopy

        self.n = max(0, args.queries)
        self.fs = _space(args.feature_dim)
        self.qcfg = MapperConfig().query
        self.threads = resolve_query_threads(0)
        self.snap = QueryCopy()
        self.gen = 0
        if args.query_source == "text":
            self.reqs = [QueryRequest(text=TEXTS[i % len(TEXTS)], top_k=10) for i in range(self.n)]
        else:
            g = torch.Generator().manual_seed(args.seed + 1)
            e = torch.nn.functional.normalize(torch.randn(self.n, self.fs.lang_dim, generator=g), dim=1)
            self.reqs = [QueryRequest(embedding=np.asarray(e[i], np.float32), top_k=10) for i in range(self.n)]
        t = time.perf_counter()
        if self.n and args.query_source == "text":
            from mapper.query_answer import warm_up_text
            warm_up_text(self.fs, [r.text for r in self.reqs if r.text is not None])   # all, from text
        self.warm_up_s = time.perf_counter() - t

    def sample(self, m) -> dict:
        """Sync the snapshot to ``m`` and answer every query: latencies in ms."""
        import numpy as np
        import torch

        from mapper.query_answer import answer_snapshot

        if not self.n:
            return {}
        old = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        try:
            self.gen += 1
            self.snap.reserve(m)
            self.snap.sync(m, self.gen)
            sync_ms = self.snap.take_ms
            wall, cpu = [], []
            for req in self.reqs:
                t, c = time.perf_counter(), time.process_time()
                answer_snapshot(self.snap, self.fs, req, self.qcfg, device="cpu")
                wall.append(1e3 * (time.perf_counter() - t))
                cpu.append(1e3 * (time.process_time() - c))
        finally:
            torch.set_num_threads(old)
        return {"query_sync_ms": round(sync_ms, 2), "query_ms_p50": round(float(np.median(wall)), 2),
                "query_ms_max": round(max(wall), 2), "query_cpu_ms_p50": round(float(np.median(cpu)), 2)}


def map_memory(m) -> dict:
    """The map's memory estimate (MiB): the semantic layers and their parts, the occupancy grid apart."""
    mb = 1 / 2**20
    layers, grid, parts = m.memory_bytes(), m.occupancy_memory_bytes(), m.memory_parts()
    return {"map_memory_mb": round(layers * mb, 3),
            "semantic_mb": round(parts["voxels"] * mb, 3),
            "rays_mb": round(parts["rays"] * mb, 3),
            "frontiers_mb": round(parts["frontiers"] * mb, 3),
            "occupancy_mb": round(grid * mb, 3),
            "total_memory_mb": round((layers + grid) * mb, 3)}


def _boundaries(n: int, window: int, chunk: int) -> list[int]:
    """Frame indices where a fed block ends: every window end, every chunk, the 10 % / 90 % marks."""
    n10 = max(1, round(0.1 * n))
    b = set(range(window, n, window)) | set(range(chunk, n, chunk)) | {n10, n - n10, n}
    return sorted(x for x in b if 0 < x <= n)


def run(args: argparse.Namespace) -> dict:
    import os

    import torch

    from apps.bench import meta
    from apps.bench.mapper import FeedSide, peak_rss_mb
    from common.config import parse_override
    from common.geometry import intrinsics_from_fov
    from semantic_map import kernels
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    from synthetic_world.mission import MissionCity

    n = args.frames
    if n < 10:
        raise ValueError(f"--frames must be >= 10, got {n}")
    window = args.window or max(1, round(0.05 * n))
    if window < 1 or args.chunk < 1 or args.step <= 0:
        raise ValueError("--window, --chunk and --step must be positive")
    torch.set_num_threads(max(1, args.threads))
    over = {"depth_limit": args.depth_limit}
    for item in args.override:
        over.update(parse_override(item))
    m = RayFrontsMap(map_config("throughput", over), args.feature_dim, "bench")
    use_kernels = kernels.enabled()
    side = FeedSide("mission", m, not args.no_pipeline, use_kernels, args.threads)
    queries = _Queries(args)
    city = MissionCity(args.seed)
    hw = tuple(args.resolution)
    K = intrinsics_from_fov(90.0, hw[0], hw[1])
    gen = torch.Generator().manual_seed(args.seed)
    res: dict = {"target": "mission", "frames": n, "window": window, "resolution_hw": list(hw), "step_m": args.step,
                 "route_m": round(n * args.step, 1), "preset": "throughput", "depth_limit": args.depth_limit,
                 "feature_dim": args.feature_dim, "pipeline": not args.no_pipeline, "kernels": use_kernels,
                 "threads_per_stage": max(1, args.threads), "chunk": args.chunk, "seed": args.seed,
                 "queries_per_window": queries.n, "query_source": args.query_source,
                 "query_threads": queries.threads, "query_warm_up_s": round(queries.warm_up_s, 2),
                 "main_section": None}
    n10 = max(1, round(0.1 * n))
    marks: dict[int, float] = {0: 0.0}
    windows: list[dict] = []
    render_s = 0.0
    ws = 0
    win0 = (side.cpu, side.wall, dict(side.stages), meta.loadavg(), time.perf_counter(), render_s)
    with meta.timed("mission_loop", frames=n):  # rendering and queries included; the windows' CPU is mapping only
        prev = 0
        for end in _boundaries(n, window, args.chunk):
            t = time.perf_counter()
            frames = render_chunk(city, prev, end - prev, args.step, K, hw, args.feature_dim, gen)
            render_s += time.perf_counter() - t
            side.feed(frames, K)
            del frames
            marks[end] = side.cpu
            prev = end
            if end % window and end != n:
                continue
            windows.append(_window(side, queries, ws, end, win0, render_s))
            w = windows[-1]
            print(f"[bench mission] frames {ws}-{end}: {w['cpu_ms_per_frame']} CPU-ms/frame, {w['n_voxels']} voxels, "
                  f"{w['map_memory_mb']:.1f} MiB map, RSS {w['rss_mb']:.0f} MiB, query p50 {w.get('query_ms_p50')} ms, "
                  f"window {w['window_wall_s']:.0f} s", file=sys.stderr, flush=True)
            ws = end
            win0 = (side.cpu, side.wall, dict(side.stages), meta.loadavg(), time.perf_counter(), render_s)
    side.close()
    m.flush()
    st = m.stats()
    first = 1e3 * marks[n10] / n10
    last = 1e3 * (marks[n] - marks[n - n10]) / n10
    res.update({
        "windows": windows, "render_s_excluded": round(render_s, 1),
        "cpu_ms_per_frame": round(1e3 * side.cpu / n, 2),
        "frames_per_s": round(n / side.wall, 2) if side.wall else None,
        "cpu_ms_per_frame_first_10pct": round(first, 2), "cpu_ms_per_frame_last_10pct": round(last, 2),
        "flat_cost_ratio": round(last / first, 3) if first > 0 else None,
        "n_voxels": st["n_voxels"], "n_frontiers": st["n_frontiers"], "n_rays": st["n_rays"],
        "n_occupancy_active": st["n_occupancy_active"], **map_memory(m),
        "bytes_per_voxel": round(st["memory_bytes"] / st["n_voxels"], 1) if st["n_voxels"] else None,
        "peak_rss_mb": round(peak_rss_mb(), 1), "rss_mb": round(current_rss_mb(), 1),
        "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()],
    })
    if queries.n:
        res["final_query"] = queries.sample(m)
    if args.plot is not None:
        res["plot"] = str(plot(windows, args.plot, res))
    return res


def _window(side: FeedSide, queries: _Queries, s: int, e: int, win0: tuple, render_s: float) -> dict:
    """One window's record (``win0``: side CPU, wall, stages, load, clock, render seconds at its start)."""
    from apps.bench.mapper import peak_rss_mb, window_record

    c0, w0, st0, load0, t0, r0 = win0
    rec = window_record(side, s, e - s, c0, w0, st0, load0)
    rec.update(map_memory(side.map))
    rec["n_occupancy_active"] = int(side.map.occupancy_view().num_active)
    rec["rss_mb"] = round(current_rss_mb(), 1)
    rec["peak_rss_mb"] = round(peak_rss_mb(), 1)
    rec["render_s"] = round(render_s - r0, 2)
    rec.update(queries.sample(side.map))
    rec["window_wall_s"] = round(time.perf_counter() - t0, 2)
    return rec


#: (keys drawn in one panel, y label); query latency: wall p50 and the process CPU p50 (load-robust)
_PANELS = [(("cpu_ms_per_frame",), "CPU ms / frame (mapping)"), (("rss_mb",), "RSS (MiB)"),
           (("map_memory_mb",), "map memory (MiB)"), (("n_voxels",), "semantic voxels"),
           (("n_frontiers",), "frontiers"), (("n_rays",), "ray bins"),
           (("query_ms_p50", "query_cpu_ms_p50"), "query p50 (ms)")]


def plot(windows: list[dict], path: Path, res: dict) -> Path:
    """One panel per per-window quantity against the frame at the window's end; PNG at ``path``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(ks, lab) for ks, lab in _PANELS if any(k in w for w in windows for k in ks)]
    x = [w["frames"][1] for w in windows]
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, 1.7 * len(panels) + 0.6), sharex=True)
    for ax, (ks, lab) in zip(axes, panels, strict=True):
        for k in ks:
            ax.plot(x, [w.get(k) for w in windows], marker="o", ms=3, label=k if len(ks) > 1 else None)
        if len(ks) > 1:
            ax.legend(fontsize=7)
        ax.set_ylabel(lab, fontsize=8)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("frames")
    fig.suptitle(f"bench mission: {res['frames']} frames, {res['route_m']:.0f} m, {res['resolution_hw'][0]}x"
                 f"{res['resolution_hw'][1]}, throughput preset\nflat_cost_ratio {res.get('flat_cost_ratio')}, "
                 f"{res.get('bytes_per_voxel')} B/voxel at the end",
                 fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
