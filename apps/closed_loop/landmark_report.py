"""``rayfronts eval landmarks``: where each far-landmark episode started and ended, against
the world's landmarks — the target and its look-alike (the other landmark class).

A search run's landmark missions (kind ``landmark``) have a target class of
:data:`apps.closed_loop.missions.TARGETS` (water tower or radio tower; the teddy bear or the
robot statue); the other landmark class of the world is its look-alike. The world is rebuilt
from its seed (:func:`apps.closed_loop.evaluate.make_world`; deterministic), so a committed run
needs nothing but its JSON. Per episode (seed, mission, depth limit):

* ``landmarks``: every landmark instance with its horizontal distance (m) from the start to
  its box centre and its bearing (degrees counter-clockwise from +x, world frame z up),
  nearest first; ``target_nearer``: the target's nearest instance is nearer than every
  look-alike instance (a tie counts as not nearer);
* per policy: success, SPL, path, false finds, the end (xy, m), the horizontal distance from
  the end to each landmark class's nearest instance (``end_m``), and ``by_look_alike``: a
  failed episode that ended within ``near_m`` of a look-alike instance.

``summary`` per policy: episodes and finds where the target was the nearer landmark and where a
look-alike was, and how many failures ended by a look-alike.

With the episodes' traces (``eval search --trace DIR``; ``traces``: the directory) each policy
row adds ``traced_steps`` and ``rays_at``: per landmark class, the steps whose strongest ray
(the first of the step's ``rays``) points within :data:`RAY_AT_DEG` of the horizontal bearing
from the ray's goal to that class's nearest instance centre.
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from apps.closed_loop.missions import TARGETS

#: default: a failed episode ending this close (m, horizontal, to the box centre) to a
#: look-alike counts as ended by it
NEAR_M = 30.0
#: a ray points at a landmark when its heading is within this many degrees of the bearing
#: from its goal to the landmark's centre (horizontal)
RAY_AT_DEG = 15.0


def _landmarks(world, classes: list[str]) -> list[tuple[str, int, np.ndarray]]:
    """(class, instance id, box centre xy) of every instance of ``classes`` in ``world``."""
    out = []
    for name in classes:
        cid = world.classes.index(name)
        out += [(name, int(i.id), np.asarray(i.center[:2], np.float64)) for i in world.instances_of(cid)]
    return out


def _rays_at(trace: list[dict], marks: list) -> dict[str, int]:
    """Per landmark class: the steps of ``trace`` whose strongest ray points at it."""
    out = {name: 0 for name, _, _ in marks}
    for s in trace:
        if not s.get("rays"):
            continue
        r = s["rays"][0]
        p = np.asarray(r["position"][:2], np.float64)
        for name in out:
            off = min(abs((math.degrees(math.atan2(c[1] - p[1], c[0] - p[0])) - r["heading_deg"] + 180.0) % 360.0
                          - 180.0) for n, _, c in marks if n == name)
            out[name] += off <= RAY_AT_DEG
    return out


def _policy_row(e: dict, marks: list, target: str, near_m: float) -> dict:
    end = np.asarray(e["end"][:2], np.float64)
    end_m: dict[str, float] = {}
    for name, _, c in marks:
        d = float(np.hypot(*(c - end)))
        end_m[name] = min(end_m.get(name, math.inf), d)
    by_look_alike = (not e["success"]) and any(d <= near_m for n, d in end_m.items() if n != target)
    return {"policy": e["policy"], "success": bool(e["success"]), "spl": float(e["spl"]),
            "path_m": float(e["path_m"]), "false_finds": int(e.get("false_finds", 0)),
            "end": [float(v) for v in end], "end_m": end_m, "by_look_alike": bool(by_look_alike)}


def landmark_report(docs: list[dict], near_m: float = NEAR_M,
                    make: Callable[[str, int], Any] | None = None, traces: str | Path | None = None) -> dict:
    """The report of the landmark episodes of ``docs`` (``eval search`` documents; module
    docstring). ``make(world, seed)`` builds a world (default ``make_world``); ``traces``: the
    ``--trace`` directory of the runs (an episode without a file there has no trace fields).
    ``ValueError`` when the documents hold no landmark episode or a landmark class is not in
    its world."""
    if make is None:
        from apps.closed_loop.evaluate import make_world

        make = make_world
    groups: dict[tuple, list[dict]] = {}
    for doc in docs:
        family = doc.get("settings", {}).get("world", "synthetic")
        for e in doc.get("episodes", []):
            if e.get("kind") == "landmark" and "robots" not in e:
                key = (family, int(e["seed"]), int(e.get("episode", 0)), float(e["depth_limit_m"]),
                       e.get("platform", ""), e["target"])
                groups.setdefault(key, []).append(e)
    if not groups:
        raise ValueError("no single-robot landmark episodes in the documents (run eval search --missions landmark)")
    rows = []
    built: dict[tuple[str, int], list] = {}
    for (family, seed, episode, depth, platform, target), eps in sorted(groups.items()):
        if (family, seed) not in built:
            world = make(family, seed)
            try:
                for name in TARGETS[family]["landmark"]:
                    if name not in world.classes:
                        raise ValueError(f"landmark class {name!r} is not in the {family} world of seed {seed}")
                built[(family, seed)] = _landmarks(world, TARGETS[family]["landmark"])
            finally:
                close = getattr(world, "close", None)
                if close is not None:
                    close()
        marks = built[(family, seed)]
        start = np.asarray(eps[0]["start"][:2], np.float64)
        listed = sorted(({"class": n, "id": i, "distance_m": float(np.hypot(*(c - start))),
                          "bearing_deg": float(math.degrees(math.atan2(c[1] - start[1], c[0] - start[0])))}
                         for n, i, c in marks), key=lambda m: m["distance_m"])
        own = min((m["distance_m"] for m in listed if m["class"] == target), default=math.inf)
        other = min((m["distance_m"] for m in listed if m["class"] != target), default=math.inf)
        rows.append({"world": family, "seed": seed, "episode": episode, "depth_limit_m": depth,
                     "platform": platform, "target": target, "start": [float(v) for v in start],
                     "landmarks": listed, "target_nearer": bool(own < other),
                     "policies": [_traced(_policy_row(e, marks, target, near_m), e, marks, traces) for e in eps]})
    return {"near_m": near_m, "episodes": rows, "summary": _summary(rows),
            "sources": [{"commit": d.get("meta", {}).get("commit"), "argv": d.get("meta", {}).get("argv")}
                        for d in docs]}


def _traced(row: dict, e: dict, marks: list, traces: str | Path | None) -> dict:
    """``row`` with ``traced_steps`` and ``rays_at`` when ``traces`` holds the episode's trace."""
    if traces is None:
        return row
    from apps.closed_loop.evaluate import trace_name

    f = Path(traces) / trace_name(e)
    if not f.is_file():
        return row
    steps = json.loads(f.read_text())["trace"]
    return {**row, "traced_steps": len(steps), "rays_at": _rays_at(steps, marks)}


