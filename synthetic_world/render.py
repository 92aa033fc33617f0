"""Exact ray casting of a primitive scene into RGB, planar depth, labels and instance ids.

Each pixel's ray goes through its centre (``common.geometry`` convention) with direction
``R · (x, y, 1)`` (camera-frame z = 1), so the hit parameter ``t`` *is* the planar depth.
Culling: every primitive's world AABB, clipped against the near plane, is projected into
the image, and the primitive is intersected only with the pixels of that rectangle
(skipped if it lies behind the camera or outside the image). Nearest hit wins (ties: earlier primitive).
Shading: colour × (ambient + Lambert with a fixed sun), a slight aerial-perspective fade
with distance, plus ±3 levels of noise from a generator seeded by the pose bytes, so
rendering is deterministic.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.geometry import camera_rays

from .primitives import HIT, NORMAL

#: direction *towards* the sun, world frame (z up).
SUN = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])
SKY_HORIZON = np.array([205.0, 222.0, 240.0])
SKY_ZENITH = np.array([105.0, 155.0, 225.0])
_NEAR = 1e-3


@dataclass
class Render:
    """One rendered view. ``rgb`` (H,W,3) uint8; ``depth`` (H,W) float32 planar z in metres
    (+inf = sky/nothing); ``labels`` (H,W) int32 class ids (0 = sky); ``instance`` (H,W)
    int32 instance ids (−1 = none)."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    instance: np.ndarray


_RAY_CACHE: dict[tuple, np.ndarray] = {}


def _rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    key = (K.tobytes(), h, w)
    r = _RAY_CACHE.get(key)
    if r is None:
        if len(_RAY_CACHE) > 16:
            _RAY_CACHE.clear()
        r = camera_rays(K, h, w)
        _RAY_CACHE[key] = r
    return r


def _pose_seed(pose: np.ndarray) -> int:
    return int.from_bytes(hashlib.blake2b(np.ascontiguousarray(pose, dtype=np.float64).tobytes(),
                                          digest_size=8).digest(), "little")


# The 12 edges of a box with corners indexed by bits (x, y, z).
_EDGES = np.array([(i, i | (1 << a)) for i in range(8) for a in range(3) if not i & (1 << a)])


def _pixel_boxes(corners: np.ndarray, R: np.ndarray, o: np.ndarray, K: np.ndarray, h: int, w: int):
    """Pixel rectangles [r0, r1) × [c0, c1) covering each primitive's AABB (P, 8, 3 corners),
    clipped against the near plane, and a visibility flag."""
    pc = (corners - o) @ R  # camera frame (P, 8, 3)
    za, zb = pc[:, _EDGES[:, 0], 2], pc[:, _EDGES[:, 1], 2]
    cross = (za < _NEAR) != (zb < _NEAR)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (_NEAR - za) / (zb - za)
    ep = pc[:, _EDGES[:, 0]] + np.where(cross, s, 0.0)[..., None] * (pc[:, _EDGES[:, 1]] - pc[:, _EDGES[:, 0]])
    pts = np.concatenate([pc, ep], axis=1)  # (P, 20, 3)
    ok = np.concatenate([pc[..., 2] >= _NEAR, cross], axis=1)
    z = np.where(ok, np.maximum(pts[..., 2], _NEAR), 1.0)
    u = K[0, 0] * pts[..., 0] / z + K[0, 2]
    v = K[1, 1] * pts[..., 1] / z + K[1, 2]
    umin, umax = np.where(ok, u, np.inf).min(1), np.where(ok, u, -np.inf).max(1)
    vmin, vmax = np.where(ok, v, np.inf).min(1), np.where(ok, v, -np.inf).max(1)
    any_ok = ok.any(1)
    with np.errstate(invalid="ignore"):
        c0 = np.clip(np.floor(np.where(any_ok, umin, 0) - 0.5), 0, w).astype(np.int64)
        c1 = np.clip(np.ceil(np.where(any_ok, umax, 0) + 0.5), 0, w).astype(np.int64)
        r0 = np.clip(np.floor(np.where(any_ok, vmin, 0) - 0.5), 0, h).astype(np.int64)
        r1 = np.clip(np.ceil(np.where(any_ok, vmax, 0) + 0.5), 0, h).astype(np.int64)
    return r0, r1, c0, c1, any_ok & (c1 > c0) & (r1 > r0)


