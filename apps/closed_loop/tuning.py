"""``rayfronts eval tune-sem-poses``: choose Semantic Poses' threshold on development seeds,
by the procedure the ray policies' thresholds went through (docs/pybullet_world.md#baselines).

Procedure: the same missions (``--seeds dev``: every development seed of the world family,
:data:`apps.closed_loop.seeds.DEVELOPMENT_SEEDS`; default missions landmark and object) run
with ``sem-poses`` alone once per candidate cut of the pose margin's z-score
(``--cuts``); the chosen cut has the best mean SPL over the far-target (``landmark``)
episodes — object episodes are the check that a low cut does not buy far targets with false
finds — ties going to the higher (more conservative) cut. Held-out seeds are refused: a
threshold chosen on them would make their table a development table. Output: one summary
per cut (overall and per mission kind), the choice and its SPL, the run's ``meta`` and
``seeds`` as in ``rayfronts eval search``.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from apps.closed_loop.evaluate import SearchEvalConfig, run_search_eval
from apps.closed_loop.seeds import HELD_OUT_SEEDS


def choose_cut(per_cut: dict[float, dict]) -> tuple[float, float]:
    """(cut, its far-target SPL): the best mean ``landmark`` SPL (else overall SPL when no
    landmark episode ran), ties to the higher cut. ``per_cut``: cut → ``policies["sem-poses"]``."""
    def far_spl(s: dict) -> float:
        return float(s.get("by_kind", {}).get("landmark", s)["spl"])

    best = max(per_cut, key=lambda c: (round(far_spl(per_cut[c]), 9), c))
    return best, far_spl(per_cut[best])


def tune_sem_poses(cfg: SearchEvalConfig, cuts: list[float], argv: list[str] | None = None,
                   partial_path: str | None = None) -> dict:
    """Run the procedure (module docstring) on ``cfg``'s seeds and missions; returns the JSON.
    ``partial_path``: the cut being run writes its finished episodes there as it goes
    (:func:`run_search_eval`), and each finished cut's summary is kept beside it
    (``<partial_path>.cut<C>.json``), so a run cut off keeps what it did."""
    held = set(HELD_OUT_SEEDS.get(cfg.world, [])) & set(cfg.seeds)
    if held:
        raise ValueError(f"seeds {sorted(held)} are held-out seeds; tune on development seeds "
                         f"(--seeds dev)")
    if not cuts:
        raise ValueError("give at least one cut with --cuts")
    per_cut, docs = {}, {}
    for c in cuts:
        doc = run_search_eval(dataclasses.replace(cfg, policies=["sem-poses"], sem_poses_min_z=float(c)), argv=argv,
                              partial_path=partial_path)
        if partial_path is not None:
            Path(f"{partial_path}.cut{float(c)}.json").write_text(json.dumps(doc, indent=2, default=float))
        per_cut[float(c)] = doc["policies"]["sem-poses"]
        docs[float(c)] = doc
    chosen, spl = choose_cut(per_cut)
    last = docs[float(cuts[-1])]
    return {"procedure": __doc__, "cuts": {str(c): s for c, s in per_cut.items()}, "chosen": chosen,
            "chosen_spl": spl, "settings": last["settings"], "seeds": last["seeds"], "meta": last["meta"]}
