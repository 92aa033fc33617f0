"""A long mission route that never comes back: a city of streets generated lazily, leg by leg.

The route is a staircase of straight streets, ``leg`` metres each (default 100 m), alternating
east (+x) and north (+y) and starting at the origin heading east; the corners are rounded with
``corner_radius`` (default 8 m), left turns (east → north) and right turns (north → east) in
turn. Points of the route at least two legs apart are at least ``leg − corner_radius`` metres
from each other (the route is monotone in x + y), so with a 20 m depth limit the map never
sees a place twice.

Both sides of every leg are lined like the town's streets (:mod:`synthetic_world.generate`:
buildings, roof chimneys, lamps, verge trees, parked cars, a fence, a bench, a rock; a road
box per leg that reaches past both corners), drawn from one random stream seeded by ``seed``
in leg order, with one footprint set shared by consecutive legs so a corner's buildings never
overlap. Legs are generated on first use and cached; :meth:`MissionCity.world_at` is the
:class:`~synthetic_world.World` of the legs around one leg (``k − 2 … k + 2``, the farthest a
camera on leg ``k`` can see a street of, plus a ground plane), so rendering cost does not grow
with the route. World frame z up, metres; poses camera-to-world, RDF camera axes.
"""
from __future__ import annotations

import numpy as np

from common.geometry import look_at

from .classes import CLASS_COLORS, CLASS_NAMES
from .generate import ROAD_HW, ROAD_TOP, _add_street_side, _Side, _Town
from .parts import Layout, Part
from .primitives import Box
from .scene import World

#: legs of the route each side of the camera's leg that :meth:`MissionCity.world_at` includes
VIEW_LEGS = 2


