"""Search policies: given what the map says this step (:class:`Observation`) and where the
robot can drive (:class:`NavField`), where to go next and which found instance to declare.

Every map-based policy confirms the same way: an undeclared found instance of the target
(the search's ``found``, stable ids) is driven to; once the robot is within ``reach_m``
(xy) of its box it is declared. They differ in how they explore until then:

* ``rayfronts``: the look-next goal with the best semantic score (rays of the RayFronts map
  toward the target, 30° bins), the nearest by path among goals within 10 % of the best;
  without evidence (score < ``min_score``) like ``frontier``;
* ``unidirectional`` / ``spherical``: the same rule on the maps of the paper's semantic
  frontier baselines (one 360° bin per frontier, direction inferred or none);
* ``frontier``: the frontier viewpoint with the best unknown volume per path length,
  ``gain_m3 / (1 + path_m)`` (information-gain exploration, no semantics);
* ``sem-poses``: toward the direction of the best-scoring camera pose (image-level features):
  the goal whose bearing from that pose is closest to its heading (cosine ≥ 0.8), nearest
  first; without evidence like ``frontier``;
* ``oracle``: the true shortest tour (:func:`apps.closed_loop.missions.oracle_tour`) —
  SPL's reference; it does not use the map.

A goal whose reachable cell is the robot's own (no progress) is set aside for the episode.
World frame, metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from apps.closed_loop.missions import xy_box_distance
from apps.closed_loop.navigation import NavField
from apps.closed_loop.world_model import Observation

#: policy name -> (map method of semantic_map.config.METHODS, semantic look-next, scores poses)
POLICIES: dict[str, tuple[str | None, bool, bool]] = {
    "rayfronts": ("rayfronts", True, False),
    "frontier": ("semantic_voxels", False, False),
    "unidirectional": ("unidirectional_semfronts", True, False),
    "spherical": ("spherical_semfronts", True, False),
    "sem-poses": ("semantic_voxels", False, True),
    "oracle": (None, False, False),
}


@dataclass
class Decision:
    """``goal_cell`` to drive toward (None: nowhere to go), ``declare`` a found instance dict
    to declare now, ``why`` a short reason (for logs and recordings)."""

    goal_cell: np.ndarray | None = None
    goal_xy: np.ndarray | None = None
    declare: dict | None = None
    why: str = ""
    score: float = 0.0


@dataclass
class PolicyState:
    """What a policy remembers over an episode."""

    declared: set = field(default_factory=set)
    set_aside: list = field(default_factory=list)     # xy of goals that gave no progress
    goal: tuple | None = None                         # (xy, score) of the exploration goal held


def _progress(nav: NavField, cell: np.ndarray) -> bool:
    return tuple(int(v) for v in cell) != nav.start


def _set_aside(state: PolicyState, xy: np.ndarray, radius: float = 1.5) -> bool:
    return any(np.linalg.norm(np.asarray(xy[:2]) - a) < radius for a in state.set_aside)


def confirm(obs: Observation, nav: NavField, at: np.ndarray, state: PolicyState, reach_m: float
            ) -> Decision | None:
    """Declare or approach the nearest undeclared found instance (None: nothing found)."""
    best = None
    for inst in obs.found:
        if inst["id"] in state.declared:
            continue
        lo, hi = np.asarray(inst["box_min"]), np.asarray(inst["box_max"])
        if xy_box_distance(at, lo, hi) <= reach_m - 0.5:
            return Decision(declare=inst, why=f"declare {inst['target']} #{inst['id']}")
        aim = np.clip(at[:2], lo[:2], hi[:2])
        cell, path_m, gap = nav.nearest_reachable(aim)
        if not _progress(nav, cell) or gap > 0.5 * reach_m + xy_box_distance(at, lo, hi):
            continue
        if best is None or path_m < best[0]:
            best = (path_m, cell, inst, aim)
    if best is None:
        return None
    return Decision(goal_cell=best[1], goal_xy=best[3], why=f"approach {best[2]['target']} #{best[2]['id']}")


def _reachable_goals(obs: Observation, nav: NavField, state: PolicyState) -> list[tuple[dict, np.ndarray, float]]:
    out = []
    for g in obs.look_next:
        xy = np.asarray(g["position"][:2])
        if _set_aside(state, xy):
            continue
        cell, path_m, gap = nav.nearest_reachable(xy)
        if not _progress(nav, cell):
            state.set_aside.append(xy)
            continue
        out.append((g, cell, path_m))
    return out


def explore(name: str, obs: Observation, nav: NavField, state: PolicyState, min_score: float = 0.3,
            min_goal_m: float = 4.0) -> Decision:
    """The exploration goal of policy ``name`` (module docstring). Goals closer than
    ``min_goal_m`` by path are being seen already; they are taken only when nothing else is."""
    goals = _reachable_goals(obs, nav, state)
    if not goals:
        state.goal = None
        return Decision(why="no reachable goal")
    held = _held(state, nav, goals)
    if held is not None:
        return held
    far = [x for x in goals if x[2] >= min_goal_m]
    goals = far or goals
    d = _choose(name, obs, goals, min_score)
    state.goal = (d.goal_xy, d.score)
    return d


def _held(state: PolicyState, nav: NavField, goals: list) -> Decision | None:
    """Keep driving to the held goal until it is reached (its cell is the robot's), set aside,
    or a goal with clearly more evidence (+0.2 score) appears."""
    if state.goal is None:
        return None
    xy, score = state.goal
    cell, path_m, gap = nav.nearest_reachable(xy)
    top = max(g["score"] for g, _, _ in goals)
    if not _progress(nav, cell) or gap > 2.0 or _set_aside(state, xy) or top > score + 0.2:
        if not _progress(nav, cell):
            state.set_aside.append(np.asarray(xy))
        state.goal = None
        return None
    return Decision(goal_cell=cell, goal_xy=xy, why="held goal", score=score)


def _choose(name: str, obs: Observation, goals: list, min_score: float) -> Decision:
    if name in ("rayfronts", "unidirectional", "spherical"):
        top = max(g["score"] for g, _, _ in goals)
        if top >= min_score:
            pool = [x for x in goals if x[0]["score"] >= 0.9 * top]
            g, cell, _ = min(pool, key=lambda x: x[2])
            return Decision(goal_cell=cell, goal_xy=np.asarray(g["position"][:2]), why=f"rays {g['score']:.2f}",
                            score=float(g["score"]))
    if name == "sem-poses" and obs.poses:
        o, d, s = max(obs.poses, key=lambda p: p[2])
        h = np.asarray(d[:2], np.float64)
        if s >= min_score and np.linalg.norm(h) > 1e-6:
            h = h / np.linalg.norm(h)
            pool = []
            for g, cell, path_m in goals:
                v = np.asarray(g["position"][:2]) - o[:2]
                if np.linalg.norm(v) > 1e-6 and float(v @ h) / np.linalg.norm(v) >= 0.8:
                    pool.append((g, cell, path_m))
            if pool:
                g, cell, _ = min(pool, key=lambda x: x[2])
                return Decision(goal_cell=cell, goal_xy=np.asarray(g["position"][:2]), why=f"pose {s:.2f}",
                                score=float(s))
    g, cell, _ = max(goals, key=lambda x: (x[0].get("gain_m3", 0.0) / (1.0 + x[2]), -x[2]))
    return Decision(goal_cell=cell, goal_xy=np.asarray(g["position"][:2]), why="frontier gain/path")


def decide(name: str, obs: Observation, nav: NavField, at: np.ndarray, state: PolicyState, reach_m: float
           ) -> Decision:
    """One step's decision of map-based policy ``name``."""
    d = confirm(obs, nav, at, state, reach_m)
    return d if d is not None else explore(name, obs, nav, state)