def _summary(rows: list[dict]) -> dict:
    out: dict[str, dict] = {}
    for r in rows:
        side = "target_nearer" if r["target_nearer"] else "look_alike_nearer"
        for p in r["policies"]:
            s = out.setdefault(p["policy"], {k: {"episodes": 0, "found": 0, "by_look_alike": 0}
                                             for k in ("target_nearer", "look_alike_nearer")})[side]
            s["episodes"] += 1
            s["found"] += p["success"]
            s["by_look_alike"] += p["by_look_alike"]
    return out


def report_markdown(rep: dict) -> str:
    """Per episode and policy, then the summary, as Markdown."""
    policies = list(dict.fromkeys(p["policy"] for r in rep["episodes"] for p in r["policies"]))
    lines = ["| world | platform | depth m | seed | start | target | landmarks (distance, bearing) | "
             + " | ".join(policies) + " |", "|" + "---|" * (7 + len(policies))]
    for r in rep["episodes"]:
        marks = "; ".join(f"{m['class']} #{m['id']} {m['distance_m']:.0f} m, {m['bearing_deg']:.0f}°"
                          for m in r["landmarks"])
        cells = []
        by = {p["policy"]: p for p in r["policies"]}
        for name in policies:
            p = by.get(name)
            if p is None:
                cells.append("")
                continue
            if p["success"]:
                cell = f"**found**, SPL {p['spl']:.2f}"
            else:
                nearest = min(p["end_m"], key=p["end_m"].get)
                cell = f"ended {p['end_m'][nearest]:.0f} m from the {nearest}"
            if p["false_finds"]:
                cell += f"; {p['false_finds']} false"
            if "rays_at" in p:
                cell += "; strongest ray at " + ", ".join(f"{k} {v}" for k, v in p["rays_at"].items()) + \
                    f" of {p['traced_steps']} steps"
            cells.append(cell)
        lines.append(f"| {r['world']} | {r['platform']} | {r['depth_limit_m']:g} | {r['seed']} | "
                     f"({r['start'][0]:.0f}, {r['start'][1]:.0f}) | {r['target']}"
                     f"{'' if r['target_nearer'] else ' (look-alike nearer)'} | {marks} | " + " | ".join(cells) + " |")
    lines += ["", f"| policy | target nearer: found | look-alike nearer: found | failures ended ≤ {rep['near_m']:g} m "
              "from a look-alike |", "|---|---|---|---|"]
    for name, s in rep["summary"].items():
        t, o = s["target_nearer"], s["look_alike_nearer"]
        lines.append(f"| {name} | {t['found']}/{t['episodes']} | {o['found']}/{o['episodes']} | "
                     f"{t['by_look_alike'] + o['by_look_alike']} |")
    return "\n".join(lines) + "\n"
