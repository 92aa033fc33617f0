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

import numpy as np

from .parts import Layout, Part
from .primitives import Box, Cone, Cylinder, Sphere

PRESETS = ("default", "sparse")
ROAD_HW = 4.0  # road half width, m
ROAD_TOP = 0.02
GROUND_HALF = 400.0


class _Footprints:
    """Axis-aligned 2-D footprints already taken (x0, y0, x1, y1)."""

    def __init__(self):
        self.rects: list[tuple[float, float, float, float]] = []

    def free(self, x0, y0, x1, y1, margin=0.5) -> bool:
        for a0, b0, a1, b1 in self.rects:
            if x0 - margin < a1 and a0 < x1 + margin and y0 - margin < b1 and b0 < y1 + margin:
                return False
        return True

    def take(self, x0, y0, x1, y1) -> None:
        self.rects.append((x0, y0, x1, y1))


def _jitter(rng, color, amount=18):
    return tuple(int(np.clip(c + rng.integers(-amount, amount + 1), 0, 255)) for c in color)


def generate_parts(seed: int = 0, preset: str = "default") -> tuple[list[Part], Layout]:
    """Parts of the town for ``seed`` and ``preset`` (``"default"`` or ``"sparse"``, the
    latter with about half the street furniture)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown world preset {preset!r}; valid presets: {', '.join(PRESETS)}")
    rng = np.random.default_rng(seed)
    density = 1.0 if preset == "default" else 0.5
    ax = float(40.0 + rng.uniform(-4, 4))
    ay = float(25.0 + rng.uniform(-3, 3))
    parts: list[Part] = []
    counts: dict[str, int] = {}
    fp = _Footprints()

    def new_name(cls: str) -> str:
        k = counts.get(cls, 0)
        counts[cls] = k + 1
        return f"{cls.replace(' ', '_')}_{k}"

    def add(cls: str, shapes, color=None, name=None):
        name = name or new_name(cls)
        for s in shapes:
            parts.append(Part(s, cls, name, color))
        return name

    # Ground and roads.
    add("ground", [Box((0.0, 0.0, -0.25), (GROUND_HALF, GROUND_HALF, 0.25))], name="ground_0")
    counts["ground"] = 1
    ext = 35.0
    for sy in (-1, 1):
        add("road", [Box((0.0, sy * ay, ROAD_TOP / 2), (ax + ext, ROAD_HW, ROAD_TOP / 2))])
        fp.take(-ax - ext, sy * ay - ROAD_HW, ax + ext, sy * ay + ROAD_HW)
    for sx in (-1, 1):
        add("road", [Box((sx * ax, 0.0, ROAD_TOP / 2), (ROAD_HW, ay + ext, ROAD_TOP / 2))])
        fp.take(sx * ax - ROAD_HW, -ay - ext, sx * ax + ROAD_HW, ay + ext)

    # The four loop streets: (centre, unit tangent, half length, inner normal).
    streets = [
        (np.array([0.0, -ay]), np.array([1.0, 0.0]), ax, np.array([0.0, 1.0])),
        (np.array([ax, 0.0]), np.array([0.0, 1.0]), ay, np.array([-1.0, 0.0])),
        (np.array([0.0, ay]), np.array([-1.0, 0.0]), ax, np.array([0.0, -1.0])),
        (np.array([-ax, 0.0]), np.array([0.0, -1.0]), ay, np.array([1.0, 0.0])),
    ]

    def rect_fp(center, along, across, u):
        """World AABB footprint of a street-aligned rectangle."""
        ex = abs(u[0]) * along + abs(u[1]) * across
        ey = abs(u[1]) * along + abs(u[0]) * across
        return center[0] - ex, center[1] - ey, center[0] + ex, center[1] + ey

    for c, u, half_len, inner in streets:
        yaw = float(np.arctan2(u[1], u[0]))
        for side in (-1.0, 1.0):
            n = inner * side
            is_inner = side > 0
            usable = half_len - 9.0
            # Buildings along the street.
            a = -usable + rng.uniform(0, 4)
            while a < usable - 5:
                w = rng.uniform(7, 15)
                depth = rng.uniform(7, 11) if is_inner else rng.uniform(8, 14)
                setback = rng.uniform(9.0, 12.5)
                a_c = a + w / 2
                if a_c + w / 2 > usable + 3:
                    break
                if is_inner:
                    depth = min(depth, (ay if abs(u[0]) > 0 else ax) - setback - 4.0)
                low = rng.random() < 0.5
                hgt = rng.uniform(5, 8) if low else rng.uniform(10, 24)
                ctr = c + a_c * u + (setback + depth / 2) * n
                box = rect_fp(ctr, w / 2, depth / 2, u)
                if depth > 4 and fp.free(*box):
                    fp.take(*box)
                    col = _jitter(rng, (196, 170, 140), 30)
                    add("building", [Box((ctr[0], ctr[1], hgt / 2), (w / 2, depth / 2, hgt / 2), yaw)], col)
                    if low and rng.random() < 0.75:
                        hc = rng.uniform(2.2, 3.5)
                        pc = c + (a_c + rng.uniform(-w / 4, w / 4)) * u + (setback + rng.uniform(1.0, 2.0)) * n
                        if rng.random() < 0.5:
                            sh = Box((pc[0], pc[1], hgt + hc / 2), (0.4, 0.4, hc / 2), yaw)
                        else:
                            sh = Cylinder(pc[0], pc[1], hgt, hgt + hc, 0.35)
                        add("chimney", [sh])
                a += w + rng.uniform(3, 9)

            def place(along_range, offset, half_along, half_across, tries=20):
                for _ in range(tries):
                    aa = rng.uniform(*along_range)
                    ctr = c + aa * u + offset * n
                    box = rect_fp(ctr, half_along, half_across, u)
                    if fp.free(*box, margin=0.4):
                        fp.take(*box)
                        return ctr
                return None

            rng_along = (-usable, usable)
            # Street lamps every ~20 m on the kerb.
            for a_l in np.arange(-usable + rng.uniform(0, 8), usable, 20.0 / density):
                ctr = c + a_l * u + 5.0 * n
                if fp.free(*rect_fp(ctr, 0.3, 0.3, u), margin=0.2):
                    fp.take(*rect_fp(ctr, 0.3, 0.3, u))
                    add("street lamp", [Cylinder(ctr[0], ctr[1], 0.0, 6.0, 0.09),
                                        Sphere((ctr[0] - 0.0, ctr[1], 6.2), 0.3)])
            # Trees on the verge.
            for _ in range(int(round(rng.integers(2, 5) * density)) or 1):
                r = rng.uniform(1.4, 2.2)
                ctr = place(rng_along, rng.uniform(6.4, 8.6 - r + 1.4), r, r)
                if ctr is not None:
                    trunk = rng.uniform(2.4, 3.6)
                    shapes = [Cylinder(ctr[0], ctr[1], 0.0, trunk, rng.uniform(0.15, 0.25))]
                    if rng.random() < 0.6:
                        shapes.append(Sphere((ctr[0], ctr[1], trunk + r * 0.8), r))
                    else:
                        shapes.append(Cone(ctr[0], ctr[1], trunk - 0.5, trunk + 3.2 * r, r))
                    add("tree", shapes, _jitter(rng, (46, 112, 46), 15))
                    parts[-2] = Part(parts[-2].shape, "tree", parts[-2].instance, (105, 75, 45))
            # Parked cars on the road edge (clear of the centre line by 2 m).
            for _ in range(int(rng.integers(1, 3)) if density == 1.0 else int(rng.integers(0, 2))):
                aa = rng.uniform(*rng_along)
                ctr = c + aa * u + 2.95 * n
                yaw_c = yaw + rng.uniform(-0.05, 0.05)
                if all(not (abs(ctr[0] - q[0]) < 5.0 and abs(ctr[1] - q[1]) < 2.5)
                       for q in [(p.shape.center[0], p.shape.center[1]) for p in parts if p.class_name == "car"]):
                    col = tuple(int(v) for v in rng.choice([(190, 40, 40), (40, 70, 170), (230, 230, 230),
                                                            (30, 30, 35), (200, 170, 40)]))
                    fwd = np.array([np.cos(yaw_c), np.sin(yaw_c)])
                    cab = ctr - 0.3 * fwd
                    add("car", [Box((ctr[0], ctr[1], ROAD_TOP + 0.45), (2.1, 0.88, 0.45), yaw_c),
                                Box((cab[0], cab[1], ROAD_TOP + 0.9 + 0.32), (1.1, 0.8, 0.32), yaw_c)], col)
            # A fence along a lot boundary.
            if rng.random() < 0.8 * density + 0.2:
                ln = rng.uniform(4, 9)
                ctr = place(rng_along, rng.uniform(8.0, 8.6), ln, 0.05)
                if ctr is not None:
                    hf = rng.uniform(1.1, 1.8)
                    add("fence", [Box((ctr[0], ctr[1], hf / 2), (ln, 0.05, hf / 2), yaw)])
            # A bench and a rock on the verge.
            if rng.random() < 0.7:
                ctr = place(rng_along, 5.9, 0.9, 0.3)
                if ctr is not None:
                    back = ctr + 0.25 * n
                    add("bench", [Box((ctr[0], ctr[1], 0.225), (0.9, 0.25, 0.225), yaw),
                                  Box((back[0], back[1], 0.55), (0.9, 0.05, 0.3), yaw)])
            if rng.random() < 0.7:
                r = rng.uniform(0.35, 0.9)
                ctr = place(rng_along, rng.uniform(6.0, 8.0), r, r)
                if ctr is not None:
                    add("rock", [Sphere((ctr[0], ctr[1], 0.35 * r), r)], _jitter(rng, (125, 120, 115), 12))

    # Fields around the town: trees and rocks.
    n_field = int(40 * density)
    placed = 0
    for _ in range(n_field * 5):
        if placed >= n_field:
            break
        ang = rng.uniform(0, 2 * np.pi)
        rad = rng.uniform(70, 150)
        x, y = rad * np.cos(ang), rad * np.sin(ang)
        r = rng.uniform(1.5, 3.0)
        if not fp.free(x - r, y - r, x + r, y + r, margin=1.0):
            continue
        fp.take(x - r, y - r, x + r, y + r)
        placed += 1
        if rng.random() < 0.8:
            trunk = rng.uniform(2.5, 4.0)
            add("tree", [Cylinder(x, y, 0.0, trunk, 0.25), Sphere((x, y, trunk + 0.8 * r), r)],
                _jitter(rng, (46, 112, 46), 15))
            parts[-2] = Part(parts[-2].shape, "tree", parts[-2].instance, (105, 75, 45))
        else:
            add("rock", [Sphere((x, y, 0.3 * r), r * 0.6)], _jitter(rng, (125, 120, 115), 12))

    # Far landmarks, in view along the streets.
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

    layout = Layout(half_x=ax, half_y=ay, corner_radius=8.0, road_top=ROAD_TOP,
                     extra={"far_instances": ["water_tower_0", "radio_tower_0", "chimney_factory", "building_factory",
                                              "building_far_0", "building_far_1", "building_far_2"]})
    return parts, layout
