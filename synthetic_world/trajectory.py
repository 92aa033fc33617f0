"""Camera trajectories through the town (camera-to-world, RDF camera axes, z-up world).

Both presets follow the loop of streets (a rounded rectangle on the street centre lines,
corner radius ``layout.corner_radius``), one full lap over the requested frames
(``n_frames`` evenly spaced poses, the last one short of closing the loop), starting at a
seed-dependent point and direction:

* ``"ground"``: eye 1.5 m above the road, heading along the street, with slow ±10° yaw
  sway and ±1.5° pitch sway around a 2° downward tilt (a car-mounted camera).
* ``"drone"``: altitude 10–18 m, pitched down 17–29°, heading along the street with ±15°
  yaw sway.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from common.geometry import look_at

from .parts import Layout

PRESETS = ("ground", "drone")


class HasLayout(Protocol):
    """What a trajectory needs of a world (a :class:`synthetic_world.World`): its town layout."""

    layout: Layout


def loop_path(half_x: float, half_y: float, radius: float,
              step: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense samples of the counter-clockwise rounded-rectangle loop starting at
    ``(-half_x + radius, -half_y)`` heading east: (s, x, y, heading) arrays, heading unwrapped."""
    r = float(radius)
    pts, heads = [], []

    def straight(p0, p1):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        n = max(int(np.ceil(np.linalg.norm(p1 - p0) / step)), 1)
        t = np.arange(n) / n
        pts.append(p0 + t[:, None] * (p1 - p0))
        heads.append(np.full(n, np.arctan2(*(p1 - p0)[::-1])))

    def arc(center, a0):
        n = max(int(np.ceil(r * np.pi / 2 / step)), 1)
        a = a0 + (np.arange(n) / n) * np.pi / 2
        pts.append(np.stack([center[0] + r * np.cos(a), center[1] + r * np.sin(a)], -1))
        heads.append(a + np.pi / 2)

    ax, ay = half_x, half_y
    straight((-ax + r, -ay), (ax - r, -ay))
    arc((ax - r, -ay + r), -np.pi / 2)
    straight((ax, -ay + r), (ax, ay - r))
    arc((ax - r, ay - r), 0.0)
    straight((ax - r, ay), (-ax + r, ay))
    arc((-ax + r, ay - r), np.pi / 2)
    straight((-ax, ay - r), (-ax, -ay + r))
    arc((-ax + r, -ay + r), np.pi)
    xy = np.concatenate(pts + [pts[0][:1]])
    hd = np.unwrap(np.concatenate(heads + [heads[0][:1] + 2 * np.pi]))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    return s, xy[:, 0], xy[:, 1], hd


def _pose(eye: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    return look_at(eye, eye + f)


def trajectory(world: HasLayout, preset: str = "ground", n_frames: int = 100, seed: int | None = 0) -> np.ndarray:
    """(n_frames, 4, 4) float64 camera-to-world RDF poses for ``world`` (see module doc)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown trajectory preset {preset!r}; valid presets: {', '.join(PRESETS)}")
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames}")
    n_frames = int(n_frames)
    lay = world.layout
    s, x, y, hd = loop_path(lay.half_x, lay.half_y, lay.corner_radius)
    length = s[-1]
    rng = np.random.default_rng(np.random.SeedSequence([0 if seed is None else int(seed), 7]))
    start = rng.uniform(0, length)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    ph = rng.uniform(0, 2 * np.pi, size=4)
    dist = np.arange(n_frames) * (length / n_frames)  # distance travelled
    q = np.mod(start + direction * dist, length)
    px, py = np.interp(q, s, x), np.interp(q, s, y)
    heading = np.interp(q, s, hd) + (0.0 if direction > 0 else np.pi)
    out = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        d = dist[i]
        if preset == "ground":
            yaw = heading[i] + np.deg2rad(10.0) * np.sin(2 * np.pi * d / 55.0 + ph[0])
            pitch = np.deg2rad(-2.0 + 1.5 * np.sin(2 * np.pi * d / 37.0 + ph[1]))
            z = lay.road_top + 1.5
        else:
            yaw = heading[i] + np.deg2rad(15.0) * np.sin(2 * np.pi * d / 80.0 + ph[0])
            pitch = -np.deg2rad(23.0 + 6.0 * np.sin(2 * np.pi * d / 61.0 + ph[1]))
            z = 14.0 + 4.0 * np.sin(2 * np.pi * 2 * d / length + ph[2])
        out[i] = _pose(np.array([px[i], py[i], z]), yaw, pitch)
    return out
