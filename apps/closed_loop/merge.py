"""``rayfronts eval merge``: one ``eval search`` document from runs split by seed or policy.

A table's episodes are independent of each other: each seed builds its own world and edge
chain, and every episode restarts the sensor's and the encoder's random draws
(:meth:`apps.closed_loop.sensing.EdgeChain.start_episode`). So ``--seeds 100-105`` run as
two processes (``100-101`` and ``102-105``, on one machine's two cores or on two machines)
gives the same episode rows as one run, and :func:`merge_documents` rebuilds that run's
document: the seeds ascending, the policies in the parts' order (the built-in order when
the parts ran different policies), the rows in the order
one run writes them (seed, mission, depth limit, policy),
the per-policy summaries recomputed from them, and the parts' own ``meta`` (commit, command
line, machine, load) kept under ``merged_from``.

Refused with one line: runs whose settings differ in anything but the seeds and policies,
an episode present twice, a fleet run beside runs of another fleet size, a partial file
(``FILE.partial.json``) unless ``allow_partial`` (then only the seeds it has rows of count
as run, and the result says ``"partial": true``).
"""
from __future__ import annotations

from apps.closed_loop.evaluate import summarize_policies
from apps.closed_loop.fleet_episode import FLEET_POLICIES
from apps.closed_loop.policies import POLICIES
from apps.closed_loop.seeds import seed_sets

#: settings that may differ between the merged runs (what a run is split by)
SPLIT_BY = ("seeds", "policies")


def settings_differences(first: dict, other: dict, may_differ: tuple[str, ...]) -> list[str]:
    """The settings keys (sorted) in which two ``eval search`` documents' ``settings`` differ,
    leaving out ``may_differ``."""
    a = {k: v for k, v in first.items() if k not in may_differ}
    b = {k: v for k, v in other.items() if k not in may_differ}
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def _episode_key(r: dict) -> tuple:
    return (r["seed"], r["kind"], r["episode"], float(r["depth_limit_m"]), r["policy"], r.get("robots", 1))


def merge_documents(docs: list[dict], allow_partial: bool = False) -> dict:
    """One document from ``docs`` (``eval search`` JSON documents; module docstring)."""
    if not docs:
        raise ValueError("nothing to merge: give at least one eval search JSON")
    for i, d in enumerate(docs):
        if not isinstance(d, dict) or not {"settings", "episodes"} <= set(d):
            raise ValueError(f"part {i + 1}: not an eval search document (no settings / episodes)")
        if d.get("partial") and not allow_partial:
            raise ValueError(f"part {i + 1}: a partial run (its FILE.partial.json); pass --allow-partial to use it")
    base = {k: v for k, v in docs[0]["settings"].items() if k not in SPLIT_BY}
    for i, d in enumerate(docs[1:], 2):
        diff = settings_differences(docs[0]["settings"], d["settings"], SPLIT_BY)
        if diff:
            raise ValueError(f"part {i}: settings differ from part 1 in {', '.join(diff)} "
                             f"(only {' and '.join(SPLIT_BY)} may differ)")

    def part_seeds(d: dict) -> list[int]:        # a partial part holds the seeds it finished
        return sorted({int(r["seed"]) for r in d["episodes"]}) if d.get("partial") else list(d["settings"]["seeds"])

    seeds = sorted({int(s) for d in docs for s in part_seeds(d)})
    policies = list(docs[0]["settings"]["policies"])
    if any(list(d["settings"]["policies"]) != policies for d in docs):     # split by policy: the built-in order
        known = list(POLICIES) + list(FLEET_POLICIES)
        policies = sorted({p for d in docs for p in d["settings"]["policies"]},
                          key=lambda p: (known.index(p) if p in known else len(known), p))
    rows = [r for d in docs for r in d["episodes"]]
    seen: set = set()
    for r in rows:
        k = _episode_key(r)
        if k in seen:
            raise ValueError(f"episode seed {k[0]} {k[1]} #{k[2]} depth {k[3]:g} m {k[4]} is in more than one part")
        seen.add(k)
    kinds = list(dict.fromkeys(r["kind"] for r in rows))
    depths = list(dict.fromkeys(float(x) for x in base.get("depth_limits", [])))
    rows.sort(key=lambda r: (seeds.index(r["seed"]), kinds.index(r["kind"]), r["episode"],
                             depths.index(float(r["depth_limit_m"])) if float(r["depth_limit_m"]) in depths else 0,
                             policies.index(r["policy"])))
    parts = [{"seeds": part_seeds(d), "policies": d["settings"]["policies"], "meta": d.get("meta"),
              "machine": d.get("machine"), "wall_s": d.get("wall_s"), "cpu_s": d.get("cpu_s"),
              "partial": bool(d.get("partial"))} for d in docs]
    out = {"policies": summarize_policies(rows, policies),
           "settings": {**docs[0]["settings"], "seeds": seeds, "policies": policies},
           "episodes": rows,
           "seeds": seed_sets(str(base.get("world", "synthetic")), seeds),
           "merged_from": parts,
           "wall_s": sum(float(p["wall_s"] or 0.0) for p in parts),
           "cpu_s": sum(float(p["cpu_s"] or 0.0) for p in parts)}
    if any(p["partial"] for p in parts):
        out["partial"] = True
    return out
