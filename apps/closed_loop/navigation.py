"""Where the robot can go this step: the traversable cells of the map's costmap and the
shortest paths to them from the robot (:mod:`apps.closed_loop.planner`). Metres, world frame."""
from __future__ import annotations

import numpy as np

from apps.closed_loop.planner import distance_field, path_to, route, traversable


class NavField:
    """Shortest paths from the robot at ``at`` (m) through the traversable cells of a costmap
    (``states`` [x, y], ``origin`` (2,) m, ``cell`` m) for a body of ``radius_m``."""

    def __init__(self, states: np.ndarray, origin: np.ndarray, cell: float, at: np.ndarray, radius_m: float):
        self.origin, self.cell = np.asarray(origin, np.float64), float(cell)
        self.ok = traversable(states, cell, radius_m)
        c = np.floor((np.asarray(at[:2], np.float64) - self.origin) / cell).astype(int)
        self.start = (int(np.clip(c[0], 0, states.shape[0] - 1)), int(np.clip(c[1], 0, states.shape[1] - 1)))
        dist, self.pred = distance_field(self.ok, self.start)
        self.dist_m = dist * self.cell
        cells = np.argwhere(np.isfinite(self.dist_m))
        self._cells = cells
        self._xy = self.origin + (cells + 0.5) * self.cell

    @classmethod
    def free_cells_only(cls, states: np.ndarray, origin: np.ndarray, cell: float, at: np.ndarray) -> "NavField":
        """Paths through FREE cells without clearance: how a robot leaves a spot where the
        clearance rule boxes it in (every move is still checked against the true world)."""
        return cls(states, origin, cell, at, -float(cell))

    def boxed_in(self) -> bool:
        """Whether the robot can reach no cell but its own (its clearance is violated where it
        stands, e.g. by an obstacle it has only just seen)."""
        return len(self._cells) <= 1

    def nearest_reachable(self, xy: np.ndarray) -> tuple[np.ndarray, float, float]:
        """(cell (2,), path length m, xy distance m from the cell centre to ``xy``) of the
        reachable cell closest to ``xy`` (ties: the shorter path)."""
        d = np.linalg.norm(self._xy - np.asarray(xy[:2], np.float64), axis=1)
        pl = self.dist_m[self._cells[:, 0], self._cells[:, 1]]
        i = int(np.lexsort((pl, np.round(d, 3)))[0])
        return self._cells[i], float(pl[i]), float(d[i])

    def route_toward(self, cell: np.ndarray, step_m: float, at: np.ndarray) -> np.ndarray:
        """(K, 2) xy points passed moving at most ``step_m`` from ``at`` along the path to
        ``cell`` (:func:`~apps.closed_loop.planner.route`: the cell centres passed, then the
        point reached; the first leg goes from ``at`` to the centre of the first cell after the
        start's). A robot drives them leg by leg: the legs join traversable cells."""
        path = path_to(self.pred, tuple(int(v) for v in cell))
        pts = [np.asarray(at[:2], np.float64)] + [self.origin + (np.asarray(c) + 0.5) * self.cell for c in path[1:]]
        return route(np.asarray(pts), step_m)

