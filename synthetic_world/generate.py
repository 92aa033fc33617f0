"""Procedural town: the layout behind :meth:`synthetic_world.World.generate`.

A rectangular loop of streets (centre lines ``x = ±half_x``, ``y = ±half_y``, 8 m wide,
extended 35 m past each corner) on a 800 m × 800 m ground square. Along each side of each
loop street: buildings (some low ones with a roof chimney), trees, street lamps, parked
cars, fences, benches and rocks, all 2–25 m from the street centre line that the
trajectories follow. Trees and rocks are scattered in the fields around the town. Far
landmarks (a water tower, a radio tower, a tall factory chimney with its factory, a few
tall buildings) stand 150–260 m beyond the loop, in view along the streets, so they stay
beyond any realistic depth limit. Placement uses rejection sampling on 2-D footprints, so
different-class solids never overlap (chimneys sit on roofs, cars on the road).
Everything is drawn from ``numpy.random.default_rng(seed)``: same seed, same world.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .parts import Layout, Part
from .primitives import Box, Cone, Cylinder, Shape, Sphere

PRESETS = ("default", "sparse")
ROAD_HW = 4.0  # road half width, m
ROAD_TOP = 0.02
GROUND_HALF = 400.0


class _Footprints:
    """Axis-aligned 2-D footprints already taken (x0, y0, x1, y1)."""

    def __init__(self) -> None:
        self.rects: list[tuple[float, float, float, float]] = []

    def free(self, x0: float, y0: float, x1: float, y1: float, margin: float = 0.5) -> bool:
        """Whether the rectangle (metres) keeps ``margin`` metres from every taken one."""
        for a0, b0, a1, b1 in self.rects:
            if x0 - margin < a1 and a0 < x1 + margin and y0 - margin < b1 and b0 < y1 + margin:
                return False
        return True

    def take(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """Mark the rectangle (metres) as taken."""
        self.rects.append((x0, y0, x1, y1))


def _jitter(rng: np.random.Generator, color: tuple[int, int, int], amount: int = 18) -> tuple[int, ...]:
    return tuple(int(np.clip(c + rng.integers(-amount, amount + 1), 0, 255)) for c in color)


def _rect_fp(center: np.ndarray, along: float, across: float, u: np.ndarray) -> tuple[float, float, float, float]:
    """World AABB footprint of a street-aligned rectangle."""
    ex = abs(u[0]) * along + abs(u[1]) * across
    ey = abs(u[1]) * along + abs(u[0]) * across
    return center[0] - ex, center[1] - ey, center[0] + ex, center[1] + ey


@dataclass
class _Side:
    """One side of a loop street: centre ``c`` (2,), unit tangent ``u``, unit normal ``n``
    pointing away from the street, ``yaw`` of ``u`` (rad) and the usable half length (m)."""

    c: np.ndarray
    u: np.ndarray
    n: np.ndarray
    yaw: float
    usable: float
    is_inner: bool

    def at(self, along: float, offset: float) -> np.ndarray:
        """The point ``along`` metres down the street, ``offset`` metres off its centre line."""
        return self.c + along * self.u + offset * self.n


class _Town:
    """The parts generated so far, their footprints and the one random stream they all draw from."""

    def __init__(self, rng: np.random.Generator, density: float, ax: float, ay: float) -> None:
        self.rng = rng
        self.density = density
        self.ax = ax
        self.ay = ay
        self.parts: list[Part] = []
        self.counts: dict[str, int] = {}
        self.fp = _Footprints()

    def new_name(self, cls: str) -> str:
        k = self.counts.get(cls, 0)
        self.counts[cls] = k + 1
        return f"{cls.replace(' ', '_')}_{k}"

    def add(self, cls: str, shapes: Sequence[Shape], color: tuple[int, ...] | None = None,
            name: str | None = None) -> str:
        name = name or self.new_name(cls)
        for s in shapes:
            self.parts.append(Part(s, cls, name, color))
        return name

    def place(self, side: _Side, along_range: tuple[float, float], offset: float, half_along: float,
              half_across: float, tries: int = 20) -> np.ndarray | None:
        """Centre of a free street-aligned rectangle at ``offset`` m from the centre line (taken), or None."""
        for _ in range(tries):
            aa = self.rng.uniform(*along_range)
            ctr = side.at(aa, offset)
            box = _rect_fp(ctr, half_along, half_across, side.u)
            if self.fp.free(*box, margin=0.4):
                self.fp.take(*box)
                return ctr
        return None

    def brown_trunk(self) -> None:
        """Recolour the trunk of the tree just added (the part before its crown) brown."""
        self.parts[-2] = Part(self.parts[-2].shape, "tree", self.parts[-2].instance, (105, 75, 45))


def generate_parts(seed: int = 0, preset: str = "default") -> tuple[list[Part], Layout]:
    """Parts of the town for ``seed`` and ``preset`` (``"default"`` or ``"sparse"``, the
    latter with about half the street furniture)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown world preset {preset!r}; valid presets: {', '.join(PRESETS)}")
    rng = np.random.default_rng(seed)
    density = 1.0 if preset == "default" else 0.5
    ax = float(40.0 + rng.uniform(-4, 4))
    ay = float(25.0 + rng.uniform(-3, 3))
    town = _Town(rng, density, ax, ay)
    _add_ground_and_roads(town)
    for side in _street_sides(ax, ay):
        _add_street_side(town, side)
    _add_fields(town)
    _add_landmarks(town)
    layout = Layout(half_x=ax, half_y=ay, corner_radius=8.0, road_top=ROAD_TOP,
                     extra={"far_instances": ["water_tower_0", "radio_tower_0", "chimney_factory", "building_factory",
                                              "building_far_0", "building_far_1", "building_far_2"]})
    return town.parts, layout


