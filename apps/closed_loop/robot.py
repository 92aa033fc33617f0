"""Robot platforms for closed-loop search: camera poses and collision checks against the TRUE
synthetic world (docs/synthetic_world.md).

World frame z up, metres; poses camera-to-world with RDF camera axes (x right, y down,
z forward). ``ground``: camera 1.5 m above the ground plane, body a vertical cylinder of
``radius`` from its ground clearance (:data:`GROUND_CLEARANCE_M`: it drives over anything
lower, as the map's 0.5 m voxels cannot tell such things from the ground) to the camera
height. ``drone``: a sphere of ``radius`` around the camera, cruising at ``cruise_z`` (the
middle of its altitude band).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from synthetic_world import World

#: the ground robot's body starts this high (m): lower things pass under it
GROUND_CLEARANCE_M = 0.55


@dataclass(frozen=True)
class Platform:
    """Motion model: ``name`` 'ground' or 'drone', body ``radius`` (m), camera/altitude band (m)."""

    name: str = "ground"
    radius: float = 0.4
    z_band: tuple[float, float] = (1.5, 1.5)

    @classmethod
    def make(cls, name: str) -> "Platform":
        """The default ground robot (camera at 1.5 m) or drone (altitude 3-8 m)."""
        if name == "ground":
            return cls("ground", 0.4, (1.5, 1.5))
        if name == "drone":
            return cls("drone", 0.4, (3.0, 8.0))
        raise ValueError(f"unknown platform {name!r} (ground, drone)")

    @property
    def cruise_z(self) -> float:
        """Camera height (m) the platform keeps: 1.5 m (ground) or the middle of the band (drone)."""
        return self.z_band[0] if self.name == "ground" else 0.5 * (self.z_band[0] + self.z_band[1])

    @property
    def goal_band(self) -> tuple[float, float]:
        """z band (m) of the frontiers worth driving to: what the camera can see from its height."""
        return (-1.0, 4.0) if self.name == "ground" else (self.z_band[0] - 4.0, self.z_band[1] + 4.0)

    def costmap_band(self, vox: float) -> tuple[float, float]:
        """z band (m) of the map a 2D costmap for this body reads: ground from the first voxel
        layer above the ground's up to the camera; drone the voxel layers its body spans."""
        if self.name == "ground":
            return (max(GROUND_CLEARANCE_M - 0.05, vox) + 1e-3, self.z_band[0] + 0.2)
        return (self.cruise_z - self.radius, self.cruise_z + self.radius)

    def with_own_body_free(self, states: np.ndarray, origin: np.ndarray, cell: float, at: np.ndarray
                           ) -> np.ndarray:
        """The costmap ``states`` ([x, y], cells of ``cell`` m from ``origin``) with the UNKNOWN
        cells within ``radius + cell`` of the body at ``at`` (m) marked FREE — drone only. The
        drone stands in that space (every move is checked against the true world), but its
        cameras, tilted down, see the layer just above its own height only from ~0.7 m out; a
        ground camera sees the ground around it from 0.55 m, so its costmap is left as it is."""
        if self.name == "ground":
            return states
        from apps.closed_loop.planner import FREE, UNKNOWN

        c = np.asarray(origin, np.float64) + (np.indices(states.shape).transpose(1, 2, 0) + 0.5) * cell
        near = np.linalg.norm(c - np.asarray(at[:2], np.float64), axis=2) <= self.radius + cell
        out = np.array(states, copy=True)
        out[near & (out == UNKNOWN)] = FREE
        return out

    def body_points(self, centre: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N, 3) sample points of the body (a disk of radius ``radius + margin`` m per level)
        with the camera at ``centre`` (3,) metres."""
        c = np.asarray(centre, np.float64).reshape(3)
        ang = np.linspace(0.0, 2 * math.pi, 16, endpoint=False)
        unit = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
        r = self.radius + margin
        ring = np.concatenate([np.zeros((1, 3))] + [unit * f * r for f in np.linspace(0.25, 1.0, 4)], 0)
        if self.name == "ground":
            zs = np.linspace(GROUND_CLEARANCE_M, c[2], 4) - c[2]
        else:
            zs = np.array([-self.radius, 0.0, self.radius])
        pts = [c + ring + [0.0, 0.0, dz] for dz in zs] + [c[None]]
        return np.concatenate(pts, 0)

    def collides(self, world: World, a: np.ndarray, b: np.ndarray, spacing: float = 0.1) -> bool:
        """True if the body swept from ``a`` to ``b`` (camera centres, m) touches any solid of the
        true world (sampled every ``spacing`` m along the segment)."""
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / spacing)) + 1)
        pts = np.concatenate([self.body_points(a + (b - a) * t) for t in np.linspace(0.0, 1.0, n)], 0)
        return bool((world.labels_at(pts) != 0).any())


def camera_pose(centre: np.ndarray, yaw: float, pitch: float = 0.0) -> np.ndarray:
    """(4, 4) camera-to-world RDF pose at ``centre`` (m) looking along yaw (rad, counter-clockwise
    from +x), tilted down by ``pitch`` (rad)."""
    h = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    fwd = h * math.cos(pitch) + np.array([0.0, 0.0, -math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, fwd, np.asarray(centre, np.float64)
    return pose


def true_free_grid(world: World, platform: Platform, xy_min: np.ndarray, xy_max: np.ndarray,
                   cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(states (nx, ny) int8 FREE=0/OCCUPIED=1, origin (2,) m) of the TRUE world for the
    platform at its cruise height: a cell is free when the body, inflated by the cell's half-diagonal, standing at the
    cell centre touches no solid (so moves between free neighbours are collision free)."""
    lo = np.asarray(xy_min, np.float64)
    n = np.maximum(1, np.ceil((np.asarray(xy_max, np.float64) - lo) / cell).astype(int))
    ii, jj = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
    centres = np.stack([lo[0] + (ii.ravel() + 0.5) * cell, lo[1] + (jj.ravel() + 0.5) * cell,
                        np.full(ii.size, platform.cruise_z)], 1)
    body = platform.body_points(np.array([0.0, 0.0, platform.cruise_z]), cell * 0.75)
    body[:, 2] -= platform.cruise_z
    pts = (centres[:, None, :] + body[None]).reshape(-1, 3)
    hit = (world.labels_at(pts) != 0).reshape(len(centres), len(body)).any(1)
    return hit.reshape(n[0], n[1]).astype(np.int8), lo
