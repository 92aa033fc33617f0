"""Diagnostic: where a far-landmark episode's metres go, by what the policy was doing.

Runs one tower episode per policy (the same world, start and target as ``rayfronts eval
search``) with a step trace and splits the path by the reason of each step's decision
(``Decision.why``, grouped):

* ``explore``   — geometric exploration, no semantic evidence (``frontier gain/path``);
* ``rays``      — following rays that stand out (``ray z``, ``bearing``, ``beyond``) or
  probabilities (``rays p``) or the rays' crossing (``toward estimate``);
* ``approach``  — driving to a found instance (``approach``, ``declare``);
* ``held``      — a goal held from an earlier step; ``other`` — anything else.

For each group: metres driven, steps, and the horizontal distance to the nearest target
instance it took off (metres gained toward the target; the straight-line distance is a lower
bound on any path, so ``driven − gained`` is what that part of the episode spent beyond it).
Also by distance band to the target (> 200, 200–80, 80–40, < 40 m). With ``--json`` the
breakdown is written per policy.

    .venv/bin/python benchmarks/diagnostics/where_the_metres_go.py --platform drone --seed 12 \
        --json out/drone12.json --rerun out/drone12

A diagnostic, not part of the product; run it on development seeds.
"""
from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from apps.closed_loop.episode import LoopSettings, Trace, run_episode
from apps.closed_loop.evaluate import SearchEvalConfig, seed_missions
from apps.closed_loop.robot import Platform
from apps.closed_loop.sensing import EdgeChain, SensorConfig
from synthetic_world import World

BANDS_M = (200.0, 80.0, 40.0)


def group(why: str) -> str:
    """The group of a decision's reason (module docstring)."""
    if why.startswith("frontier"):
        return "explore"
    if why.startswith(("ray z", "bearing", "beyond", "rays", "toward estimate")):
        return "rays"
    if why.startswith(("approach", "declare")):
        return "approach"
    if why.startswith("held"):
        return "held"
    return "other"


def band(d: float) -> str:
    """The distance band (m) of a horizontal distance ``d`` to the target."""
    for b in BANDS_M:
        if d > b:
            return f">{b:.0f}"
    return f"<{BANDS_M[-1]:.0f}"


def _off_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) between two xy vectors (0 when either is ~0)."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-6 or nb < 1e-6:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def breakdown(positions: list, why: list, target_xy: np.ndarray, goals: list | None = None) -> dict:
    """Per group and per distance band: metres driven, steps, metres gained toward the target
    (``target_xy``: (K, 2) instance centres; the nearest counts), and the median angle off the
    target's bearing of the goal (``goals``: each step's goal xy or None) and of the move."""
    pos = np.asarray(positions, np.float64)[:, :2]
    near = np.argmin(np.linalg.norm(pos[:, None, :] - target_xy[None], axis=2), axis=1)
    dist = np.linalg.norm(pos - target_xy[near], axis=1)
    out: dict = {"by_reason": {}, "by_band": {}}
    angles: dict = {}
    first_rays = next((i for i, w in enumerate(why) if group(w) == "rays"), None)
    for i, w in enumerate(why):
        if i + 1 >= len(pos):
            break
        moved = float(np.linalg.norm(pos[i + 1] - pos[i]))
        gained = float(dist[i] - dist[i + 1])
        to_target = target_xy[near[i]] - pos[i]
        g = None if goals is None or i >= len(goals) else goals[i]
        for key, name in (("by_reason", group(w)), ("by_band", band(dist[i]))):
            e = out[key].setdefault(name, {"driven_m": 0.0, "gained_m": 0.0, "steps": 0})
            e["driven_m"] += moved
            e["gained_m"] += gained
            e["steps"] += 1
            a = angles.setdefault((key, name), {"goal": [], "move": [], "goal_m": []})
            if moved > 1e-6:
                a["move"].append(_off_deg(pos[i + 1] - pos[i], to_target))
            if g is not None:
                a["goal"].append(_off_deg(np.asarray(g[:2]) - pos[i], to_target))
                a["goal_m"].append(float(np.linalg.norm(np.asarray(g[:2]) - pos[i])))
    for (key, name), a in angles.items():
        for k, v in a.items():
            out[key][name][f"median_{k}_off_deg" if k != "goal_m" else "median_goal_m"] = \
                float(np.median(v)) if v else None
    out["start_m"], out["end_m"] = float(dist[0]), float(dist[-1])
    out["to_goals"] = to_goals(pos, goals or [None] * len(why))
    out["first_rays_step"] = first_rays
    out["first_rays_distance_m"] = None if first_rays is None else float(dist[first_rays])
    out["driven_before_first_rays_m"] = float(np.sum(np.linalg.norm(np.diff(pos[: (first_rays or 0) + 1], axis=0),
                                                                     axis=1))) if first_rays else 0.0
    return out


