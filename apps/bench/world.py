"""``rayfronts bench world``: rendering throughput of the synthetic world (frames/s).

Each resolution is one timed section (:mod:`apps.bench.meta`), so the JSON also has the
process CPU ms per frame of each (``cpu_ms_per_frame_WxH``)."""
from __future__ import annotations

import argparse
import time

HELP = "synthetic-world rendering speed (frames/s at 224x224 and 640x480)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=30, help="frames rendered per resolution (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="world seed (default 0)")
    parser.add_argument("--preset", choices=["ground", "drone"], default="ground", help="trajectory (default ground)")
    parser.add_argument("--hfov", type=float, default=90.0, help="horizontal field of view, degrees (default 90)")


def run(args: argparse.Namespace) -> dict:
    from apps.bench import meta
    from synthetic_world.scene import World

    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    t = time.perf_counter()
    world = World.generate(args.seed)
    gen_s = time.perf_counter() - t
    poses = world.trajectory(args.preset, args.frames, seed=args.seed)
    result = {"target": "world", "seed": args.seed, "trajectory": args.preset, "frames": args.frames,
              "hfov_deg": args.hfov, "n_primitives": world.n_primitives, "n_instances": len(world.instances),
              "n_classes": len(world.classes), "generate_s": round(gen_s, 4), "main_section": None}
    for h, w in ((224, 224), (480, 640)):
        K = world.camera((h, w), args.hfov)
        world.render(poses[0], K, (h, w))  # warm-up (ray cache)
        with meta.timed(f"render_{w}x{h}", frames=args.frames) as sec:
            for p in poses:
                world.render(p, K, (h, w))
        r = sec.result
        result[f"fps_{w}x{h}"] = round(args.frames / r["wall_s"], 2)
        result[f"ms_per_frame_{w}x{h}"] = round(1000 * r["wall_s"] / args.frames, 2)
        result[f"cpu_ms_per_frame_{w}x{h}"] = r["cpu_ms_per_frame"]
    return result
