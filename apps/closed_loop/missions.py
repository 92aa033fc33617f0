"""Search missions in the synthetic world and their ground truth (docs/synthetic_world.md).

A mission: a target class, the true instances that count, how many must be found (``k``), a
start (camera centre, m) on free ground, and the distances that define success:

* ``reach_m``: the robot has reached an instance when its camera centre is within this
  horizontal (xy) distance of the instance's box (a ground robot cannot climb to a chimney);
* ``declare_m``: a declared instance is correct when its centroid lies within this 3D
  distance of a true instance's box (else it is a false find).

Kinds: ``object`` (nearest in-range object of the class: car, bench, street lamp...; in the
pybullet world teddy bear, shelf, r2d2), ``landmark`` (a far landmark: water tower, radio
tower; in the pybullet world the statues — beyond any depth limit at the start)
and ``all`` (find ``k`` instances of a class). The shortest path (SPL's reference) is computed
on the TRUE world (:func:`apps.closed_loop.robot.true_free_grid`) with scipy's Dijkstra; for
``all`` it is the greedy nearest-first tour over true shortest paths (what ``oracle`` drives;
not an optimal tour). World frame z up, metres.
"""
from __future__ import annotations

import math
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from apps.closed_loop.planner import distance_field, path_to
from apps.closed_loop.robot import Platform, true_free_grid
from synthetic_world import World

#: mission kinds and their default target classes (synthetic world)
OBJECT_TARGETS = ["car", "bench", "street lamp"]
LANDMARK_TARGETS = ["water tower", "radio tower"]
#: world family -> mission kind -> target classes (the pybullet world's: docs/pybullet_world.md)
TARGETS = {"synthetic": {"object": OBJECT_TARGETS, "landmark": LANDMARK_TARGETS, "all": ["car"]},
           "pybullet": {"object": ["teddy bear", "shelf", "r2d2"], "landmark": ["teddy bear statue", "robot statue"],
                        "all": ["teddy bear"]}}
#: success distances (m) per kind: (reach_m, declare_m)
DISTANCES = {"object": (3.0, 2.0), "landmark": (10.0, 5.0), "all": (3.0, 2.0)}


@dataclass
class Mission:
    """One episode's task (module docstring)."""

    kind: str
    target: str
    instances: list  # synthetic_world Instance objects that count
    k: int
    start: np.ndarray
    reach_m: float
    declare_m: float
    budget_steps: int
    shortest_m: float = 0.0
    oracle_path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def describe(self) -> dict:
        return {"kind": self.kind, "target": self.target, "k": self.k, "start": [float(v) for v in self.start],
                "reach_m": self.reach_m, "declare_m": self.declare_m, "budget_steps": self.budget_steps,
                "shortest_m": self.shortest_m, "instances": [int(i.id) for i in self.instances]}


def xy_box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Horizontal distance (m) from point ``p`` to the xy extent of box ``[lo, hi]``."""
    d = np.maximum(np.maximum(lo[:2] - p[:2], 0.0), p[:2] - hi[:2])
    return float(np.hypot(*d))


def box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """3D distance (m) from ``p`` to box ``[lo, hi]`` (0 inside)."""
    return float(np.linalg.norm(np.maximum(np.maximum(lo - p, 0.0), p - hi)))


@dataclass
class TruthGrid:
    """The true world's free cells for a platform over a window (cell ``cell`` m)."""

    ok: np.ndarray
    origin: np.ndarray
    cell: float

    def cell_of(self, xy: np.ndarray) -> tuple[int, int]:
        c = np.floor((np.asarray(xy[:2], np.float64) - self.origin) / self.cell).astype(int)
        return int(c[0]), int(c[1])

    def centre(self, c) -> np.ndarray:
        return self.origin + (np.asarray(c, np.float64) + 0.5) * self.cell

    def inside(self, c) -> bool:
        return 0 <= c[0] < self.ok.shape[0] and 0 <= c[1] < self.ok.shape[1]


#: per world (weakly held): the last few :func:`truth_grid` results, by platform, box and cell
_TRUTH_GRIDS: "weakref.WeakKeyDictionary[World, OrderedDict]" = weakref.WeakKeyDictionary()
TRUTH_GRIDS_PER_WORLD = 4


def truth_grid(world: World, platform: Platform, lo: np.ndarray, hi: np.ndarray, cell: float = 0.5) -> TruthGrid:
    """The platform's true free cells over the xy box ``[lo, hi]`` (m) at ``cell`` (m)
    (:func:`~apps.closed_loop.robot.true_free_grid`), kept for the last few boxes of a world
    (worlds are not changed after they are built; each seed's missions ask for the same boxes)."""
    key = (platform, tuple(float(v) for v in np.asarray(lo).ravel()), tuple(float(v) for v in np.asarray(hi).ravel()),
           float(cell))
    try:
        kept = _TRUTH_GRIDS.setdefault(world, OrderedDict())
    except TypeError:                         # a world that cannot be weakly referenced: no cache
        kept = OrderedDict()
    tg = kept.get(key)
    if tg is None:
        states, origin = true_free_grid(world, platform, lo, hi, cell)
        tg = kept[key] = TruthGrid(states == 0, origin, cell)
        tg.ok.setflags(write=False)               # shared by the missions that ask for this box
        tg.origin.setflags(write=False)
        while len(kept) > TRUTH_GRIDS_PER_WORLD:
            kept.popitem(last=False)
    return tg


