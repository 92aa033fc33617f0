"""Fleet goal allocation: share look-next goals out across the robots of one search (pure
computation; world frame, metres, z up).

Candidates are look-next goals (:class:`planning.look_next.Goal`) computed once for the whole
fleet, best without ``from_xyz`` (then ``distance_m`` is 0 and the ranking is by evidence and
gain alone; with a fleet centroid as ``from_xyz`` the nearest frontiers of the centroid are
also examined). Their ``distance_m`` is ignored here: each robot's cost is its OWN path
length to the goal's viewpoint, ``path_m(robot, position)`` (default: the straight line from
the robot's position; ``inf`` or ``None`` = the robot cannot get there).

Objective (what :func:`allocate_goals` maximises, :attr:`Assignment.utility`)::

    U = Σ over robots r given a goal g   value(g) / (1 + path_m(r, g))

with ``value`` :func:`goal_value` by default: ``gain_m3 / gain_ref_m3 + evidence_weight ·
evidence(g)``, ``evidence(g) = max(score, RAY_Z_SHARE · min(max(ray_z, 0) / RAY_Z_FULL, 1))``
— the semantic gain of going there (unknown volume to be seen, in units of ``gain_ref_m3``,
plus the target evidence of the rays there, which outweighs any volume when it is present)
per metre of that robot's own path. Constraints: a robot gets at most one goal and a goal at
most one robot; the viewpoints of any two assigned goals are at least ``footprint_m`` apart
(no two robots sent to the same frontier region); a robot is never given a goal within
``unreachable_tol_m`` of a position it reported unreachable (:attr:`RobotSlot.unreachable`);
a robot with no feasible goal left gets ``None``.

Methods: ``greedy`` (default) repeatedly gives the pair (robot, goal) of highest utility
among those still feasible (ties: fleet order, then candidate order). Bound (proved in the
docstring of :func:`greedy_bound`, checked against ``brute_force`` in
tests/test_fleet_allocation.py): ``U_greedy ≥ U_opt / min(N, 1 + KISSING_3D)`` for N robots,
i.e. ≥ ½ of the optimum for two robots and ≥ ⅓ for three. ``brute_force`` enumerates every
assignment honouring the constraints (a depth-first search; exact, for small cases and as
the tests' reference; refused above ``max_combinations``).

Found instances: :func:`discount_found` takes the evidence off candidates that would send
robots toward a target's instance already confirmed (by any robot) — or toward any instance
of a target once ``target_count`` of them are found — so no robot is sent to find it again;
the frontiers stay candidates for their unknown volume. :func:`allocate_goals` applies it
when given ``found``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from planning.look_next import Goal

#: most points strictly inside a ball of radius r that lie pairwise ≥ r apart (3D kissing number)
KISSING_3D = 12
#: ``ray_z`` at which a goal's outlier evidence counts fully in :func:`goal_value`
RAY_Z_FULL = 10.0
#: the evidence a full-strength outlier ray is worth, next to a probability score of 1
RAY_Z_SHARE = 0.5
#: the methods of :func:`allocate_goals`
METHODS = ("greedy", "brute_force")


@dataclass(frozen=True)
class RobotSlot:
    """One robot of the fleet at this map update: ``robot`` its id, ``position`` (m, world
    frame), ``unreachable`` the goal positions (m) it reported it could not reach."""

    robot: str
    position: tuple[float, float, float]
    unreachable: tuple[tuple[float, float, float], ...] = ()


@dataclass(frozen=True)
class FoundInstance:
    """An instance of ``target`` a robot confirmed: its ``centroid`` (m) and who (``robot``)."""

    target: str
    centroid: tuple[float, float, float]
    robot: str | None = None


@dataclass
class Assignment:
    """The allocation: ``goals`` robot -> its goal or None (nothing feasible left for it);
    ``utility`` the objective U (module docstring) of these goals; ``method`` how it was
    found; ``paths_m`` robot -> its path length to its goal (absent for None)."""

    goals: dict[str, Goal | None]
    utility: float
    method: str
    paths_m: dict[str, float] = dataclasses.field(default_factory=dict)

    def as_dict(self) -> dict:
        """Plain-Python fields (goals via :meth:`Goal.as_dict`)."""
        return {"goals": {r: (None if g is None else g.as_dict()) for r, g in self.goals.items()},
                "utility": float(self.utility), "method": self.method,
                "paths_m": {r: float(v) for r, v in self.paths_m.items()}}


def goal_value(g: Goal, *, gain_ref_m3: float = 100.0, evidence_weight: float = 10.0) -> float:
    """What reaching goal ``g`` is worth (module docstring): ``gain_m3 / gain_ref_m3 +
    evidence_weight · max(score, RAY_Z_SHARE · min(max(ray_z, 0) / RAY_Z_FULL, 1))``."""
    z = RAY_Z_SHARE * min(max(float(g.ray_z), 0.0) / RAY_Z_FULL, 1.0)
    return max(float(g.gain_m3), 0.0) / gain_ref_m3 + evidence_weight * max(float(g.score), z)


def greedy_bound(n_robots: int) -> float:
    """The fraction of the optimum the greedy allocation is guaranteed: ``1 / min(N, 1 +
    KISSING_3D)``.

    Proof (charging): every pair (r, g) of an optimal assignment is either picked by the greedy
    or becomes infeasible when some greedy pick e = (r', g') is made, and was feasible just
    before, so its utility ≤ u(e) (greedy picks the best feasible pair); charge it to the first
    such e. The optimal pairs charged to e conflict with e: the one with robot r' (at most one:
    optimal robots are distinct) and those whose viewpoints lie closer than the footprint to
    g' (pairwise ≥ footprint apart, so at most KISSING_3D of them) — and at most N in all,
    the optimum having at most N pairs. Hence U_opt ≤ min(N, 1 + KISSING_3D) · U_greedy."""
    if n_robots < 1:
        raise ValueError(f"greedy_bound: n_robots must be ≥ 1, got {n_robots}")
    return 1.0 / min(n_robots, 1 + KISSING_3D)


def _finite_xyz(v, what: str) -> np.ndarray:
    a = np.asarray(v, np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{what} must be 3 finite numbers (x, y, z in metres), got {v!r}")
    return a


def _check_fleet(robots: Sequence[RobotSlot], footprint_m: float) -> None:
    if not robots:
        raise ValueError("allocate_goals: the fleet is empty; pass at least one RobotSlot")
    ids = [r.robot for r in robots]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"allocate_goals: robot ids must be unique; repeated: {', '.join(dup)}")
    for r in robots:
        if not isinstance(r.robot, str) or not r.robot:
            raise ValueError(f"allocate_goals: a robot id must be a non-empty string, got {r.robot!r}")
        _finite_xyz(r.position, f"robot {r.robot!r} position")
    if not (isinstance(footprint_m, (int, float)) and math.isfinite(footprint_m) and footprint_m >= 0):
        raise ValueError(f"allocate_goals: footprint_m must be a finite number ≥ 0 (metres), got {footprint_m!r}")


def _utilities(robots: Sequence[RobotSlot], candidates: Sequence[Goal], path_m, value, tol: float,
               eligible=None) -> tuple[np.ndarray, np.ndarray]:
    """(N, M) utility and path length per robot and candidate; -inf utility = not allowed."""
    pos = np.stack([_finite_xyz(g.position, f"candidate {i} position") for i, g in enumerate(candidates)]) \
        if candidates else np.zeros((0, 3))
    vals = np.array([float(value(g)) for g in candidates])
    util = np.full((len(robots), len(candidates)), -np.inf)
    paths = np.full((len(robots), len(candidates)), np.inf)
    for i, r in enumerate(robots):
        at = np.asarray(r.position, np.float64)
        bad = np.zeros(len(candidates), bool)
        if r.unreachable and len(candidates):
            u = np.asarray(r.unreachable, np.float64).reshape(-1, 3)
            bad = (np.linalg.norm(pos[:, None, :] - u[None], axis=2) <= tol).any(1)
        for j in range(len(candidates)):
            if bad[j] or (eligible is not None and not eligible(r.robot, candidates[j])):
                continue
            p = float(np.linalg.norm(pos[j] - at)) if path_m is None else path_m(r.robot, pos[j].copy())
            if p is None or not math.isfinite(p):
                continue
            paths[i, j] = max(float(p), 0.0)
            util[i, j] = vals[j] / (1.0 + paths[i, j])
    return util, paths


def _conflicts(candidates: Sequence[Goal], footprint_m: float) -> np.ndarray:
    """(M, M) bool: viewpoints closer than ``footprint_m`` (a goal conflicts with itself)."""
    if not candidates:
        return np.zeros((0, 0), bool)
    pos = np.stack([np.asarray(g.position, np.float64) for g in candidates])
    d = np.linalg.norm(pos[:, None, :] - pos[None], axis=2)
    return (d < footprint_m) | np.eye(len(pos), dtype=bool)


def _greedy(util: np.ndarray, conflict: np.ndarray) -> list[int]:
    """Per robot the chosen candidate index (-1: none), greedy on utility."""
    n, m = util.shape
    u = util.copy()
    out = [-1] * n
    while m and np.isfinite(u).any():
        i, j = np.unravel_index(int(np.argmax(u)), u.shape)     # first max: fleet order, then candidates
        out[int(i)] = int(j)
        u[int(i), :] = -np.inf
        u[:, conflict[int(j)]] = -np.inf
    return out


def _brute_force(util: np.ndarray, conflict: np.ndarray, max_combinations: int) -> list[int]:
    """Per robot the chosen candidate index (-1: none) of an assignment of maximal total
    utility among all honouring the constraints (depth-first over robots)."""
    n, m = util.shape
    if (m + 1) ** n > max_combinations:
        raise ValueError(f"allocate_goals: brute force over {n} robots and {m} candidates is {(m + 1) ** n} "
                         f"assignments, more than max_combinations={max_combinations}; use method='greedy'")
    best: list = [0.0, [-1] * n]
    choice = [-1] * n

    def visit(i: int, total: float, blocked: np.ndarray) -> None:
        if i == n:
            if total > best[0] + 1e-12:
                best[0], best[1] = total, list(choice)
            return
        choice[i] = -1
        visit(i + 1, total, blocked)
        for j in np.flatnonzero(np.isfinite(util[i]) & ~blocked):
            choice[i] = int(j)
            visit(i + 1, total + float(util[i, j]), blocked | conflict[j])
        choice[i] = -1

    visit(0, 0.0, np.zeros(m, bool))
    return best[1]


def allocate_goals(robots: Sequence[RobotSlot], candidates: Sequence[Goal], *, footprint_m: float,
                   path_m: Callable[[str, np.ndarray], float | None] | None = None,
                   value: Callable[[Goal], float] | None = None, method: str = "greedy",
                   eligible: Callable[[str, Goal], bool] | None = None,
                   unreachable_tol_m: float = 0.5, found: Sequence[FoundInstance] = (),
                   target_count: int | Mapping[str, int] = 1, max_combinations: int = 2_000_000) -> Assignment:
    """Give each robot of ``robots`` at most one of ``candidates`` (module docstring: objective,
    constraints, methods). ``path_m(robot, position)``: that robot's path length (m) to a
    viewpoint (None / inf: unreachable; default the straight line); ``value``: what a goal is
    worth (default :func:`goal_value`); ``eligible(robot, goal)``: whether that robot may be
    given that goal at all (default: every robot every goal); ``found`` / ``target_count``: instances already
    confirmed, applied with :func:`discount_found` first. Raises ``ValueError`` (one line) on
    an empty fleet, repeated robot ids, a non-finite position or an unknown method."""
    _check_fleet(robots, footprint_m)
    if method not in METHODS:
        raise ValueError(f"allocate_goals: method must be one of {', '.join(METHODS)}, not {method!r}")
    cands = discount_found(candidates, found, target_count=target_count) if found else list(candidates)
    util, paths = _utilities(robots, cands, path_m, value or goal_value, float(unreachable_tol_m), eligible)
    conflict = _conflicts(cands, float(footprint_m))
    pick = _greedy(util, conflict) if method == "greedy" else _brute_force(util, conflict, max_combinations)
    goals: dict[str, Goal | None] = {}
    used: dict[str, float] = {}
    total = 0.0
    for i, r in enumerate(robots):
        j = pick[i]
        goals[r.robot] = None if j < 0 else cands[j]
        if j >= 0:
            total += float(util[i, j])
            used[r.robot] = float(paths[i, j])
    return Assignment(goals, total, method, used)


def _wanted(target_count: int | Mapping[str, int], target: str) -> int:
    if isinstance(target_count, Mapping):
        return int(target_count.get(target, 1))
    return int(target_count)


def aimed_at(g: Goal, centroid: np.ndarray, *, near_m: float = 3.0, aim_deg: float = 30.0) -> bool:
    """Whether goal ``g`` leads toward the instance at ``centroid`` (m): the viewpoint lies within
    ``near_m`` (xy) of it, or the goal's heading (the yaw of its rays) points at it within
    ``aim_deg``."""
    d = np.asarray(centroid, np.float64)[:2] - np.asarray(g.position, np.float64)[:2]
    dist = float(np.hypot(d[0], d[1]))
    if dist <= near_m:
        return True
    h = np.array([math.cos(g.heading_rad), math.sin(g.heading_rad)])
    return float(d @ h) / dist >= math.cos(math.radians(aim_deg))


def discount_found(candidates: Sequence[Goal], found: Sequence[FoundInstance], *,
                   target_count: int | Mapping[str, int] = 1, near_m: float = 3.0, aim_deg: float = 30.0
                   ) -> list[Goal]:
    """``candidates`` with the evidence taken off (copies with ``score`` 0, ``ray_z`` 0, target
    None; the rest unchanged) where it would send a robot toward what is already found: every
    goal of a target of which ``target_count`` instances (an int for all targets, or per target;
    default 1) are in ``found``, and, for a target still wanting more, the goals
    :func:`aimed_at` one of its found instances. Order and length are kept (the frontiers still
    hold unknown volume worth exploring)."""
    by_target: dict[str, list[np.ndarray]] = {}
    for f in found:
        by_target.setdefault(f.target, []).append(_finite_xyz(f.centroid, f"found {f.target!r} centroid"))
    out = []
    for g in candidates:
        seen = by_target.get(g.target, []) if g.target is not None else []
        spent = bool(seen) and (len(seen) >= _wanted(target_count, g.target or "")
                                or any(aimed_at(g, c, near_m=near_m, aim_deg=aim_deg) for c in seen))
        out.append(dataclasses.replace(g, score=0.0, ray_z=0.0, target=None) if spent else g)
    return out
