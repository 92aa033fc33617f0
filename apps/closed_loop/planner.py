"""Shortest paths through known free space of an occupancy state grid (2D or 3D).

States follow :mod:`planning.occupancy_queries`: FREE = 0, OCCUPIED = 1, UNKNOWN = -1,
arrays indexed ``[x, y(, z)]``; cell ``c`` has its centre at ``origin + (c + 0.5)·cell`` (metres,
world frame z up). The path may only pass through FREE cells; the goal cell alone may be
UNKNOWN (a frontier being explored), never OCCUPIED. Moves go to the 8 (2D) or 26 (3D)
neighbours with Euclidean step costs, and a diagonal move is allowed only when every cell it
cuts across is free, so the polyline between cell centres stays in free cells.
"""
from __future__ import annotations

import heapq
import itertools
import math
from typing import Sequence, SupportsInt

import numpy as np

FREE, OCCUPIED, UNKNOWN = 0, 1, -1


def _offsets(ndim: int) -> list[tuple[int, ...]]:
    return [d for d in itertools.product((-1, 0, 1), repeat=ndim) if any(d)]


def _corner_cells(cell: tuple[int, ...], d: tuple[int, ...]) -> list[tuple[int, ...]]:
    """Cells a diagonal move from ``cell`` by ``d`` cuts across (all partial sub-moves)."""
    nz = [i for i, v in enumerate(d) if v]
    out = []
    for r in range(1, len(nz)):
        for sub in itertools.combinations(nz, r):
            out.append(tuple(c + (d[i] if i in sub else 0) for i, c in enumerate(cell)))
    return out


def astar(states: np.ndarray, start: tuple[int, ...], goal: tuple[int, ...]) -> list[tuple[int, ...]] | None:
    """A* cell path ``start .. goal`` (inclusive) through FREE cells, or None if none exists.

    ``start`` must be FREE; ``goal`` FREE or UNKNOWN. Cost: Euclidean length in cells."""
    states = np.asarray(states)
    start, goal = tuple(int(v) for v in start), tuple(int(v) for v in goal)
    shape = states.shape

    def inside(c: tuple[int, ...]) -> bool:
        return all(0 <= v < n for v, n in zip(c, shape, strict=True))

    if not (inside(start) and inside(goal)) or states[start] != FREE or states[goal] == OCCUPIED:
        return None
    offs = [(d, math.sqrt(sum(v * v for v in d))) for d in _offsets(states.ndim)]
    g_cost = {start: 0.0}
    parent: dict[tuple[int, ...], tuple[int, ...]] = {}
    goal_arr = np.asarray(goal, np.float64)
    heap = [(0.0, 0.0, start)]
    while heap:
        _, g, cur = heapq.heappop(heap)
        if cur == goal:
            path = [cur]
            while cur in parent:
                cur = parent[cur]
                path.append(cur)
            return path[::-1]
        if g > g_cost.get(cur, math.inf):
            continue
        for d, w in offs:
            nxt = tuple(c + v for c, v in zip(cur, d, strict=True))
            if not inside(nxt):
                continue
            s = states[nxt]
            if not (s == FREE or (nxt == goal and s == UNKNOWN)):
                continue
            if w > 1.0 and any(not inside(c) or states[c] != FREE for c in _corner_cells(cur, d)):
                continue
            ng = g + w
            if ng < g_cost.get(nxt, math.inf):
                g_cost[nxt] = ng
                parent[nxt] = cur
                h = float(np.linalg.norm(goal_arr - np.asarray(nxt, np.float64)))
                heapq.heappush(heap, (ng + h, ng, nxt))
    return None


def path_length(path: list[tuple[int, ...]], cell: float) -> float:
    """Length in metres of a cell path with cells of size ``cell`` (m)."""
    p = np.asarray(path, np.float64)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() * cell) if len(p) > 1 else 0.0


def follow(points: np.ndarray, done_m: float, step_m: float) -> tuple[np.ndarray, float]:
    """Point after driving ``step_m`` more along polyline ``points`` (N, D) having driven
    ``done_m`` already, and the new driven length (clipped at the polyline's end)."""
    points = np.asarray(points, np.float64)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    total = float(seg.sum())
    if len(seg) == 0 or total == 0.0:
        return points[-1].copy(), 0.0
    target = min(total, done_m + step_m)
    cum = np.r_[0.0, np.cumsum(seg)]
    i = min(int(np.searchsorted(cum, target, side="right")) - 1, len(seg) - 1)
    t = (target - cum[i]) / seg[i] if seg[i] > 0 else 0.0
    return points[i] + (points[i + 1] - points[i]) * t, target


