"""``rayfronts bench mapper``: RayFronts map throughput / memory on synthetic-world frames.

Frames are rendered up front (not timed) at the preset's resolution (throughput 224×224,
online 640×640) with random 100-dim features at 1/16 resolution (float16, as on the wire);
then every frame goes through the map and a final flush. By default frames go through
the two-stage pipeline (:class:`mapper.pipeline.MapPipeline`: frame N+1's geometry and
sampling on a second thread while frame N is committed); ``--no-pipeline`` integrates
sequentially. ``--no-kernels`` forces the torch paths. Peak RSS includes the pre-rendered
frames (``rss_after_render_mb``).

The timed section ``integrate`` (:mod:`apps.bench.meta`) gives ``frames_per_s`` and
``cpu_ms_per_frame`` = process CPU (all threads) per frame, the figure that survives a
busy machine. ``stage_ms_per_frame`` are wall-clock stage times (stretched by load).

* ``--compare kernels|pipeline``: both sides (C++ kernels vs torch paths, or pipeline vs
  sequential) on two maps fed the same frames, **interleaved** in blocks of ``--block``
  frames (A B A B …, each map drained at the end of its block), so both see the same load;
  each side's frames/s and CPU ms/frame are the sums over its blocks, and the JSON says
  whether the two maps came out identical.
* ``--growing``: per-window (``--window`` frames, default 200) CPU ms/frame and stage times
  over one long lap (the map grows through the run: new streets every window);
  ``growth_cpu_ratio`` = last window / first window (``growth_cpu_ratio_from_second``: / the
  second window, as the first also pays start-up costs). The windows see different streets,
  so ``growth_control`` feeds the last window's frames again to an empty map afterwards:
  ``content_ratio`` = that / the first window (what the frames cost by themselves),
  ``map_size_ratio`` = the grown map's last window / that (what the map's size costs);
  its ``stage_ms_per_frame`` against the last window's say which stages the size costs in.
"""
from __future__ import annotations

import argparse
import resource
import time
from typing import TYPE_CHECKING, Callable, Sequence

from apps.bench.meta import add_synthetic_map_arguments

if TYPE_CHECKING:
    import numpy as np
    import torch

    from semantic_map.map import RayFrontsMap

    #: one pre-rendered frame: (pose 4×4, depth (H, W) float32, rgb (H, W, 3) uint8, features (C, h, w) float16)
    BenchFrame = tuple[np.ndarray, np.ndarray, np.ndarray, torch.Tensor]

HELP = "RayFronts map throughput and memory on synthetic frames (JSON)"