def _add_ground_and_roads(town: _Town) -> None:
    ax, ay = town.ax, town.ay
    town.add("ground", [Box((0.0, 0.0, -0.25), (GROUND_HALF, GROUND_HALF, 0.25))], name="ground_0")
    town.counts["ground"] = 1
    ext = 35.0
    for sy in (-1, 1):
        town.add("road", [Box((0.0, sy * ay, ROAD_TOP / 2), (ax + ext, ROAD_HW, ROAD_TOP / 2))])
        town.fp.take(-ax - ext, sy * ay - ROAD_HW, ax + ext, sy * ay + ROAD_HW)
    for sx in (-1, 1):
        town.add("road", [Box((sx * ax, 0.0, ROAD_TOP / 2), (ROAD_HW, ay + ext, ROAD_TOP / 2))])
        town.fp.take(sx * ax - ROAD_HW, -ay - ext, sx * ax + ROAD_HW, ay + ext)


def _street_sides(ax: float, ay: float) -> list[_Side]:
    """Both sides of the four loop streets, in generation order (outer side first)."""
    # The four loop streets: (centre, unit tangent, half length, inner normal).
    streets = [
        (np.array([0.0, -ay]), np.array([1.0, 0.0]), ax, np.array([0.0, 1.0])),
        (np.array([ax, 0.0]), np.array([0.0, 1.0]), ay, np.array([-1.0, 0.0])),
        (np.array([0.0, ay]), np.array([-1.0, 0.0]), ax, np.array([0.0, -1.0])),
        (np.array([-ax, 0.0]), np.array([0.0, -1.0]), ay, np.array([1.0, 0.0])),
    ]
    sides = []
    for c, u, half_len, inner in streets:
        yaw = float(np.arctan2(u[1], u[0]))
        for side in (-1.0, 1.0):
            sides.append(_Side(c, u, inner * side, yaw, half_len - 9.0, side > 0))
    return sides


def _add_street_side(town: _Town, side: _Side) -> None:
    """Buildings, lamps, trees, parked cars, a fence, a bench and a rock along one street side."""
    _add_buildings(town, side)
    _add_lamps(town, side)
    _add_verge_trees(town, side)
    _add_parked_cars(town, side)
    _add_fence(town, side)
    _add_bench_and_rock(town, side)


def _add_buildings(town: _Town, side: _Side) -> None:
    rng, usable, u = town.rng, side.usable, side.u
    a = -usable + rng.uniform(0, 4)
    while a < usable - 5:
        w = rng.uniform(7, 15)
        depth = rng.uniform(7, 11) if side.is_inner else rng.uniform(8, 14)
        setback = rng.uniform(9.0, 12.5)
        a_c = a + w / 2
        if a_c + w / 2 > usable + 3:
            break
        if side.is_inner:
            depth = min(depth, (town.ay if abs(u[0]) > 0 else town.ax) - setback - 4.0)
        low = rng.random() < 0.5
        hgt = rng.uniform(5, 8) if low else rng.uniform(10, 24)
        ctr = side.at(a_c, setback + depth / 2)
        box = _rect_fp(ctr, w / 2, depth / 2, u)
        if depth > 4 and town.fp.free(*box):
            town.fp.take(*box)
            col = _jitter(rng, (196, 170, 140), 30)
            town.add("building", [Box((ctr[0], ctr[1], hgt / 2), (w / 2, depth / 2, hgt / 2), side.yaw)], col)
            if low and rng.random() < 0.75:
                _add_roof_chimney(town, side, a_c, w, setback, hgt)
        a += w + rng.uniform(3, 9)


