"""Pinhole geometry with planar depth, numpy (float64 unless stated).

Pixel ``(u, v)`` = (column, row); pixel centres are at integer + 0.5 offsets, i.e. the
pixel at row ``r``, column ``c`` looks through ``(c + 0.5, r + 0.5)``. Camera axes RDF,
poses camera-to-world (see :mod:`common.conventions`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


def intrinsics_from_fov(hfov_deg: float, height: int, width: int, vfov_deg: float | None = None) -> np.ndarray:
    """3×3 K for an image of ``(height, width)`` with horizontal FoV ``hfov_deg``
    (square pixels unless ``vfov_deg`` is given); principal point at the image centre."""
    fx = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
    fy = fx if vfov_deg is None else 0.5 * height / np.tan(np.deg2rad(vfov_deg) / 2)
    return np.array([[fx, 0, width / 2.0], [0, fy, height / 2.0], [0, 0, 1.0]])


def fov_deg(K: np.ndarray, height: int, width: int) -> tuple[float, float]:
    """(horizontal, vertical) field of view in degrees."""
    return (float(np.rad2deg(2 * np.arctan(0.5 * width / K[0, 0]))),
            float(np.rad2deg(2 * np.arctan(0.5 * height / K[1, 1]))))


def scale_intrinsics(K: np.ndarray, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """K for the same camera resampled from ``from_hw`` to ``to_hw`` (height, width)."""
    sy, sx = to_hw[0] / from_hw[0], to_hw[1] / from_hw[1]
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, :] *= sx
    K2[1, :] *= sy
    K2[2] = [0, 0, 1]
    return K2


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) pixel-centre coordinates, each (H, W)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return u + 0.5, v + 0.5


def camera_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) camera-frame directions with z = 1 (multiply by planar depth → points)."""
    u, v = pixel_grid(height, width)
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def unproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points from planar depth (NaN/inf propagate)."""
    h, w = depth.shape
    return camera_rays(K, h, w) * np.asarray(depth, dtype=np.float64)[..., None]


def unproject_pixels(u: ArrayLike, v: ArrayLike, z: ArrayLike, K: np.ndarray) -> np.ndarray:
    """(N, 3) camera points from pixel coordinates ``u, v`` and planar depths ``z``."""
    u, v, z = (np.asarray(a, dtype=np.float64) for a in (u, v, z))
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)


def project(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) camera points → ((N, 2) pixel (u, v), (N,) planar depth z)."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    return np.stack([u, v], axis=-1), z


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 transform to (..., 3) points."""
    p = np.asarray(points, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world RDF pose at ``eye`` looking at ``target`` with world ``up`` (z-up)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-9:  # looking straight up/down: pick any right vector
        r = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)  # down = forward × right
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = r, d, f, eye
    return T