_RES = {"throughput": (224, 224), "online": (640, 640)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", choices=sorted(_RES), default="throughput",
                        help="map preset and input resolution (throughput: 224x224, 0.3 m; online: 640x640, 1 m)")
    parser.add_argument("--frames", type=int, default=300, help="frames to integrate (default 300)")
    parser.add_argument("--backend", choices=["auto", "vdb", "torch"], default="auto", help="occupancy backend")
    add_synthetic_map_arguments(parser)
    parser.add_argument("--trajectory", choices=["ground", "drone"], default="ground", help="camera trajectory")
    parser.add_argument("--no-kernels", action="store_true",
                        help="use the pure-torch paths instead of the C++ kernels (semantic_map._rfkernels); "
                             "same results")
    parser.add_argument("--no-pipeline", action="store_true",
                        help="integrate sequentially on one thread instead of the two-stage pipeline; same map")
    parser.add_argument("--compare", choices=["kernels", "pipeline"], default=None,
                        help="time both sides interleaved in one run (kernels vs torch, pipeline vs sequential)")
    parser.add_argument("--block", type=int, default=25,
                        help="frames per interleaved block with --compare (default 25)")
    parser.add_argument("--growing", action="store_true", help="report CPU ms/frame per window of --window frames")
    parser.add_argument("--window", type=int, default=200, help="window size for --growing (default 200)")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the map (cpu, cuda, cuda:1); the occupancy grid and the C++ kernels "
                             "stay on the CPU, map tensors elsewhere take the torch paths")


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (``ru_maxrss``)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class FeedSide:
    """One map fed frame blocks; sums wall and process CPU over its blocks."""

    def __init__(self, name: str, m: RayFrontsMap, pipeline: bool, kernels_on: bool, threads: int) -> None:
        from mapper.pipeline import MapPipeline
        self.name, self.map, self.kernels_on = name, m, kernels_on
        self.pipe = MapPipeline(m, prepare_threads=threads) if pipeline else None
        self.wall = self.cpu = 0.0
        self.frames = 0
        self.stages: dict[str, float] = {}

    def feed(self, frames: Sequence[BenchFrame], K: np.ndarray) -> None:
        from apps.bench import meta
        from semantic_map import kernels
        old = kernels.set_enabled(self.kernels_on)
        try:
            c0, t0 = meta.cpu_seconds(), time.perf_counter()
            if self.pipe is not None:
                done = []
                for p, d, rgb, f in frames:
                    done += self.pipe.submit(p, K, d, rgb, f)
                done += self.pipe.drain()
                for c in done:
                    if c.error is not None:
                        raise c.error
                    assert c.timings is not None          # a frame without an error has its timings
                    self._add(c.timings)
            else:
                for p, d, rgb, f in frames:
                    self._add(self.map.integrate(p, K, d, rgb, f))
            if self.map.device.type == "cuda":
                import torch
                torch.cuda.synchronize(self.map.device)
            self.wall += time.perf_counter() - t0
            self.cpu += meta.cpu_seconds() - c0
            self.frames += len(frames)
        finally:
            kernels.set_enabled(old)

    def _add(self, tm: dict) -> None:
        for k, v in tm.items():
            self.stages[k] = self.stages.get(k, 0.0) + v

    def close(self) -> None:
        if self.pipe is not None:
            self.pipe.close()

    def summary(self) -> dict:
        n = max(1, self.frames)
        return {"frames": self.frames, "frames_per_s": round(self.frames / self.wall, 2) if self.wall else None,
                "cpu_ms_per_frame": round(1e3 * self.cpu / n, 2), "wall_ms_per_frame": round(1e3 * self.wall / n, 2),
                "stage_ms_per_frame": {k: round(v / n, 3) for k, v in sorted(self.stages.items())}}


def maps_identical(a: RayFrontsMap, b: RayFrontsMap) -> bool:
    """Every array of two maps' state equal (voxels, frontiers, rays, occupancy sample)."""
    import torch
    va, vb = a.voxels(), b.voxels()
    ra, rb = a.rays(), b.rays()
    fa, fb = a.frontiers(), b.frontiers()
    pairs = [(va.xyz, vb.xyz), (va.rgb, vb.rgb), (va.features, vb.features), (va.counts, vb.counts),
             (fa.keys, fb.keys), (fa.counts, fb.counts),
             (ra.frontier_keys, rb.frontier_keys), (ra.features, rb.features), (ra.weights, rb.weights),
             (ra.directions, rb.directions)]
    if not all(x.shape == y.shape and torch.equal(x, y) for x, y in pairs):
        return False
    return (a.schedule_counters() == b.schedule_counters()
            and int(a.occupancy_view().num_active) == int(b.occupancy_view().num_active))