def _add_roof_chimney(town: _Town, side: _Side, a_c: float, w: float, setback: float, hgt: float) -> None:
    """A chimney on the roof (height ``hgt`` m) of the building centred ``a_c`` m down the street."""
    rng = town.rng
    hc = rng.uniform(2.2, 3.5)
    pc = side.c + (a_c + rng.uniform(-w / 4, w / 4)) * side.u + (setback + rng.uniform(1.0, 2.0)) * side.n
    sh: Shape
    if rng.random() < 0.5:
        sh = Box((pc[0], pc[1], hgt + hc / 2), (0.4, 0.4, hc / 2), side.yaw)
    else:
        sh = Cylinder(pc[0], pc[1], hgt, hgt + hc, 0.35)
    town.add("chimney", [sh])


def _add_lamps(town: _Town, side: _Side) -> None:
    """Street lamps every ~20 m on the kerb."""
    usable = side.usable
    for a_l in np.arange(-usable + town.rng.uniform(0, 8), usable, 20.0 / town.density):
        ctr = side.at(a_l, 5.0)
        if town.fp.free(*_rect_fp(ctr, 0.3, 0.3, side.u), margin=0.2):
            town.fp.take(*_rect_fp(ctr, 0.3, 0.3, side.u))
            town.add("street lamp", [Cylinder(ctr[0], ctr[1], 0.0, 6.0, 0.09),
                                     Sphere((ctr[0] - 0.0, ctr[1], 6.2), 0.3)])


def _add_verge_trees(town: _Town, side: _Side) -> None:
    rng = town.rng
    rng_along = (-side.usable, side.usable)
    for _ in range(int(round(rng.integers(2, 5) * town.density)) or 1):
        r = rng.uniform(1.4, 2.2)
        ctr = town.place(side, rng_along, rng.uniform(6.4, 8.6 - r + 1.4), r, r)
        if ctr is not None:
            trunk = rng.uniform(2.4, 3.6)
            shapes: list[Shape] = [Cylinder(ctr[0], ctr[1], 0.0, trunk, rng.uniform(0.15, 0.25))]
            if rng.random() < 0.6:
                shapes.append(Sphere((ctr[0], ctr[1], trunk + r * 0.8), r))
            else:
                shapes.append(Cone(ctr[0], ctr[1], trunk - 0.5, trunk + 3.2 * r, r))
            town.add("tree", shapes, _jitter(rng, (46, 112, 46), 15))
            town.brown_trunk()


def _add_parked_cars(town: _Town, side: _Side) -> None:
    """Parked cars on the road edge (clear of the centre line by 2 m)."""
    rng = town.rng
    rng_along = (-side.usable, side.usable)
    for _ in range(int(rng.integers(1, 3)) if town.density == 1.0 else int(rng.integers(0, 2))):
        aa = rng.uniform(*rng_along)
        ctr = side.at(aa, 2.95)
        yaw_c = side.yaw + rng.uniform(-0.05, 0.05)
        cars = [(p.shape.center[0], p.shape.center[1]) for p in town.parts
                if p.class_name == "car" and isinstance(p.shape, (Box, Sphere))]   # cars are boxes
        if all(not (abs(ctr[0] - q[0]) < 5.0 and abs(ctr[1] - q[1]) < 2.5) for q in cars):
            col = tuple(int(v) for v in rng.choice([(190, 40, 40), (40, 70, 170), (230, 230, 230),
                                                    (30, 30, 35), (200, 170, 40)]))
            fwd = np.array([np.cos(yaw_c), np.sin(yaw_c)])
            cab = ctr - 0.3 * fwd
            town.add("car", [Box((ctr[0], ctr[1], ROAD_TOP + 0.45), (2.1, 0.88, 0.45), yaw_c),
                             Box((cab[0], cab[1], ROAD_TOP + 0.9 + 0.32), (1.1, 0.8, 0.32), yaw_c)], col)


def _add_fence(town: _Town, side: _Side) -> None:
    """A fence along a lot boundary."""
    rng = town.rng
    if rng.random() < 0.8 * town.density + 0.2:
        ln = rng.uniform(4, 9)
        ctr = town.place(side, (-side.usable, side.usable), rng.uniform(8.0, 8.6), ln, 0.05)
        if ctr is not None:
            hf = rng.uniform(1.1, 1.8)
            town.add("fence", [Box((ctr[0], ctr[1], hf / 2), (ln, 0.05, hf / 2), side.yaw)])


