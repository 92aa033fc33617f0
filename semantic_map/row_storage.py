"""Growth policy of the map's append-only row tables (semantic voxels, ray bins).

A table that outgrows its capacity is re-allocated with room for ``need`` rows plus one
32nd of that (at least ``min_step`` rows): at most ~3 % of the rows held are spare, against
up to 50 % with doubling, and every row is copied about 32 times over the table's life
(amortised O(1) per insert; at 1 M voxels of 220 B a growth copies ~220 MB, once per ~30 k
new voxels).
"""
from __future__ import annotations

GROWTH_FRACTION = 32   # spare rows after a growth = need // GROWTH_FRACTION
MIN_STEP = 1024        # ... but at least this many


def grown_capacity(cap: int, need: int, min_step: int = MIN_STEP) -> int:
    """Capacity for at least ``need`` rows: ``cap`` itself when it suffices, else ``need``
    plus the spare rows of the module docstring."""
    if need <= cap:
        return cap
    return need + max(need // GROWTH_FRACTION, min_step)