class MissionCity:
    """The staircase city of the module doc for ``seed``; ``leg`` and ``corner_radius`` in metres."""

    def __init__(self, seed: int = 0, leg: float = 100.0, corner_radius: float = 8.0) -> None:
        if leg < 4 * corner_radius or corner_radius <= 0:
            raise ValueError(f"need corner_radius > 0 and leg >= 4 * corner_radius, got {leg}, {corner_radius}")
        self.seed, self.leg, self.radius = int(seed), float(leg), float(corner_radius)
        self._town = _Town(np.random.default_rng(np.random.SeedSequence([self.seed, 31])), 1.0, leg / 2, leg / 2)
        self._legs: list[list[Part]] = []
        self._fp_marks: list[int] = []  # footprint count before each leg
        self._world_key: tuple[int, int] | None = None
        self._world: World | None = None

    # ------------------------------------------------------------------ geometry of the route

    def corner(self, k: int) -> np.ndarray:
        """(2,) start of leg ``k`` (the sharp corner of the street centre lines), metres."""
        return np.array([(k + 1) // 2, k // 2], dtype=np.float64) * self.leg

    @staticmethod
    def direction(k: int) -> np.ndarray:
        """(2,) unit direction of leg ``k``: east for even ``k``, north for odd."""
        return np.array([1.0, 0.0]) if k % 2 == 0 else np.array([0.0, 1.0])

    @property
    def segment_length(self) -> float:
        """Route length per leg (straight part plus rounded corner), metres."""
        return self.leg - 2 * self.radius + np.pi * self.radius / 2

    def path(self, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Route at distances ``dist`` (N,) metres from the start (``≥ 0``): ``(xy (N, 2),
        heading (N,) rad, leg (N,) int)``."""
        d = np.asarray(dist, dtype=np.float64)
        if np.any(d < 0):
            raise ValueError("route distances must be >= 0")
        r, ls = self.radius, self.segment_length
        k = np.floor(d / ls).astype(np.int64)
        t = d - k * ls
        straight = self.leg - 2 * r
        even = k % 2 == 0
        h0 = np.where(even, 0.0, np.pi / 2)
        u = np.stack([np.where(even, 1.0, 0.0), np.where(even, 0.0, 1.0)], -1)
        c = np.stack([(k + 1) // 2, k // 2], -1).astype(np.float64) * self.leg
        xy = c + (r + np.minimum(t, straight))[:, None] * u
        th = np.maximum(t - straight, 0.0) / r  # turned angle on the arc
        on_arc = t > straight
        # left turn (even legs): centre left of travel; right turn (odd legs): centre right of it
        sgn = np.where(even, 1.0, -1.0)
        head = h0 + sgn * th
        end = c + (self.leg - r) * u
        left = np.stack([-np.sin(h0), np.cos(h0)], -1)
        q = end + (sgn * r)[:, None] * left
        arc = q + (sgn * r)[:, None] * np.stack([np.sin(head), -np.cos(head)], -1)
        xy = np.where(on_arc[:, None], arc, xy)
        return xy, head, k

    def poses(self, start: int, n: int, step: float = 0.15, seed: int | None = None) -> np.ndarray:
        """(n, 4, 4) float64 camera-to-world RDF poses of frames ``start … start + n − 1``, frame
        ``i`` at ``i · step`` metres down the route: a car-mounted camera as the town's
        ``"ground"`` trajectory (eye 1.5 m above the road, ±10° yaw and ±1.5° pitch sway
        around a 2° downward tilt)."""
        if n < 0 or start < 0 or step <= 0:
            raise ValueError(f"need start >= 0, n >= 0, step > 0; got {start}, {n}, {step}")
        rng = np.random.default_rng(np.random.SeedSequence([self.seed if seed is None else int(seed), 7]))
        ph = rng.uniform(0, 2 * np.pi, size=2)
        d = (start + np.arange(n)) * float(step)
        xy, head, _ = self.path(d)
        yaw = head + np.deg2rad(10.0) * np.sin(2 * np.pi * d / 55.0 + ph[0])
        pitch = np.deg2rad(-2.0 + 1.5 * np.sin(2 * np.pi * d / 37.0 + ph[1]))
        out = np.empty((n, 4, 4))
        for i in range(n):
            eye = np.array([xy[i, 0], xy[i, 1], ROAD_TOP + 1.5])
            f = np.array([np.cos(pitch[i]) * np.cos(yaw[i]), np.cos(pitch[i]) * np.sin(yaw[i]), np.sin(pitch[i])])
            out[i] = look_at(eye, eye + f)
        return out

    def leg_of(self, pose: np.ndarray) -> int:
        """The leg whose street the camera of ``pose`` is on (nearest street centre line)."""
        x, y = float(pose[0, 3]), float(pose[1, 3])
        best, kb = np.inf, 0
        k0 = max(0, int(np.floor((x + y) / self.leg)) - 1)
        for k in range(k0, k0 + 3):
            c, u = self.corner(k), self.direction(k)
            a = np.clip(np.dot(np.array([x, y]) - c, u), 0.0, self.leg)
            dist = float(np.linalg.norm(c + a * u - np.array([x, y])))
            if dist < best:
                best, kb = dist, k
        return kb

    # ------------------------------------------------------------------ the city

    def leg_parts(self, k: int) -> list[Part]:
        """Parts of leg ``k``'s street (its road, both sides), generated in leg order on first use."""
        if k < 0:
            return []
        while len(self._legs) <= k:
            self._generate_next()
        return self._legs[k]

    def _generate_next(self) -> None:
        k = len(self._legs)
        town = self._town
        self._fp_marks.append(len(town.fp.rects))
        if k >= 2:  # keep the footprints of the two previous legs (the only ones a new leg can touch)
            drop = self._fp_marks[k - 2]
            town.fp.rects = town.fp.rects[drop:]
            self._fp_marks = [m - drop for m in self._fp_marks]
        town.parts = []
        u, c = self.direction(k), self.corner(k) + self.direction(k) * self.leg / 2
        half = self.leg / 2 + ROAD_HW
        ex, ey = (half, ROAD_HW) if k % 2 == 0 else (ROAD_HW, half)
        town.add("road", [Box((c[0], c[1], ROAD_TOP / 2), (ex, ey, ROAD_TOP / 2))])
        town.fp.take(c[0] - ex, c[1] - ey, c[0] + ex, c[1] + ey)
        yaw = float(np.arctan2(u[1], u[0]))
        normal = np.array([-u[1], u[0]])
        for side in (-1.0, 1.0):
            _add_street_side(town, _Side(c, u, side * normal, yaw, self.leg / 2 - 9.0, False))
        self._legs.append(town.parts)
        town.parts = []

    def world_at(self, k: int) -> World:
        """The :class:`World` of legs ``k − VIEW_LEGS … k + VIEW_LEGS`` and a ground square
        (z = 0, 300 m either side of leg ``k``'s centre); the last one is cached."""
        key = (k, VIEW_LEGS)
        if self._world_key != key:
            c = self.corner(k) + self.direction(k) * self.leg / 2
            parts = [Part(Box((c[0], c[1], -0.25), (300.0, 300.0, 0.25)), "ground", "ground_0")]
            for j in range(k - VIEW_LEGS, k + VIEW_LEGS + 1):
                parts += self.leg_parts(j)
            layout = Layout(half_x=self.leg / 2, half_y=self.leg / 2, corner_radius=self.radius, road_top=ROAD_TOP,
                            extra={"mission_leg": k})
            self._world = World(parts, CLASS_NAMES, CLASS_COLORS, layout=layout, seed=self.seed)
            self._world_key = key
        assert self._world is not None
        return self._world

    def render(self, pose: np.ndarray, K: np.ndarray, hw: tuple[int, int]):
        """:meth:`World.render` of ``pose`` in the world around the camera's leg."""
        return self.world_at(self.leg_of(pose)).render(pose, K, hw)