def render_scene(scene: Any, pose: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> Render:
    """Render ``scene`` (a :class:`synthetic_world.World`; not imported here, the scene module imports
    this one) from camera-to-world ``pose`` (RDF)."""
    pose = np.asarray(pose, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"pose must be a finite 4x4 camera-to-world matrix, got shape {pose.shape}")
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a 3x3 intrinsics matrix with positive focal lengths, got {K}")
    h, w = (int(hw[0]), int(hw[1]))
    if h <= 0 or w <= 0:
        raise ValueError(f"image size (H, W) must be positive, got {hw}")
    R, o = pose[:3, :3], pose[:3, 3]
    dirs = _rays(K, h, w) @ R.T  # (H, W, 3) world directions, camera z = 1
    comp = [np.ascontiguousarray(dirs[..., i]) for i in range(3)]
    depth = np.full((h, w), np.inf)
    prim = np.full((h, w), -1, dtype=np.int64)

    r0, r1, c0, c1, visible = _pixel_boxes(scene._corners, R, o, K, h, w)
    kinds, kidx, params = scene._kind, scene._kidx, scene._params
    for i in np.nonzero(visible)[0]:
        a, b, c, e = r0[i], r1[i], c0[i], c1[i]
        d = (comp[0][a:b, c:e].ravel(), comp[1][a:b, c:e].ravel(), comp[2][a:b, c:e].ravel())
        t = HIT[kinds[i]](o, d, params[kinds[i]][kidx[i]]).reshape(b - a, e - c)
        cur = depth[a:b, c:e]
        m = t < cur
        if not m.any():
            continue
        cur[m] = t[m]
        prim[a:b, c:e][m] = i

    # Normals of the visible surfaces, one primitive at a time.
    normal = np.zeros((h, w, 3))
    hitm = prim >= 0
    flat = prim.ravel()
    idx = np.nonzero(hitm.ravel())[0]
    if len(idx):
        pts = o + dirs.reshape(-1, 3)[idx] * depth.ravel()[idx, None]
        ids = flat[idx]
        order = np.argsort(ids, kind="stable")
        ids_s = ids[order]
        starts = np.flatnonzero(np.r_[True, ids_s[1:] != ids_s[:-1]])
        ends = np.r_[starts[1:], len(ids_s)]
        nflat = normal.reshape(-1, 3)
        for s0, s1 in zip(starts, ends, strict=True):
            i = ids_s[s0]
            sel = order[s0:s1]
            nflat[idx[sel]] = NORMAL[kinds[i]](pts[sel], params[kinds[i]][kidx[i]])

    labels = np.where(hitm, scene._cls[np.maximum(prim, 0)], 0).astype(np.int32)
    instance = np.where(hitm, scene._inst[np.maximum(prim, 0)], -1).astype(np.int32)

    # Shading.
    base = scene._color[np.maximum(prim, 0)]
    lam = np.clip(normal @ SUN, 0.0, None)
    shade = 0.42 + 0.58 * lam
    col = base * shade[..., None]
    dist = depth * np.linalg.norm(dirs, axis=-1)
    fog = 1.0 - np.exp(-np.where(hitm, dist, 0.0) / 900.0)
    col = col * (1 - fog[..., None]) + SKY_HORIZON * fog[..., None]
    elev = dirs[..., 2] / np.linalg.norm(dirs, axis=-1)
    s = np.clip(elev, 0.0, 1.0) ** 0.6
    sky = SKY_HORIZON * (1 - s[..., None]) + SKY_ZENITH * s[..., None]
    col = np.where(hitm[..., None], col, sky)
    noise = np.random.default_rng(_pose_seed(pose)).integers(-3, 4, size=(h, w, 3), dtype=np.int8)
    rgb = np.clip(col + noise, 0, 255).astype(np.uint8)
    return Render(rgb=rgb, depth=depth.astype(np.float32), labels=labels, instance=instance)