def _reach_cells(tg: TruthGrid, inst, reach_m: float) -> np.ndarray:
    """Mask of grid cells whose centre is within ``reach_m`` (xy) of ``inst``'s box."""
    nx, ny = tg.ok.shape
    xs = tg.origin[0] + (np.arange(nx) + 0.5) * tg.cell
    ys = tg.origin[1] + (np.arange(ny) + 0.5) * tg.cell
    dx = np.maximum(np.maximum(inst.aabb_min[0] - xs, 0.0), xs - inst.aabb_max[0])
    dy = np.maximum(np.maximum(inst.aabb_min[1] - ys, 0.0), ys - inst.aabb_max[1])
    return (dx[:, None] ** 2 + dy[None, :] ** 2) <= (reach_m - tg.cell) ** 2


def oracle_tour(tg: TruthGrid, start: np.ndarray, instances: list, k: int, reach_m: float
                ) -> tuple[float, np.ndarray, list]:
    """(length m, (N, 2) path points, visited instances): from ``start`` to the nearest
    reachable instance, then the next nearest, ``k`` times (true free space, Dijkstra)."""
    pos = np.asarray(start[:2], np.float64)
    seen: list
    pts, total, left, seen = [pos.copy()], 0.0, list(instances), []
    for _ in range(k):
        s = tg.cell_of(pos)
        if not tg.inside(s):
            return math.inf, np.asarray(pts), seen
        d, pred = distance_field(tg.ok, s)
        best = None
        for inst in left:
            m = _reach_cells(tg, inst, reach_m) & np.isfinite(d)
            if m.any():
                c = np.unravel_index(np.argmin(np.where(m, d, np.inf)), d.shape)
                if best is None or d[c] < best[0]:
                    best = (float(d[c]), c, inst)
        if best is None:
            return math.inf, np.asarray(pts), seen
        cells = path_to(pred, best[1])
        seg = np.array([tg.centre(c) for c in cells[1:]]).reshape(-1, 2)
        # the robot starts off the cell centre: its first leg goes to the first cell after its own
        path = np.vstack([pos[None], seg]) if len(seg) else pos[None]
        total += float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
        pts.extend(path[1:])
        pos = path[-1]
        left.remove(best[2])
        seen.append(best[2])
    return total, np.asarray(pts), seen


def _free_starts(tg: TruthGrid, rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """``n`` random start points (cell centres) among the truth grid's free cells."""
    free = np.argwhere(tg.ok)
    pick = rng.choice(len(free), size=min(n, len(free)), replace=False)
    return [tg.centre(free[i]) for i in pick]


def make_mission(world: World, platform: Platform, kind: str, target: str, rng: np.random.Generator,
                 budget_steps: int, k: int = 1, town_half_m: float = 45.0, min_start_m: float = 15.0,
                 cell: float = 0.5, tries: int = 40) -> Mission:
    """A random mission of ``kind`` for ``target`` whose oracle tour exists (start in the town,
    at least ``min_start_m`` from every counted instance)."""
    reach, declare = DISTANCES[kind]
    insts = world.instances_of(world.class_id(target))
    if not insts:
        raise ValueError(f"the world has no {target!r}")
    z = platform.cruise_z
    for _ in range(tries):
        town = truth_grid(world, platform, np.array([-town_half_m] * 2), np.array([town_half_m] * 2), 2.0)
        start_xy = _free_starts(town, rng, 1)[0] + rng.uniform(-0.5, 0.5, 2)
        start = np.r_[start_xy, z]
        if min(xy_box_distance(start, i.aabb_min, i.aabb_max) for i in insts) < min_start_m:
            continue
        lo = np.minimum(start_xy, np.min([i.aabb_min[:2] for i in insts], 0)) - 15.0
        hi = np.maximum(start_xy, np.max([i.aabb_max[:2] for i in insts], 0)) + 15.0
        if kind != "landmark":   # objects: the town is enough (and the grid stays small)
            lo, hi = np.maximum(lo, -town_half_m - 15.0), np.minimum(hi, town_half_m + 15.0)
        tg = truth_grid(world, platform, lo, hi, cell)
        if not tg.inside(tg.cell_of(start)) or not tg.ok[tg.cell_of(start)]:
            continue
        length, pts, _ = oracle_tour(tg, start, insts, k, reach)
        if math.isfinite(length):
            path = np.c_[pts, np.full(len(pts), z)]
            return Mission(kind, target, insts, k, start, reach, declare, budget_steps, length, path)
    raise ValueError(f"no start found from which a {target!r} mission is feasible")
