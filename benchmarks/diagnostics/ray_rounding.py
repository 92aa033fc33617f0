"""Diagnostic: the rays that stand out for a far landmark in the first steps of a closed-loop
tower episode, and whether they survive without the wire's float16 rounding.

For each step it prints the map's rays with the largest ``ray_z`` for the target: ``ray_z``,
the distinct cosine it is the z-score of (``mapper.search_answer.distinct_cosines``), the
ray's heading (degrees, yaw in the xy plane) and its origin (m). With ``--float32`` the
edge chain keeps the PCA coefficients float32 and skips the wire's encode/decode (``q16z``
decodes to float16), so what stands out only through rounding falls away. The search's floor
(``search.ray_cosine_resolution``, which sets such rays' ``ray_z`` to 0) is set aside unless
``--floor``.

    .venv/bin/python benchmarks/diagnostics/ray_rounding.py --seed 19 --steps 6
    .venv/bin/python benchmarks/diagnostics/ray_rounding.py --seed 19 --steps 6 --float32

A diagnostic, not part of the product: it wraps two search functions to read their values.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

import apps.closed_loop.sensing as sensing
import common.wire as wire
import edge.runtime as edge_runtime
import mapper.search_answer as search_answer
from apps.closed_loop.episode import LoopSettings, run_episode
from apps.closed_loop.evaluate import SearchEvalConfig, seed_missions
from apps.closed_loop.robot import Platform
from synthetic_world import World


def _float32_coefficients(pca, feats) -> np.ndarray:
    f = feats if isinstance(feats, torch.Tensor) else torch.as_tensor(np.asarray(feats))
    c, h, w = f.shape
    z = torch.as_tensor(np.asarray(pca.compress(f.reshape(c, h * w).T.to(torch.float32))))
    return z.T.reshape(-1, h, w).to(torch.float32).cpu().numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--depth-limit", type=float, default=20.0)
    ap.add_argument("--policy", default="rayfronts")
    ap.add_argument("--top", type=int, default=4, help="rays printed per step")
    ap.add_argument("--float32", action="store_true", help="no float16 on the way from encoder to map")
    ap.add_argument("--floor", action="store_true",
                    help="keep search.ray_cosine_resolution (by default it is set aside, to show the rounding)")
    args = ap.parse_args()

    if args.float32:
        wire.encode_frame = lambda frame, feature_codec=None: frame
        wire.decode_frame = lambda frame: frame
        edge_runtime.compress_features = _float32_coefficients
    distinct: dict[str, np.ndarray] = {}
    outlier_z, look_next = search_answer.ray_outlier_z, search_answer.look_next

    def record_z(values, resolution=0.0):
        distinct["v"] = np.asarray(values)[0].copy()
        return outlier_z(values, resolution if args.floor else 0.0)

    def report(grid, vox, frontiers, origins, dirs, scores, targets, from_xyz, **kw):
        v, z = distinct["v"], kw["ray_z"][:, 0]
        if len(z) == len(v):                       # the whole map's rays are the area's
            heading = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0]))
            print(f"rays {len(v)}  median distinct cosine {np.median(v):.2e}  max |.| {np.abs(v).max():.2e}")
            for i in np.argsort(-z)[:args.top]:
                print(f"   ray_z {z[i]:10.1f}  distinct {v[i]: .3e}  heading {heading[i]:5.0f}  "
                      f"at {np.round(origins[i, :2]).astype(int)}")
        return look_next(grid, vox, frontiers, origins, dirs, scores, targets, from_xyz, **kw)

    search_answer.ray_outlier_z = record_z
    search_answer.look_next = report
    world = World.generate(args.seed)
    (_, _, mission), = seed_missions(SearchEvalConfig(missions=["landmark"], seeds=[args.seed]), world,
                                     Platform.make("ground"), args.seed)
    mission = dataclasses.replace(mission, budget_steps=args.steps)
    target = mission.instances[0].center[:2] - mission.start[:2]
    print(f"seed {args.seed}: {mission.target} {np.hypot(*target):.0f} m away at heading "
          f"{np.degrees(np.arctan2(target[1], target[0])):.0f}; float32: {args.float32}")
    for inst in world.instances:
        if inst.name.startswith("radio_tower"):
            d = inst.center[:2] - mission.start[:2]
            print(f"radio tower {np.hypot(*d):.0f} m away at heading {np.degrees(np.arctan2(d[1], d[0])):.0f}")
    run_episode(world, mission, args.policy, LoopSettings(depth_limit_m=args.depth_limit),
                chain=sensing.EdgeChain(world, sensing.SensorConfig(resolution=224)))


if __name__ == "__main__":
    main()
