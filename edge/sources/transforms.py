"""Rigid-transform helpers for the sources (numpy, float64, pure computation).

Quaternions are ``(x, y, z, w)`` (ROS / TartanAir order), Hamilton convention, and
need not be normalised on input.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


def quat_to_matrix(q: ArrayLike) -> np.ndarray:
    """3×3 rotation matrix of quaternion ``(x, y, z, w)``."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` with ``w >= 0`` of a 3×3 rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[3] < 0 else qa


def pose_from_tq(t: ArrayLike, q: ArrayLike) -> np.ndarray:
    """4×4 transform from translation ``t`` and quaternion ``q = (x, y, z, w)``."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def slerp(q0: ArrayLike, q1: ArrayLike, a: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions (shortest arc), ``a`` in [0, 1]."""
    q0 = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(min(d, 1.0))
    return (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """Pose a fraction ``a`` of the way from ``T0`` to ``T1`` (linear translation, slerp rotation)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(slerp(matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3]), a))
    T[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
    return T


class PoseTrack:
    """Time series of 4×4 poses, looked up at arbitrary times.

    ``at(t)``: the exact sample if one has stamp ``t``; else, with ``interpolate``, the
    interpolation between the samples just before and after ``t`` when they are at most
    ``max_gap`` seconds apart; else the nearest sample within ``tolerance`` seconds; else
    ``None`` (no extrapolation beyond ``tolerance``)."""

    def __init__(self, times: ArrayLike, poses: ArrayLike, tolerance: float, interpolate: bool = True,
                 max_gap: float = 0.5):
        order = np.argsort(np.asarray(times, dtype=np.float64), kind="stable")
        self.times = np.asarray(times, dtype=np.float64)[order]
        self.poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[order]
        self.tolerance = float(tolerance)
        self.interpolate = bool(interpolate)
        self.max_gap = float(max_gap)

    def __len__(self) -> int:
        return len(self.times)

    def at(self, t: float) -> np.ndarray | None:
        n = len(self.times)
        if n == 0:
            return None
        j = int(np.searchsorted(self.times, t, side="left"))
        if j < n and self.times[j] == t:
            return self.poses[j].copy()
        lo, hi = j - 1, j
        if self.interpolate and lo >= 0 and hi < n and self.times[hi] - self.times[lo] <= self.max_gap:
            a = (t - self.times[lo]) / (self.times[hi] - self.times[lo])
            return interpolate_pose(self.poses[lo], self.poses[hi], a)
        best = min((k for k in (lo, hi) if 0 <= k < n), key=lambda k: abs(self.times[k] - t))
        if abs(self.times[best] - t) <= self.tolerance:
            return self.poses[best].copy()
        return None