def _render_frames(args: argparse.Namespace, hw: tuple[int, int]) -> tuple[list[BenchFrame], np.ndarray, float]:
    """``(frames, K, seconds)``: the trajectory's frames rendered up front, each with random
    float16 features at 1/16 resolution."""
    import numpy as np
    import torch

    from synthetic_world import World

    world = World.generate(args.seed)
    poses = world.trajectory(args.trajectory, args.frames, seed=args.seed)
    K = world.camera(hw, 90.0)
    g = torch.Generator().manual_seed(args.seed)
    fh, fw = max(1, hw[0] // 16), max(1, hw[1] // 16)
    t = time.perf_counter()
    frames = []
    for p in poses:
        r = world.render(p, K, hw)
        frames.append((p, r.depth.astype(np.float32), r.rgb,
                       torch.randn(args.feature_dim, fh, fw, generator=g).to(torch.float16)))
    return frames, K, time.perf_counter() - t


def run(args: argparse.Namespace) -> dict:
    import torch

    from common.config import parse_override
    from semantic_map import kernels
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    from semantic_map.occupancy import backend_name

    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    if args.block < 1 or args.window < 1:
        raise ValueError("--block and --window must be >= 1")
    torch.set_num_threads(max(1, args.threads))
    if str(args.device).startswith("cuda") and not torch.cuda.is_available():
        from common.config import ConfigError
        raise ConfigError(f"--device {args.device}: CUDA is not available on this machine")
    hw = _RES[args.preset]
    over = {"depth_limit": args.depth_limit}
    for item in args.override:
        over.update(parse_override(item))
    cfg = map_config(args.preset, over)
    frames, K, render_s = _render_frames(args, hw)
    rss_before = peak_rss_mb()
    n = len(frames)
    use_kernels = kernels.enabled() and not args.no_kernels

    def new_map() -> RayFrontsMap:
        return RayFrontsMap(cfg, args.feature_dim, "bench", device=args.device, occupancy_backend=args.backend)

    res: dict = {"target": "mapper", "preset": args.preset, "resolution_hw": list(hw), "frames": n,
                 "backend": backend_name(args.backend), "threads_per_stage": max(1, args.threads),
                 "kernels_available": kernels.available(), "depth_limit": args.depth_limit,
                 "feature_dim": args.feature_dim, "trajectory": args.trajectory, "device": str(args.device),
                 "render_s_excluded": round(render_s, 2), "rss_after_render_mb": round(rss_before, 1)}
    if args.compare:
        return _run_compare(args, res, new_map, frames, K, use_kernels)
    res = _run_main(args, res, new_map(), frames, K, use_kernels)
    if args.growing and len(res.get("windows", [])) >= 2:
        res["growth_control"] = _fresh_map_control(args, new_map(), frames, K, use_kernels, res["windows"])
    return res


def _fresh_map_control(args: argparse.Namespace, m: RayFrontsMap, frames: list[BenchFrame], K: np.ndarray,
                       use_kernels: bool, windows: list[dict]) -> dict:
    """``--growing``: the last window's frames once more, on an empty map. Their CPU-ms/frame
    there against the first window's (both on an empty map) is what the frames' content costs;
    the grown map's last window against it is what the map's size costs."""
    s, e = windows[-1]["frames"]
    side = FeedSide("control", m, not args.no_pipeline, use_kernels, args.threads)
    side.feed(frames[s:e], K)
    side.close()
    fresh = round(1e3 * side.cpu / (e - s), 2)
    first, last = windows[0]["cpu_ms_per_frame"], windows[-1]["cpu_ms_per_frame"]
    return {"frames": [s, e], "fresh_map_cpu_ms_per_frame": fresh, "n_voxels": m.n_voxels(),
            "stage_ms_per_frame": side.summary()["stage_ms_per_frame"],
            "content_ratio": round(fresh / first, 3) if first else None,
            "map_size_ratio": round(last / fresh, 3) if fresh else None}


def _run_compare(args: argparse.Namespace, res: dict, new_map: Callable[[], RayFrontsMap],
                 frames: list[BenchFrame], K: np.ndarray, use_kernels: bool) -> dict:
    """``--compare``: two sides fed the same frames interleaved in blocks; ``res`` completed."""
    from apps.bench import meta

    n = len(frames)
    if args.compare == "kernels":
        sides = [FeedSide("kernels", new_map(), not args.no_pipeline, True, args.threads),
                 FeedSide("torch", new_map(), not args.no_pipeline, False, args.threads)]
    else:
        sides = [FeedSide("pipeline", new_map(), True, use_kernels, args.threads),
                 FeedSide("sequential", new_map(), False, use_kernels, args.threads)]
    with meta.timed("interleaved", frames=2 * n):
        for s in range(0, n, args.block):
            for side in sides:
                side.feed(frames[s:s + args.block], K)
    for side in sides:
        side.close()
        side.map.flush()
    a, b = sides
    res.update(compare=args.compare, block=args.block,
               pipeline=(not args.no_pipeline) if args.compare == "kernels" else "both",
               sides={s.name: s.summary() for s in sides}, maps_identical=maps_identical(a.map, b.map))
    fps_b = res["sides"][b.name]["frames_per_s"]
    res[f"{a.name}_vs_{b.name}_fps"] = round(res["sides"][a.name]["frames_per_s"] / fps_b, 3) if fps_b else None
    res[f"{a.name}_vs_{b.name}_cpu"] = round(a.cpu / b.cpu, 3) if b.cpu else None
    res["peak_rss_mb"] = round(peak_rss_mb(), 1)
    res["main_section"] = None
    return res


def _run_main(args: argparse.Namespace, res: dict, m: RayFrontsMap, frames: list[BenchFrame], K: np.ndarray,
              use_kernels: bool) -> dict:
    """One map fed every frame (per window with ``--growing``), flushed and queried; ``res`` completed."""
    import os

    import torch

    from apps.bench import meta

    n = len(frames)
    side = FeedSide("main", m, not args.no_pipeline, use_kernels, args.threads)
    windows = []
    step = args.window if args.growing else n
    with meta.timed("integrate", frames=n):
        for s in range(0, n, step):
            c0, w0, st0 = side.cpu, side.wall, dict(side.stages)
            load0 = meta.loadavg()
            side.feed(frames[s:s + step], K)
            if args.growing:
                windows.append(window_record(side, s, min(step, n - s), c0, w0, st0, load0))
    side.close()
    t1 = time.perf_counter()
    m.flush()
    t2 = time.perf_counter()
    q = torch.randn(4, args.feature_dim)
    m.query(q)
    t3 = time.perf_counter()
    st = m.stats()
    summ = side.summary()
    res.update({
        "main_section": "integrate", "pipeline": not args.no_pipeline, "kernels": use_kernels,
        "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "frames_per_s": summ["frames_per_s"], "ms_per_frame": summ["wall_ms_per_frame"],
        "cpu_ms_per_frame": summ["cpu_ms_per_frame"],
        "flush_ms": round(1e3 * (t2 - t1), 2), "query_ms_4q": round(1e3 * (t3 - t2), 2),
        "stage_ms_per_frame": summ["stage_ms_per_frame"],
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "n_voxels": st["n_voxels"], "n_frontiers": st["n_frontiers"], "n_rays": st["n_rays"],
        "n_occupancy_active": st["n_occupancy_active"], "map_memory_mb": round(st["memory_bytes"] / 2**20, 2),
        "occupancy_memory_mb": round(st["occupancy_memory_bytes"] / 2**20, 2),
    })
    if args.growing:
        res["windows"] = windows
        res["window"] = step
        if len(windows) >= 2:
            res["growth_cpu_ratio"] = round(windows[-1]["cpu_ms_per_frame"] / windows[0]["cpu_ms_per_frame"], 3)
            res["growth_first_last_cpu_ms"] = [windows[0]["cpu_ms_per_frame"], windows[-1]["cpu_ms_per_frame"]]
        if len(windows) >= 3:   # the first window also carries start-up costs: the ratio without it
            res["growth_cpu_ratio_from_second"] = round(windows[-1]["cpu_ms_per_frame"]
                                                        / windows[1]["cpu_ms_per_frame"], 3)
    return res


def window_record(side: FeedSide, s: int, k: int, c0: float, w0: float, st0: dict[str, float],
                   load0: list[float]) -> dict:
    """``--growing``: one window of ``k`` frames from frame ``s`` (side totals before it: CPU
    ``c0``, wall ``w0``, stages ``st0``; load average ``load0``)."""
    from apps.bench import meta

    st = side.map.stats()
    return {"frames": [s, s + k], "cpu_ms_per_frame": round(1e3 * (side.cpu - c0) / k, 2),
            "wall_ms_per_frame": round(1e3 * (side.wall - w0) / k, 2),
            "load_before": load0, "load_after": meta.loadavg(),
            "stage_ms_per_frame": {key: round((v - st0.get(key, 0.0)) / k, 3)
                                   for key, v in sorted(side.stages.items())},
            "n_voxels": st["n_voxels"], "n_frontiers": st["n_frontiers"], "n_rays": st["n_rays"]}
