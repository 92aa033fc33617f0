"""Growth policy of the map's append-only row tables (semantic voxels, ray bins).

A table that outgrows its capacity is re-allocated with room for ``need`` rows plus one
sixteenth of that (at least ``min_step`` rows): at most ~6 % of the rows held are spare,
against up to 50 % with doubling, and every row is copied O(16) times over the table's life
(amortised O(1) per insert).
"""
from __future__ import annotations

GROWTH_FRACTION = 16   # spare rows after a growth = need // GROWTH_FRACTION
MIN_STEP = 1024        # ... but at least this many


def grown_capacity(cap: int, need: int, min_step: int = MIN_STEP) -> int:
    """Capacity for at least ``need`` rows: ``cap`` itself when it suffices, else ``need``
    plus the spare rows of the module docstring."""
    if need <= cap:
        return cap
    return need + max(need // GROWTH_FRACTION, min_step)
