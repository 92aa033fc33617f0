"""``rayfronts eval tune-sem-poses``: choose Semantic Poses' threshold on development seeds,
by the procedure the ray policies' thresholds went through (docs/pybullet_world.md#baselines).

Procedure: the same missions (``--seeds dev``: every development seed of the world family,
:data:`apps.closed_loop.seeds.DEVELOPMENT_SEEDS`; default missions landmark and object) run
with ``sem-poses`` alone once per candidate cut of the pose margin's z-score
(``--cuts``); the chosen cut has the best mean SPL over the far-target (``landmark``)
episodes — object episodes are the check that a low cut does not buy far targets with false
finds — ties going to the higher (more conservative) cut. Held-out seeds are refused: a
threshold chosen on them would make their table a development table. Output: one summary
per cut (overall and per mission kind), the choice and its SPL, every episode (with its
``cut``), the run's ``meta`` and ``seeds`` as in ``rayfronts eval search``.

Episodes are not run twice when the answer is known: the cut enters an episode only at the
steps where sem-poses' best pose by margin z-score heads toward a reachable goal (the cut
then decides between that goal and frontier exploration; each episode row lists those
steps' z-scores, ``pose_z``), and everything else is deterministic for a seed. So a seed's episodes at cut
``a`` are exactly its episodes at cut ``b`` when no z-score recorded in the ``b`` run lies
between the two (every comparison comes out the same, step by step); such a seed is
copied (``reused_from_cut``) instead of run. Seeds run one after another, each through
every cut in the order given (highest first fires least), so a run cut off holds whole
seeds, and the seed it was in up to its last finished cut: ``--resume PARTIAL.json`` (the
same settings) takes those episodes as run and goes on where it stopped.
"""
from __future__ import annotations

import copy
import dataclasses
import time
from pathlib import Path

from apps.closed_loop.evaluate import SearchEvalConfig, _write_json, run_search_eval, run_settings, summarize_policies
from apps.closed_loop.seeds import HELD_OUT_SEEDS, seed_sets

#: a z-score this close to either cut counts as between them (the rows round z to 1e-6)
Z_TOLERANCE = 1e-5

#: an episode row's outcome: what a rerun of the seed at the same cut must reproduce
#: (timings and the ``reused_from_cut`` mark aside)
OUTCOME_FIELDS = ("success", "spl", "path_m", "steps", "false_finds", "finds", "declarations", "end", "pose_z")


def far_target(summary: dict) -> dict:
    """A cut's summary over its far-target (``landmark``) episodes; the whole summary when no
    landmark episode ran."""
    return summary.get("by_kind", {}).get("landmark", summary)


def choose_cut(per_cut: dict[float, dict]) -> tuple[float, float]:
    """(cut, its far-target SPL): the best mean :func:`far_target` SPL, ties to the higher
    cut. ``per_cut``: cut → ``policies["sem-poses"]``."""
    best = max(per_cut, key=lambda c: (round(float(far_target(per_cut[c])["spl"]), 9), c))
    return best, float(far_target(per_cut[best])["spl"])


def same_episodes(rows: list[dict], ran_at: float, cut: float) -> bool:
    """Whether ``rows`` (one seed's sem-poses episodes, run at cut ``ran_at``) are also that
    seed's episodes at ``cut``: no recorded ``pose_z`` lies in ``[min, max)`` of the two
    cuts (within :data:`Z_TOLERANCE`, so a z at a cut counts as between)."""
    lo, hi = min(ran_at, cut), max(ran_at, cut)
    if lo == hi:
        return True
    for r in rows:
        if "pose_z" not in r:          # a row without the record proves nothing
            return False
        if any(lo - Z_TOLERANCE <= z < hi + Z_TOLERANCE for z in r["pose_z"]):
            return False
    return True


def reusable_cut(runs: dict[float, list[dict]], cut: float) -> float | None:
    """A cut already run for a seed (``runs``: cut → that seed's rows, as run or copied)
    whose episodes are the seed's episodes at ``cut`` (:func:`same_episodes`), the nearest
    first; None when the seed must be run."""
    for c in sorted(runs, key=lambda c: (abs(c - cut), c)):
        if same_episodes(runs[c], c, cut):
            return c
    return None