def _add_bench_and_rock(town: _Town, side: _Side) -> None:
    """A bench and a rock on the verge."""
    rng = town.rng
    rng_along = (-side.usable, side.usable)
    if rng.random() < 0.7:
        ctr = town.place(side, rng_along, 5.9, 0.9, 0.3)
        if ctr is not None:
            back = ctr + 0.25 * side.n
            town.add("bench", [Box((ctr[0], ctr[1], 0.225), (0.9, 0.25, 0.225), side.yaw),
                               Box((back[0], back[1], 0.55), (0.9, 0.05, 0.3), side.yaw)])
    if rng.random() < 0.7:
        r = rng.uniform(0.35, 0.9)
        ctr = town.place(side, rng_along, rng.uniform(6.0, 8.0), r, r)
        if ctr is not None:
            town.add("rock", [Sphere((ctr[0], ctr[1], 0.35 * r), r)], _jitter(rng, (125, 120, 115), 12))


def _add_fields(town: _Town) -> None:
    """Fields around the town: trees and rocks."""
    rng = town.rng
    n_field = int(40 * town.density)
    placed = 0
    for _ in range(n_field * 5):
        if placed >= n_field:
            break
        ang = rng.uniform(0, 2 * np.pi)
        rad = rng.uniform(70, 150)
        x, y = rad * np.cos(ang), rad * np.sin(ang)
        r = rng.uniform(1.5, 3.0)
        if not town.fp.free(x - r, y - r, x + r, y + r, margin=1.0):
            continue
        town.fp.take(x - r, y - r, x + r, y + r)
        placed += 1
        if rng.random() < 0.8:
            trunk = rng.uniform(2.5, 4.0)
            town.add("tree", [Cylinder(x, y, 0.0, trunk, 0.25), Sphere((x, y, trunk + 0.8 * r), r)],
                     _jitter(rng, (46, 112, 46), 15))
            town.brown_trunk()
        else:
            town.add("rock", [Sphere((x, y, 0.3 * r), r * 0.6)], _jitter(rng, (125, 120, 115), 12))


def _add_landmarks(town: _Town) -> None:
    """Far landmarks, in view along the streets."""
    rng, ax, ay, add = town.rng, town.ax, town.ay, town.add
    # Water tower: west, near the south street's line of sight.
    wx, wy = -(ax + rng.uniform(160, 200)), -ay + rng.uniform(-25, 15)
    legs = [Cylinder(wx + dx, wy + dy, 0.0, 24.0, 0.4) for dx in (-4.5, 4.5) for dy in (-4.5, 4.5)]
    add("water tower", legs + [Cylinder(wx, wy, 24.0, 32.0, 7.0), Cone(wx, wy, 32.0, 35.0, 7.3, 0.0)])
    # Radio tower: east, near the north street's line of sight.
    # A lattice mast is modelled as its solid envelope (wide base), so it stays visible at
    # low resolution and 1/16-resolution features.
    rx, ry = ax + rng.uniform(125, 150), ay + rng.uniform(-15, 30)
    add("radio tower", [Cone(rx, ry, 0.0, 55.0, 5.0, 0.6), Cylinder(rx, ry, 55.0, 62.0, 0.3),
                        Sphere((rx, ry, 62.4), 0.6)])
    # Factory chimney with its factory: north.
    fx, fy = rng.uniform(-30, 30), ay + rng.uniform(170, 210)
    add("chimney", [Cone(fx, fy, 0.0, 48.0, 3.2, 2.0)], (170, 70, 55), name="chimney_factory")
    add("building", [Box((fx + 28.0, fy + 5.0, 7.0), (20.0, 14.0, 7.0))], (170, 165, 160), name="building_factory")
    # Far tall buildings: south and beyond the west/east stubs.
    for k, (bx, by) in enumerate([(rng.uniform(-60, 60), -(ay + rng.uniform(160, 220))),
                                  (-(ax + rng.uniform(150, 200)), ay + rng.uniform(40, 90)),
                                  (ax + rng.uniform(150, 200), -(ay + rng.uniform(40, 90)))]):
        hx, hy, hz = rng.uniform(10, 20), rng.uniform(10, 20), rng.uniform(25, 55)
        add("building", [Box((bx, by, hz / 2), (hx, hy, hz / 2), rng.uniform(0, np.pi / 2))],
            _jitter(rng, (150, 160, 175), 20), name=f"building_far_{k}")
