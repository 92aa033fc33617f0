"""The seeds of ``rayfronts eval search``, in one place (docs/pybullet_world.md#seeds).

Development seeds are the ones thresholds and rules may be tuned on (every figure of an
analysis that changes the method comes from them); held-out seeds are run only for a final
table, after everything it depends on is fixed, and are not looked at before. Seeds 0-29 of
the synthetic world have been looked at in earlier rounds, so they are all development seeds;
the held-out seeds start at 100 for both world families. Every eval JSON names the seeds it
ran and which of these sets they belong to (:func:`seed_sets`).
"""
from __future__ import annotations

#: world family -> seeds for tuning and analysis
DEVELOPMENT_SEEDS: dict[str, list[int]] = {"synthetic": list(range(0, 30)), "pybullet": list(range(0, 20))}
#: world family -> seeds for the final tables only
HELD_OUT_SEEDS: dict[str, list[int]] = {"synthetic": list(range(100, 120)), "pybullet": list(range(100, 120))}


def seed_sets(world: str, seeds: list[int]) -> dict:
    """What the eval JSON says of a run's ``seeds`` on ``world``: the seeds, the development
    and held-out lists of that world family and which of them the run used (``development``,
    ``held-out``, ``mixed`` or ``other``)."""
    dev, held = set(DEVELOPMENT_SEEDS.get(world, [])), set(HELD_OUT_SEEDS.get(world, []))
    s = set(seeds)
    kind = "development" if s <= dev else "held-out" if s <= held else "mixed" if s & (dev | held) else "other"
    return {"run": list(seeds), "set": kind, "development": sorted(dev), "held_out": sorted(held)}