def tune_sem_poses(cfg: SearchEvalConfig, cuts: list[float], argv: list[str] | None = None,
                   partial_path: str | None = None, resume: dict | None = None) -> dict:
    """Run the procedure (module docstring) on ``cfg``'s seeds and missions; returns the JSON.
    ``partial_path``: the document so far (``"partial": true``) is written there after every
    cut of every seed, so a run cut off keeps what it did. ``resume``: such a document (or a
    finished one) of the same settings; its episodes of ``cfg``'s seeds count as run (its
    counts and CPU time are carried on, its ``meta`` kept under ``resumed_from``)."""
    held = set(HELD_OUT_SEEDS.get(cfg.world, [])) & set(cfg.seeds)
    if held:
        raise ValueError(f"seeds {sorted(held)} are held-out seeds; tune on development seeds "
                         f"(--seeds dev)")
    if not cuts:
        raise ValueError("give at least one cut with --cuts")
    cuts = [float(c) for c in dict.fromkeys(cuts)]
    by_seed: dict[int, dict[float, list[dict]]] = {s: {} for s in cfg.seeds}
    last: dict = {}
    t0, cpu_s, ran, reused = time.perf_counter(), 0.0, 0, 0
    if resume is not None:
        resumed_rows(resume, cfg, cuts, by_seed)
        cpu_s, ran, reused = float(resume["cpu_s"]), int(resume["episodes_run"]), int(resume["episodes_reused"])
        t0 -= float(resume["wall_s"])
    for seed in cfg.seeds:
        for c in cuts:
            if c in by_seed[seed]:            # resumed
                continue
            src = reusable_cut(by_seed[seed], c)
            if src is not None:
                rows = [dict(copy.deepcopy(r), reused_from_cut=src) for r in by_seed[seed][src]]
                reused += len(rows)
            else:
                last = run_search_eval(dataclasses.replace(cfg, seeds=[seed], policies=["sem-poses"],
                                                           sem_poses_min_z=c), argv=argv)
                rows = last["episodes"]
                cpu_s += float(last["cpu_s"])
                ran += len(rows)
            by_seed[seed][c] = [dict(r, cut=c) for r in rows]
            if partial_path is not None:
                doc = _document(cfg.world, by_seed, cuts, last, ran, reused, time.perf_counter() - t0, cpu_s)
                _write_json(partial_path, {**doc, "partial": True, **_resumed(resume)})
    if partial_path is not None:
        Path(partial_path).unlink(missing_ok=True)
    if not last and resume is not None:         # nothing left to run: the resumed run's record
        last = {"settings": resume["settings"], "meta": resume.get("meta")}
    return {**_document(cfg.world, by_seed, cuts, last, ran, reused, time.perf_counter() - t0, cpu_s),
            **_resumed(resume)}


def resumed_rows(doc: dict, cfg: SearchEvalConfig, cuts: list[float], by_seed: dict[int, dict[float, list[dict]]]
                 ) -> None:
    """Put a resumed tuning's episodes of ``by_seed``'s seeds into ``by_seed`` (seed → cut →
    rows). Refused (ValueError): not a tuning document, other settings than ``cfg``'s (the
    seeds and cuts aside), a cut not in ``cuts``, a seed of this run without every earlier
    cut (the order of ``cuts``: a seed is run cut by cut)."""
    import json

    from apps.closed_loop.merge import settings_differences

    if not isinstance(doc, dict) or not {"procedure", "episodes", "settings", "cpu_s", "episodes_run",
                                         "episodes_reused", "wall_s"} <= set(doc):
        raise ValueError("--resume: not a tune-sem-poses document (no procedure / episodes / settings)")
    mine = json.loads(json.dumps(run_settings(dataclasses.replace(cfg, policies=["sem-poses"])), default=float))
    diff = settings_differences(mine, doc["settings"], ("seeds", "sem_poses_min_z"))
    if diff:
        raise ValueError(f"--resume: the resumed run's settings differ in {', '.join(diff)} (only the seeds may)")
    for r in doc["episodes"]:
        seed, c = int(r["seed"]), float(r["cut"])
        if c not in cuts:
            raise ValueError(f"--resume: the resumed run has cut {c:g}, not in --cuts")
        if seed in by_seed:
            by_seed[seed].setdefault(c, []).append(r)
    for seed, runs in by_seed.items():
        done = [c in runs for c in cuts]
        if any(done[i + 1] and not done[i] for i in range(len(cuts) - 1)):
            raise ValueError(f"--resume: seed {seed} lacks a cut before its last one in --cuts' order")


def _resumed(resume: dict | None) -> dict:
    """The ``resumed_from`` record of a resumed run (empty without one)."""
    if resume is None:
        return {}
    return {"resumed_from": {"meta": resume.get("meta"), "seeds_complete": resume.get("seeds_complete", []),
                             "episodes": len(resume["episodes"])}}


