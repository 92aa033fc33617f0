"""``rayfronts eval fleet-compare``: fleets of N robots against one robot on the same missions.

Issue 44's aim, measured from ``eval search`` documents of one settings but for the fleet size:
the one-robot run (``--robots 1``, policy ``rayfronts``) and fleet runs (``--robots 2``, ``3``;
the policies of :data:`apps.closed_loop.fleet_episode.FLEET_POLICIES`). A mission is a (seed,
mission kind, episode, depth limit); per mission, fleet size and fleet policy:

* ``steps_ratio``: the fleet's steps until the target was found ÷ one robot's (a failed
  episode counts the mission's whole budget, whether it ran out of steps, collided or got
  stuck early — so against a one-robot failure the ratio is an upper bound: ``one_found``
  false);
* ``path_ratio``: the fleet's total path (all robots) ÷ one robot's path;
* ``bound_steps``: the fewest steps in which any robot of the fleet could have reached the
  target, ⌈(shortest_m − d) / step_m⌉ with ``shortest_m`` the oracle's path from the mission
  start and ``d`` the farthest robot start from it (a robot starting ``d`` m away has at least
  ``shortest_m − d`` m to drive, at most ``step_m`` per step); ``bound_ratio`` is that ÷ one
  robot's steps — no fleet starting there gets below it.

The summary per fleet size and policy adds up the missions: ``steps_ratio`` = Σ fleet steps ÷
Σ one-robot steps, ``path_ratio`` and ``bound_ratio`` likewise, ``found``, the mean duplicated
coverage and, for ``coordinated``, the missions it took fewer / as many / more steps than the
``uncoordinated`` fleet of its size. ``aim`` checks issue 44's aim on the largest fleet:
coordinated ``steps_ratio`` ≤ 0.5, ``path_ratio`` ≤ 1.5 and fewer steps in sum than
uncoordinated. Refused with one line: documents of other settings, no one-robot ``rayfronts``
rows, two documents of one fleet size with the same mission and policy.
"""
from __future__ import annotations

import math

from apps.closed_loop.fleet_episode import FLEET_POLICIES
from apps.closed_loop.merge import settings_differences

#: settings that may differ between the compared documents
COMPARE_ACROSS = ("seeds", "policies", "robots")
#: fleet-only settings (a one-robot document has none): compared between the fleet documents
FLEET_SETTINGS = ("start", "footprint_m")
#: issue 44's aim for the largest coordinated fleet: (steps ratio at most, path ratio at most)
AIM_STEPS_RATIO = 0.5
AIM_PATH_RATIO = 1.5


def _mission(r: dict) -> tuple:
    return (int(r["seed"]), str(r["kind"]), int(r["episode"]), float(r["depth_limit_m"]))


def _robots(doc: dict) -> int:
    return int(doc["settings"].get("robots", 1))


def _steps(r: dict) -> int:
    """Steps to find: the episode's, or the mission's budget when it failed (module docstring)."""
    return int(r["steps"]) if r["success"] else int(r.get("budget_steps", r["steps"]))


def bound_steps(shortest_m: float, starts: list, start: list, step_m: float) -> int:
    """⌈(shortest_m − the farthest of ``starts`` from ``start``) / step_m⌉, at least 0 (module docstring)."""
    d = max((math.dist(s, start) for s in starts), default=0.0)
    return max(0, math.ceil((float(shortest_m) - d) / float(step_m) - 1e-9))


