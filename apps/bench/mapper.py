"""``rayfronts bench mapper``: RayFronts map throughput / memory on synthetic-world frames.

Frames are rendered up front (not timed) at the preset's resolution (throughput 224×224,
online 640×640) with random 100-dim features at 1/16 resolution (float16, as on the wire);
then every frame goes through :meth:`RayFrontsMap.integrate` and a final flush. The JSON
records whether the C++ kernels ran (``--no-kernels`` forces the torch paths) and the
machine's load average before the timed part (the numbers are only comparable at similar
load). Peak RSS includes the pre-rendered frames (``rss_after_render_mb``).
"""
from __future__ import annotations

import argparse
import resource
import time

HELP = "RayFronts map throughput and memory on synthetic frames (JSON)"

_RES = {"throughput": (224, 224), "online": (640, 640)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", choices=sorted(_RES), default="throughput",
                        help="map preset and input resolution (throughput: 224x224, 0.3 m; online: 640x640, 1 m)")
    parser.add_argument("--frames", type=int, default=300, help="frames to integrate (default 300)")
    parser.add_argument("--backend", choices=["auto", "vdb", "torch"], default="auto", help="occupancy backend")
    parser.add_argument("--feature-dim", type=int, default=100, help="feature channels (default 100, PCA size)")
    parser.add_argument("--depth-limit", type=float, default=20.0, help="simulated sensor range in m (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="world / feature seed")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1; more threads on a shared 2-core box slow torch down)")
    parser.add_argument("--trajectory", choices=["ground", "drone"], default="ground", help="camera trajectory")
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE", help="map config overrides")
    parser.add_argument("--no-kernels", action="store_true",
                        help="use the pure-torch paths instead of the C++ kernels (mapper._rfkernels); same results")


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run(args: argparse.Namespace) -> dict:
    import numpy as np
    import torch

    import os

    from common.config import parse_override
    from common.world import World
    from mapper import kernels
    from mapper.config import map_config
    from mapper.map import RayFrontsMap
    from mapper.occupancy import backend_name

    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    torch.set_num_threads(max(1, args.threads))
    hw = _RES[args.preset]
    over = {"depth_limit": args.depth_limit}
    for item in args.override:
        over.update(parse_override(item))
    cfg = map_config(args.preset, over)
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
    render_s = time.perf_counter() - t
    rss_before = _rss_mb()
    load_before = os.getloadavg()
    old_kernels = kernels.set_enabled(kernels.enabled() and not args.no_kernels)
    try:
        m = RayFrontsMap(cfg, args.feature_dim, "bench", occupancy_backend=args.backend)
        stages: dict[str, float] = {}
        t0 = time.perf_counter()
        for p, d, rgb, f in frames:
            for k, v in m.integrate(p, K, d, rgb, f).items():
                stages[k] = stages.get(k, 0.0) + v
        t1 = time.perf_counter()
        m.flush()
        t2 = time.perf_counter()
        q = torch.randn(4, args.feature_dim)
        m.query(q)
        t3 = time.perf_counter()
        used_kernels = kernels.enabled()
    finally:
        kernels.set_enabled(old_kernels)
    st = m.stats()
    n = len(frames)
    return {
        "target": "mapper", "preset": args.preset, "resolution_hw": list(hw), "frames": n,
        "backend": backend_name(args.backend), "threads": torch.get_num_threads(),
        "kernels": used_kernels, "kernels_available": kernels.available(),
        "load_avg_1_5_15": [round(x, 2) for x in load_before],
        "depth_limit": args.depth_limit, "feature_dim": args.feature_dim,
        "frames_per_s": round(n / (t1 - t0), 2), "ms_per_frame": round(1e3 * (t1 - t0) / n, 2),
        "flush_ms": round(1e3 * (t2 - t1), 2), "query_ms_4q": round(1e3 * (t3 - t2), 2),
        "stage_ms_per_frame": {k: round(v / n, 3) for k, v in sorted(stages.items())},
        "render_s_excluded": round(render_s, 2),
        "peak_rss_mb": round(_rss_mb(), 1), "rss_after_render_mb": round(rss_before, 1),
        "n_voxels": st["n_voxels"], "n_frontiers": st["n_frontiers"], "n_rays": st["n_rays"],
        "n_occupancy_active": st["n_occupancy_active"], "map_memory_mb": round(st["memory_bytes"] / 2**20, 2),
    }