def merge_tunings(docs: list[dict]) -> dict:
    """One ``tune-sem-poses`` document from runs split by seed (processes side by side; a
    partial run counts with the seeds it finished): the cuts' summaries and the choice
    recomputed over every seed that went through every cut, the parts' ``meta`` under
    ``merged_from``. A seed's cut in two parts (a cut-off run's seed run again) is kept
    once, from the earlier part, when both give the same :data:`OUTCOME_FIELDS` (listed in
    ``reproduced``). Refused (ValueError): settings that differ in anything but the seeds,
    a seed's cut whose parts disagree."""
    from apps.closed_loop.merge import settings_differences

    if not docs:
        raise ValueError("nothing to merge: give at least one tune-sem-poses JSON")
    for i, d in enumerate(docs, 1):
        if not isinstance(d, dict) or not {"procedure", "episodes", "settings"} <= set(d):
            raise ValueError(f"part {i}: not a tune-sem-poses document (no procedure / episodes / settings)")
        diff = settings_differences(docs[0]["settings"], d["settings"], ("seeds", "sem_poses_min_z"))
        if diff:
            raise ValueError(f"part {i}: settings differ from part 1 in {', '.join(diff)} (only the seeds may)")
    cuts = list(dict.fromkeys(float(r["cut"]) for d in docs for r in d["episodes"]))
    by_seed: dict[int, dict[float, list[dict]]] = {}
    reproduced: list[dict] = []
    for i, d in enumerate(docs, 1):
        mine: dict[int, dict[float, list[dict]]] = {}
        for r in d["episodes"]:
            mine.setdefault(int(r["seed"]), {}).setdefault(float(r["cut"]), []).append(r)
        for seed, runs in mine.items():
            known = by_seed.setdefault(seed, {})
            for c, rows in runs.items():
                if c not in known:
                    known[c] = rows
                    continue
                diff = outcome_differences(known[c], rows)
                if diff:
                    raise ValueError(f"part {i}: seed {seed} at cut {c:g} is in an earlier part with another "
                                     f"outcome ({', '.join(diff)}); a rerun must reproduce it")
                reproduced.append({"seed": seed, "cut": c, "part": i})
    by_seed = dict(sorted(by_seed.items()))
    out = _document(str(docs[0]["settings"].get("world", "synthetic")), by_seed, cuts, docs[-1],
                    sum(int(d["episodes_run"]) for d in docs), sum(int(d["episodes_reused"]) for d in docs),
                    sum(float(d["wall_s"]) for d in docs), sum(float(d["cpu_s"]) for d in docs))
    out.pop("meta", None)
    out["merged_from"] = [{"seeds": sorted({int(r["seed"]) for r in d["episodes"]}), "meta": d.get("meta"),
                           "partial": bool(d.get("partial")), "wall_s": d["wall_s"], "cpu_s": d["cpu_s"]}
                          for d in docs]
    if reproduced:
        out["reproduced"] = reproduced
    if any(d.get("partial") for d in docs):
        out["partial"] = True
    return out


def outcome_differences(a: list[dict], b: list[dict]) -> list[str]:
    """The :data:`OUTCOME_FIELDS` in which two runs' rows (one seed at one cut) differ;
    ``["episodes"]`` when they hold different numbers of episodes."""
    if len(a) != len(b):
        return ["episodes"]
    return [k for k in OUTCOME_FIELDS if any(x.get(k) != y.get(k) for x, y in zip(a, b, strict=True))]


def _document(world: str, by_seed: dict[int, dict[float, list[dict]]], cuts: list[float], last: dict, ran: int,
              reused: int, wall_s: float, cpu_s: float) -> dict:
    """The JSON of the seeds run so far: the cuts' summaries over the seeds that went through
    every cut (``seeds_complete``); ``meta`` is the last run's, ``cpu_s`` the runs' total."""
    complete = [s for s, runs in by_seed.items() if all(c in runs for c in cuts)]
    per_cut = {c: summarize_policies([r for s in complete for r in by_seed[s][c]], ["sem-poses"])["sem-poses"]
               for c in cuts} if complete else {}
    out: dict = {"procedure": __doc__, "cuts": {str(c): s for c, s in per_cut.items()}, "seeds_complete": complete,
                 "episodes": [r for runs in by_seed.values() for c in cuts if c in runs for r in runs[c]],
                 "episodes_run": ran, "episodes_reused": reused,
                 "wall_s": wall_s, "cpu_s": cpu_s}
    if per_cut:
        out["chosen"], out["chosen_spl"] = choose_cut(per_cut)
    if last:
        settings = {k: v for k, v in last["settings"].items() if k != "sem_poses_min_z"}    # the cuts are above
        out.update(settings={**settings, "seeds": list(by_seed)}, seeds=seed_sets(world, list(by_seed)),
                   meta=last.get("meta"))
    return out