def compare_fleets(docs: list[dict]) -> dict:
    """The per-mission comparison, its summary and the aim (module docstring) of ``docs``."""
    if not docs:
        raise ValueError("nothing to compare: give the one-robot run and at least one fleet run")
    for i, d in enumerate(docs, 1):
        if not isinstance(d, dict) or not {"settings", "episodes"} <= set(d):
            raise ValueError(f"document {i}: not an eval search document (no settings / episodes)")
    skip = COMPARE_ACROSS + FLEET_SETTINGS
    base = {k: v for k, v in docs[0]["settings"].items() if k not in skip}
    for i, d in enumerate(docs[1:], 2):
        diff = settings_differences(docs[0]["settings"], d["settings"], skip)
        if diff:
            raise ValueError(f"document {i}: settings differ from document 1 in {', '.join(diff)} "
                             f"(only {', '.join(COMPARE_ACROSS)} may differ)")
    fleets = [d for d in docs if _robots(d) > 1]
    for i, d in enumerate(fleets[1:], 2):
        diff = [k for k in FLEET_SETTINGS if d["settings"].get(k) != fleets[0]["settings"].get(k)]
        if diff:
            raise ValueError(f"fleet document {i}: {', '.join(diff)} differ from the first fleet document's")
    one = {_mission(r): r for d in docs if _robots(d) == 1 for r in d["episodes"] if r["policy"] == "rayfronts"}
    if not one:
        raise ValueError("no one-robot rayfronts episodes: add the --robots 1 --policies rayfronts run")
    step_m = float(docs[0]["settings"].get("step_m", 2.0))
    fleet: dict[tuple, dict] = {}
    for d in docs:
        n = _robots(d)
        if n == 1:
            continue
        for r in d["episodes"]:
            key = (n, r["policy"], _mission(r))
            if key in fleet:
                raise ValueError(f"{n} robots, {r['policy']}, seed {key[2][0]}: in more than one document")
            fleet[key] = r
    missions = []
    for (n, policy, m), r in sorted(fleet.items(), key=lambda kv: (kv[0][2], kv[0][0], _order(kv[0][1]))):
        o = one.get(m)
        if o is None:
            continue
        b = bound_steps(r["shortest_m"], r.get("starts") or [r["start"]], r["start"], step_m)
        missions.append({"seed": m[0], "kind": m[1], "episode": m[2], "depth_limit_m": m[3], "robots": n,
                         "policy": policy, "found": bool(r["success"]), "steps": _steps(r),
                         "ended_at": int(r["steps"]), "collided": bool(r.get("collided", False)),
                         "path_m": float(r["path_m"]), "duplicated_coverage": float(r.get("duplicated_coverage", 0.0)),
                         "one_found": bool(o["success"]), "one_steps": _steps(o),
                         "one_path_m": float(o["path_m"]),
                         "steps_ratio": _steps(r) / max(1, _steps(o)),
                         "path_ratio": float(r["path_m"]) / max(1e-9, float(o["path_m"])),
                         "bound_steps": b, "bound_ratio": b / max(1, _steps(o))})
    summary = _summarize(missions)
    return {"missions": missions, "summary": summary, "aim": _aim(summary),
            "one_robot": {"missions": len(one), "found": sum(bool(r["success"]) for r in one.values()),
                          "steps": sum(_steps(r) for r in one.values()),
                          "path_m": sum(float(r["path_m"]) for r in one.values())},
            "settings": {**base, "step_m": step_m,
                         **{k: fleets[0]["settings"].get(k) for k in FLEET_SETTINGS if fleets}},
            "inputs": [{"robots": _robots(d), "policies": d["settings"].get("policies"),
                        "seeds": d["settings"].get("seeds"), "meta": d.get("meta"),
                        "merged_from": [p.get("meta") for p in d.get("merged_from", [])] or None} for d in docs]}


def _order(policy: str) -> int:
    known = list(FLEET_POLICIES)
    return known.index(policy) if policy in known else len(known)


def _summarize(missions: list[dict]) -> list[dict]:
    out = []
    for n, policy in sorted({(m["robots"], m["policy"]) for m in missions}, key=lambda k: (k[0], _order(k[1]))):
        rows = [m for m in missions if m["robots"] == n and m["policy"] == policy]
        one_steps = sum(m["one_steps"] for m in rows)
        s = {"robots": n, "policy": policy, "missions": len(rows), "found": sum(m["found"] for m in rows),
             "one_found": sum(m["one_found"] for m in rows),
             "steps": sum(m["steps"] for m in rows), "one_steps": one_steps,
             "steps_ratio": sum(m["steps"] for m in rows) / max(1, one_steps),
             "path_ratio": sum(m["path_m"] for m in rows) / max(1e-9, sum(m["one_path_m"] for m in rows)),
             "bound_ratio": sum(m["bound_steps"] for m in rows) / max(1, one_steps),
             "duplicated_coverage": sum(m["duplicated_coverage"] for m in rows) / len(rows)}
        if policy == "coordinated":
            unc = {_mission(m): m["steps"] for m in missions if m["robots"] == n and m["policy"] == "uncoordinated"}
            pairs = [(m["steps"], unc[_mission(m)]) for m in rows if _mission(m) in unc]
            if pairs:
                s["vs_uncoordinated"] = {"fewer": sum(a < b for a, b in pairs), "same": sum(a == b for a, b in pairs),
                                         "more": sum(a > b for a, b in pairs), "steps": sum(a for a, _ in pairs),
                                         "uncoordinated_steps": sum(b for _, b in pairs)}
        out.append(s)
    return out


