"""Beyond the mapped volume: the best semantic rays and triangulated estimates where rays
from different origins nearly cross (pure computation). World frame, metres, z up.

For two rays ``o1 + t1·d1`` and ``o2 + t2·d2`` (unit directions) the closest approach is at
``t1, t2`` minimising ``|o1 + t1 d1 − o2 − t2 d2|``. A pair gives an estimate when

* the origins are at least ``min_baseline_m`` apart and the directions at least
  ``min_angle_deg`` apart (else the crossing is ill-conditioned),
* both ``t1, t2`` are in ``(0, max_range_m]`` (in front of both origins),
* the gap ``|p1 − p2|`` is at most ``max_gap_m``.

The estimate is the midpoint of the two closest points; its uncertainty radius is
``gap / 2 + e · sqrt(1 + 1 / sin²(θ/2))`` with ``e = sin(angle_err) · max(t1, t2)`` the
lateral error of a direction known to ``angle_err`` (e.g. half the ray frontiers' angle
bin) and ``θ`` the acute angle between the rays: a point within ``e`` of both lines lies
in the intersection of two strips crossing at ``θ`` (half-diagonal ``e / sin(θ/2)``) and
within ``e`` across their common normal. To first order (``t`` measured at the estimate,
not at the true point) the true crossing point lies within it. Its score is the smaller of the two ray scores.
Estimates are kept greedily by score: one whose position lies inside a better estimate's
radius is dropped.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Estimate:
    """A triangulated target position (m) with ``radius_m`` uncertainty and its rays."""

    position: np.ndarray
    radius_m: float
    score: float
    rays: tuple[int, int]
    target: str | None = None

    def as_dict(self) -> dict:
        return dict(position=[float(v) for v in self.position], radius_m=float(self.radius_m),
                    score=float(self.score), target=self.target)


def closest_approach(o1, d1, o2, d2) -> tuple[float, float, float]:
    """``(t1, t2, gap)`` of the closest points of two lines (unit directions); ``t = nan``
    for parallel lines."""
    o1, d1, o2, d2 = (np.asarray(v, np.float64) for v in (o1, d1, o2, d2))
    w = o1 - o2
    b = float(d1 @ d2)
    dd, e = float(d1 @ w), float(d2 @ w)
    den = 1.0 - b * b
    if den < 1e-12:
        return math.nan, math.nan, float(np.linalg.norm(np.cross(w, d1)))
    t1 = (b * e - dd) / den
    t2 = (e - b * dd) / den
    return t1, t2, float(np.linalg.norm(w + t1 * d1 - t2 * d2))


def best_rays(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best rays by score (descending, ties by lower index)."""
    s = np.asarray(scores, np.float64).reshape(-1)
    return np.argsort(-s, kind="stable")[:max(0, int(k))]


def triangulate(origins: np.ndarray, dirs: np.ndarray, scores: np.ndarray, *, max_gap_m: float = 2.0,
                angle_err_deg: float = 5.0, min_angle_deg: float = 5.0, min_baseline_m: float = 0.5,
                max_range_m: float = 200.0, max_estimates: int = 10) -> list[Estimate]:
    """Estimates from every pair of the given rays (callers pass the best few: cost is
    quadratic); see the module docstring."""
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    s = np.asarray(scores, np.float64).reshape(-1)
    n = len(o)
    if n < 2:
        return []
    cos_min = math.cos(math.radians(min_angle_deg))
    sin_err = math.sin(math.radians(angle_err_deg))
    cands: list[Estimate] = []
    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(o[i] - o[j]) < min_baseline_m or abs(float(d[i] @ d[j])) > cos_min:
                continue
            t1, t2, gap = closest_approach(o[i], d[i], o[j], d[j])
            if not (0 < t1 <= max_range_m and 0 < t2 <= max_range_m) or gap > max_gap_m:
                continue
            p = 0.5 * (o[i] + t1 * d[i] + o[j] + t2 * d[j])
            half = 0.5 * math.acos(min(1.0, abs(float(d[i] @ d[j]))))
            rad = gap / 2 + sin_err * max(t1, t2) * math.sqrt(1.0 + 1.0 / math.sin(half) ** 2)
            cands.append(Estimate(p, rad, float(min(s[i], s[j])), (i, j)))
    cands.sort(key=lambda e: (-e.score, e.radius_m))
    kept: list[Estimate] = []
    for e in cands:
        if all(np.linalg.norm(e.position - k.position) > k.radius_m for k in kept):
            kept.append(e)
            if len(kept) >= max_estimates:
                break
    return kept
