"""Episode metrics for closed-loop search: success-weighted path length (SPL) and summaries.

SPL of one episode = S · l / max(p, l) with S ∈ {0, 1} success, l the shortest true-world path
length to the nearest target (m) and p the path the robot drove (m); averaged over episodes.
"""
from __future__ import annotations

from typing import Sequence


def spl(success: bool, shortest_m: float, path_m: float) -> float:
    """SPL of one episode (0 when failed; 1 when the robot drove a shortest path)."""
    if not success:
        return 0.0
    if shortest_m <= 0.0:
        return 1.0
    return float(shortest_m / max(path_m, shortest_m))


def summarize(rows: Sequence[dict]) -> dict:
    """``{"success", "spl", "path_m", "false_finds", "episodes"}`` over episode rows with keys
    ``success`` (bool), ``spl``, ``path_m`` and ``false_finds`` (int)."""
    n = len(rows)
    if n == 0:
        return {"success": 0.0, "spl": 0.0, "path_m": 0.0, "false_finds": 0, "episodes": 0}
    return {"success": sum(bool(r["success"]) for r in rows) / n,
            "spl": sum(float(r["spl"]) for r in rows) / n,
            "path_m": sum(float(r["path_m"]) for r in rows) / n,
            "false_finds": int(sum(int(r["false_finds"]) for r in rows)),
            "episodes": n}