def _aim(summary: list[dict]) -> dict | None:
    coord = [s for s in summary if s["policy"] == "coordinated"]
    if not coord:
        return None
    s = max(coord, key=lambda x: x["robots"])
    vs = s.get("vs_uncoordinated")
    checks = {"steps_ratio": s["steps_ratio"] <= AIM_STEPS_RATIO, "path_ratio": s["path_ratio"] <= AIM_PATH_RATIO,
              "ahead_of_uncoordinated": None if vs is None else vs["steps"] < vs["uncoordinated_steps"]}
    return {"robots": s["robots"], "steps_ratio": s["steps_ratio"], "path_ratio": s["path_ratio"],
            "bound_ratio": s["bound_ratio"], "checks": checks,
            "met": all(v is True for v in checks.values())}


def compare_markdown(doc: dict) -> str:
    """The per-mission table and the summary of :func:`compare_fleets`' document."""
    lines = ["| seed | robots | policy | found | steps (one robot) | steps ratio | bound ratio | total path m "
             "(one robot) | path ratio | duplicated coverage |", "|---|---|---|---|---|---|---|---|---|---|"]
    for m in doc["missions"]:
        found = "yes" if m["found"] else ("collided" if m["collided"] else "no") + f" (ended at {m['ended_at']})"
        lines.append(f"| {m['seed']} | {m['robots']} | {m['policy']} | {found} | "
                     f"{m['steps']} ({m['one_steps']}{'' if m['one_found'] else ', not found'}) | "
                     f"{m['steps_ratio']:.2f} | {m['bound_ratio']:.2f} | {m['path_m']:.0f} ({m['one_path_m']:.0f}) | "
                     f"{m['path_ratio']:.2f} | {m['duplicated_coverage']:.2f} |")
    o = doc["one_robot"]
    lines += ["", f"One robot (rayfronts): found {o['found']}/{o['missions']}, {o['steps']} steps, "
                  f"{o['path_m']:.0f} m.",
              "", "| robots | policy | found | steps ratio | bound ratio | path ratio | duplicated coverage | "
              "coordinated vs uncoordinated (fewer / same / more steps) |", "|---|---|---|---|---|---|---|---|"]
    for s in doc["summary"]:
        vs = s.get("vs_uncoordinated")
        v = (f"{vs['fewer']} / {vs['same']} / {vs['more']} ({vs['steps']} vs {vs['uncoordinated_steps']} steps)"
             if vs else "–")
        lines.append(f"| {s['robots']} | {s['policy']} | {s['found']}/{s['missions']} | {s['steps_ratio']:.2f} | "
                     f"{s['bound_ratio']:.2f} | {s['path_ratio']:.2f} | {s['duplicated_coverage']:.2f} | {v} |")
    a = doc.get("aim")
    if a:
        lines += ["", f"Aim ({a['robots']} coordinated robots: steps ≤ {AIM_STEPS_RATIO}× one robot's, total path ≤ "
                      f"{AIM_PATH_RATIO}×, ahead of uncoordinated): {'met' if a['met'] else 'not met'} — steps "
                      f"{a['steps_ratio']:.2f}× (no fleet starting there below {a['bound_ratio']:.2f}×), path "
                      f"{a['path_ratio']:.2f}×, ahead of uncoordinated: {a['checks']['ahead_of_uncoordinated']}."]
    return "\n".join(lines) + "\n"
