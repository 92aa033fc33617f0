"""Search instances (``found`` rows of a search answer: ``id``, ``centroid`` [x, y, z] m)
matched by position between two answers, for the tests that check what happens to their ids
(kept while the map grows, never reused after a restart)."""
from __future__ import annotations

import numpy as np


def match_by_position(before: list[dict], after: list[dict], max_m: float) -> tuple[list, list]:
    """(pairs, unmatched): each row of ``before`` paired with the row of ``after`` whose
    centroid is nearest to its own, if within ``max_m`` metres (3D); ``unmatched`` holds the
    rows of ``before`` with none that near. One ``after`` row may pair with several
    ``before`` rows (two fragments grown into one object)."""
    pairs, unmatched = [], []
    cen = np.array([a["centroid"] for a in after], np.float64).reshape(-1, 3)
    for b in before:
        d = np.linalg.norm(cen - np.asarray(b["centroid"], np.float64), axis=1)
        if len(d) and d.min() <= max_m:
            pairs.append((b, after[int(d.argmin())]))
        else:
            unmatched.append(b)
    return pairs, unmatched


def describe(row: dict) -> str:
    """``#id at (x, y, z)`` of a found row (for assertion messages)."""
    return f"#{row['id']} at ({', '.join(f'{v:.1f}' for v in row['centroid'])})"