def to_goals(pos: np.ndarray, goals: list) -> dict:
    """The path against the straight line to the goals it drove to: over each run of steps with
    one goal, metres driven and metres the straight-line distance to that goal shrank
    (``driven_m / closed_m`` is the planner's detour through known free space)."""
    driven = closed = 0.0
    n, i = 0, 0
    while i < len(goals):
        j = i
        while j + 1 < len(goals) and goals[j + 1] is not None and goals[i] is not None \
                and np.allclose(goals[j + 1], goals[i]):
            j += 1
        if goals[i] is not None and j + 1 < len(pos):
            g = np.asarray(goals[i][:2], np.float64)
            driven += float(np.linalg.norm(np.diff(pos[i:j + 2], axis=0), axis=1).sum())
            closed += float(np.linalg.norm(g - pos[i]) - np.linalg.norm(g - pos[j + 1]))
            n += 1
        i = j + 1
    return {"goals": n, "driven_m": driven, "closed_m": closed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--platform", choices=["ground", "drone"], default="ground")
    ap.add_argument("--depth-limit", type=float, default=20.0)
    ap.add_argument("--policies", default="rayfronts,spherical")
    ap.add_argument("--budget-scale", type=float, default=None, help="default: 1.5 for the drone, 1 on the ground")
    ap.add_argument("--json", default="", help="the breakdown and each step's position, goal and reason")
    ap.add_argument("--rerun", default="", help="PREFIX: record each policy's episode to PREFIX-<policy>.rrd")
    args = ap.parse_args()

    scale = args.budget_scale if args.budget_scale is not None else (1.5 if args.platform == "drone" else 1.0)
    cfg = SearchEvalConfig(missions=["landmark"], seeds=[args.seed], platform=args.platform, budget_scale=scale)
    world = World.generate(args.seed)
    robot = Platform.make(args.platform)
    (_, _, mission), = seed_missions(cfg, world, robot, args.seed)
    chain = EdgeChain(world, SensorConfig(resolution=224))
    settings = LoopSettings(platform=args.platform, depth_limit_m=args.depth_limit)
    target_xy = np.array([i.center[:2] for i in mission.instances])
    print(f"seed {args.seed} {args.platform}: {mission.target}, oracle {mission.shortest_m:.0f} m, "
          f"budget {mission.budget_steps} steps")
    doc: dict = {"seed": args.seed, "platform": args.platform, "depth_limit_m": args.depth_limit,
                 "target": mission.target, "shortest_m": mission.shortest_m, "policies": {}}
    for policy in args.policies.split(","):
        trace = Trace()
        row = run_episode(world, dataclasses.replace(mission), policy, settings, chain=chain, trace=trace)
        b = breakdown(trace.positions, trace.why, target_xy, trace.goals)
        b.update(success=row["success"], spl=row["spl"], path_m=row["path_m"], steps=row["steps"])
        doc["policies"][policy] = b
        if args.rerun:
            from apps.closed_loop.recording import record_episode

            record_episode(f"{args.rerun}-{policy}.rrd", world, mission, trace, row)
        b["trace"] = {"positions": np.asarray(trace.positions).round(2).tolist(), "why": trace.why,
                      "goals": [None if g is None else np.asarray(g).round(2).tolist() for g in trace.goals]}
        fr = b["first_rays_step"]
        print(f"{policy}: found {row['success']}  SPL {row['spl']:.2f}  path {row['path_m']:.0f} m  "
              f"start {b['start_m']:.0f} m → end {b['end_m']:.0f} m; first rays at step {fr} "
              f"({b['first_rays_distance_m'] or 0:.0f} m out, after {b['driven_before_first_rays_m']:.0f} m)")
        tg = b["to_goals"]
        print(f"   to its {tg['goals']} goals: driven {tg['driven_m']:.0f} m, straight-line distance to them "
              f"closed {tg['closed_m']:.0f} m")
        for key in ("by_reason", "by_band"):
            for name, e in sorted(b[key].items()):
                print(f"   {name:9s} driven {e['driven_m']:6.0f} m  gained {e['gained_m']:6.0f} m  "
                      f"spent {e['driven_m'] - e['gained_m']:6.0f} m  steps {e['steps']:4d}  goal off "
                      f"{e['median_goal_off_deg'] or 0:4.0f}° at {e['median_goal_m'] or 0:4.0f} m, move off "
                      f"{e['median_move_off_deg'] or 0:4.0f}°")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