def route(points: np.ndarray, step_m: float) -> np.ndarray:
    """The points passed driving at most ``step_m`` along polyline ``points`` (N, D) from its
    first point: the vertices passed, then the end (:func:`follow`'s point); the first point
    left out. Driving it leg by leg keeps to the polyline (a straight line to the end would
    cut its corners)."""
    points = np.asarray(points, np.float64)
    end, driven = follow(points, 0.0, step_m)
    cum = np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))
    return np.concatenate([points[1:][cum < driven], end[None]])


def advance(path: list[tuple[int, ...]], origin: np.ndarray, cell: float, step_m: float) -> np.ndarray:
    """Point (metres, world) reached after moving at most ``step_m`` along the path's cell centres."""
    pts = (np.asarray(path, np.float64) + 0.5) * cell + np.asarray(origin, np.float64)
    return follow(pts, 0.0, step_m)[0]


# ----------------------------------------------------------------- grid planning with scipy
def traversable(states: np.ndarray, cell: float, radius_m: float) -> np.ndarray:
    """(nx, ny) bool: cells where the robot may stand — FREE, and no OCCUPIED or UNKNOWN cell
    whose centre lies within ``radius_m + cell`` (m) of this cell's centre (unknown space may
    hide an obstacle, so it keeps the same clearance as occupied space). ``radius_m`` ≤
    −``cell``: no clearance (every FREE cell)."""
    from scipy.ndimage import binary_dilation

    states = np.asarray(states)
    r = (float(radius_m) + float(cell)) / float(cell)
    k = int(math.floor(r))
    off = np.arange(-k, k + 1)
    disk = (off[:, None] ** 2 + off[None, :] ** 2) <= r * r
    blocked = binary_dilation(states != FREE, structure=disk) if k > 0 else states != FREE
    return (states == FREE) & ~blocked


def _grid_graph(ok: np.ndarray):
    """Sparse graph over the cells of ``ok`` (2D bool): 8-neighbour moves between ok cells with
    Euclidean costs (in cells); a diagonal move only when both cells it cuts across are ok."""
    from scipy.sparse import coo_matrix

    nx, ny = ok.shape
    pad = np.pad(np.asarray(ok, bool), 1)
    idx = np.arange(nx * ny).reshape(nx, ny)

    def shifted(di: int, dj: int) -> np.ndarray:
        return pad[1 + di:1 + di + nx, 1 + dj:1 + dj + ny]

    rows, cols, w = [], [], []
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        m = ok & shifted(di, dj)
        if di and dj:     # both side cells of the diagonal
            m &= shifted(di, 0) & shifted(0, dj)
        a = idx[m]
        b = a + di * ny + dj
        rows += [a, b]
        cols += [b, a]
        w.append(np.full(2 * len(a), math.hypot(di, dj)))
    return coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(nx * ny, nx * ny)).tocsr()


def distance_field(ok: np.ndarray, start: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Shortest path lengths (in cells; inf = unreachable) from ``start`` to every cell through
    ``ok`` cells (scipy's Dijkstra), and the predecessor of each cell (-9999 = none). The start
    cell counts as ok (the robot stands there)."""
    from scipy.sparse.csgraph import dijkstra

    ok = np.asarray(ok, bool).copy()
    ok[tuple(start)] = True
    g = _grid_graph(ok)
    i0 = int(np.ravel_multi_index(tuple(int(v) for v in start), ok.shape))
    d, pred = dijkstra(g, directed=True, indices=i0, return_predecessors=True)
    return d.reshape(ok.shape), pred.reshape(ok.shape)


def path_to(pred: np.ndarray, goal: Sequence[SupportsInt]) -> list[tuple[int, int]]:
    """Cell path start .. goal from a :func:`distance_field` predecessor array."""
    shape = pred.shape
    flat = pred.ravel()
    cur = int(np.ravel_multi_index(tuple(int(v) for v in goal), shape))
    out = [cur]
    while flat[cur] >= 0:
        cur = int(flat[cur])
        out.append(cur)
    return [tuple(int(v) for v in np.unravel_index(c, shape)) for c in out[::-1]]  # type: ignore[misc]
