"""Solid primitives of the synthetic world and their exact geometry (numpy, float64).

World frame: z up (x east, y north), metres. Three shapes cover everything:

* :class:`Box` — oriented box: ``center`` (3,), ``half`` extents (3,) along its local axes,
  ``yaw`` (rad, counter-clockwise about +z; local x = (cos yaw, sin yaw, 0)).
* :class:`Frustum` — vertical truncated cone on the axis through ``(cx, cy)`` from
  ``z0`` to ``z1 > z0``, bottom radius ``r0`` and top radius ``r1`` (both ≥ 0, not both 0).
  :func:`Cylinder` (r0 == r1) and :func:`Cone` (r1 == 0 by default) build it.
* :class:`Sphere` — ``center`` (3,), ``radius``.

All are convex solids. The kernels below work on *packed* parameter arrays and broadcast
(``p`` of shape (..., 3) against parameters of shape (...,)), so the same code evaluates
"N points × M primitives" and "M points, one per primitive".

* ``*_hit(o, d, prm)``: first entry of the rays ``o + t d`` (t > 0) into one solid; ``d`` is
  a tuple of direction components and need not be unit length, so with camera-frame
  z = 1 directions, ``t`` is planar depth. A ray starting inside a solid does not hit it.
  Returns ``t`` (+inf on miss). ``*_normal(p, prm)``: outward unit normals at surface points.
* ``*_dist(p, ...)``: exact Euclidean distance from points to the solid (0 inside).
* ``*_contains(p, ...)``: closed point-in-solid test.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_EPS_T = 1e-9


@dataclass(frozen=True)
class Box:
    """Oriented box (yaw about +z). ``center`` and ``half`` in metres, ``yaw`` in radians."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float = 0.0

    def __post_init__(self):
        if len(self.center) != 3 or len(self.half) != 3:
            raise ValueError(f"Box needs a 3-vector center and half extents, got {self.center}, {self.half}")
        if not all(h > 0 for h in self.half):
            raise ValueError(f"Box half extents must be > 0, got {self.half}")

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        c, s = abs(np.cos(self.yaw)), abs(np.sin(self.yaw))
        hx, hy, hz = self.half
        ext = np.array([c * hx + s * hy, s * hx + c * hy, hz])
        ctr = np.asarray(self.center, dtype=np.float64)
        return ctr - ext, ctr + ext


@dataclass(frozen=True)
class Frustum:
    """Vertical truncated cone: axis through ``(cx, cy)``, ``z0 < z1``, radii ``r0`` (bottom), ``r1`` (top)."""

    cx: float
    cy: float
    z0: float
    z1: float
    r0: float
    r1: float

    def __post_init__(self):
        if not self.z1 > self.z0:
            raise ValueError(f"Frustum needs z1 > z0, got z0={self.z0}, z1={self.z1}")
        if self.r0 < 0 or self.r1 < 0 or max(self.r0, self.r1) <= 0:
            raise ValueError(f"Frustum radii must be >= 0 and not both 0, got r0={self.r0}, r1={self.r1}")

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        r = max(self.r0, self.r1)
        return (np.array([self.cx - r, self.cy - r, self.z0]), np.array([self.cx + r, self.cy + r, self.z1]))


def Cylinder(cx: float, cy: float, z0: float, z1: float, radius: float) -> Frustum:
    """Vertical cylinder (a :class:`Frustum` with equal radii)."""
    return Frustum(cx, cy, z0, z1, radius, radius)


def Cone(cx: float, cy: float, z0: float, z1: float, r0: float, r1: float = 0.0) -> Frustum:
    """Vertical cone (apex up when ``r1 = 0``) or truncated cone."""
    return Frustum(cx, cy, z0, z1, r0, r1)


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float

    def __post_init__(self):
        if len(self.center) != 3 or not self.radius > 0:
            raise ValueError(f"Sphere needs a 3-vector center and radius > 0, got {self.center}, {self.radius}")

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(self.center, dtype=np.float64)
        return c - self.radius, c + self.radius


Shape = Box | Frustum | Sphere

KIND_BOX, KIND_FRUSTUM, KIND_SPHERE = 0, 1, 2


def pack(shapes: list[Shape]) -> dict[int, np.ndarray]:
    """Packed parameter arrays per kind: box (M, 8) = cx cy cz hx hy hz cos sin;
    frustum (M, 6) = cx cy z0 z1 r0 r1; sphere (M, 4) = cx cy cz r."""
    rows: dict[int, list] = {KIND_BOX: [], KIND_FRUSTUM: [], KIND_SPHERE: []}
    for s in shapes:
        if isinstance(s, Box):
            rows[KIND_BOX].append([*s.center, *s.half, np.cos(s.yaw), np.sin(s.yaw)])
        elif isinstance(s, Frustum):
            rows[KIND_FRUSTUM].append([s.cx, s.cy, s.z0, s.z1, s.r0, s.r1])
        elif isinstance(s, Sphere):
            rows[KIND_SPHERE].append([*s.center, s.radius])
        else:
            raise TypeError(f"not a primitive shape: {s!r} (use Box, Frustum/Cylinder/Cone, Sphere)")
    width = {KIND_BOX: 8, KIND_FRUSTUM: 6, KIND_SPHERE: 4}
    return {k: np.asarray(v, dtype=np.float64).reshape(-1, width[k]) for k, v in rows.items()}


def kind_of(s: Shape) -> int:
    return KIND_BOX if isinstance(s, Box) else KIND_FRUSTUM if isinstance(s, Frustum) else KIND_SPHERE


# ----------------------------------------------------------------------------- boxes


def _box_local(v: np.ndarray, cs, sn) -> np.ndarray:
    """World vector(s) → box-local axes (rotation by −yaw)."""
    x, y = v[..., 0], v[..., 1]
    return np.stack([cs * x + sn * y, -sn * x + cs * y, np.broadcast_to(v[..., 2], np.broadcast(x, cs).shape)], axis=-1)


def box_hit(o: np.ndarray, d: tuple[np.ndarray, np.ndarray, np.ndarray], prm: np.ndarray) -> np.ndarray:
    """Slab test of rays ``o`` (3,) + t ``d`` against one box ``prm`` (8,); ``d`` is the
    tuple of direction components (each (N,)). Returns t (N,), +inf on miss."""
    c, h, cs, sn = prm[0:3], prm[3:6], prm[6], prm[7]
    ox, oy = o[0] - c[0], o[1] - c[1]
    ol = (cs * ox + sn * oy, -sn * ox + cs * oy, o[2] - c[2])
    dl = (cs * d[0] + sn * d[1], -sn * d[0] + cs * d[1], d[2]) if (sn != 0.0 or cs != 1.0) else d
    tn = tf = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            inv = 1.0 / dl[i]
            t1 = (-h[i] - ol[i]) * inv
            t2 = (h[i] - ol[i]) * inv
            lo, hi = np.fmin(t1, t2), np.fmax(t1, t2)
            tn = lo if tn is None else np.fmax(tn, lo)
            tf = hi if tf is None else np.fmin(tf, hi)
    assert tn is not None and tf is not None             # set by the three slabs above
    return np.where((tn <= tf) & (tn > _EPS_T), tn, np.inf)


def box_normal(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    """Outward unit normals (N, 3) at surface points ``p`` (N, 3) of one box."""
    cs, sn, h = prm[6], prm[7], prm[3:6]
    pl = _box_local(p - prm[0:3], cs, sn)
    axis = np.argmax(np.abs(pl) - h, axis=1)
    rows = np.arange(len(p))
    nl = np.zeros_like(pl)
    nl[rows, axis] = np.sign(pl[rows, axis])
    return np.stack([cs * nl[:, 0] - sn * nl[:, 1], sn * nl[:, 0] + cs * nl[:, 1], nl[:, 2]], axis=-1)


def box_dist(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    """Distance from points (..., 3) to boxes (..., 8) (broadcast); 0 inside."""
    q = np.abs(_box_local(p - prm[..., 0:3], prm[..., 6], prm[..., 7])) - prm[..., 3:6]
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1)


def box_contains(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    q = np.abs(_box_local(p - prm[..., 0:3], prm[..., 6], prm[..., 7])) - prm[..., 3:6]
    return np.all(q <= 0.0, axis=-1)


# ----------------------------------------------------------------------------- frusta


def frustum_hit(o: np.ndarray, d: tuple[np.ndarray, np.ndarray, np.ndarray], prm: np.ndarray) -> np.ndarray:
    """Rays ``o`` (3,) + t ``d`` (component tuple) against one vertical frustum ``prm`` (6,):
    lateral surface (quadratic) and the two cap discs. Returns t (N,), +inf on miss."""
    cx, cy, z0, z1, r0, r1 = prm
    hh = z1 - z0
    k = (r1 - r0) / hh
    ox, oy, oz = o[0] - cx, o[1] - cy, o[2] - z0
    dx, dy, dz = d
    ro = r0 + k * oz
    a = dx * dx + dy * dy - (k * k) * (dz * dz)
    b = 2.0 * (ox * dx + oy * dy - (k * ro) * dz)
    c = ox * ox + oy * oy - ro * ro
    disc = b * b - 4.0 * a * c
    best = np.full(len(dx), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(disc)  # NaN where disc < 0: every comparison below is False there
        qq = -0.5 * (b + np.copysign(sq, b))
        for t in (qq / a, c / qq):
            z = oz + t * dz
            ok = (t > _EPS_T) & (z >= 0.0) & (z <= hh) & (t < best)
            best = np.where(ok, t, best)
        for zc, rc in ((0.0, r0), (hh, r1)):
            if rc <= 0:
                continue
            t = (zc - oz) / dz
            x, y = ox + t * dx, oy + t * dy
            ok = (t > _EPS_T) & (x * x + y * y <= rc * rc) & (t < best)
            best = np.where(ok, t, best)
    return best


def frustum_normal(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    """Outward unit normals (N, 3) at surface points ``p`` (N, 3) of one frustum."""
    cx, cy, z0, z1, r0, r1 = prm
    hh = z1 - z0
    k = (r1 - r0) / hh
    px, py, z = p[:, 0] - cx, p[:, 1] - cy, p[:, 2] - z0
    rz = r0 + k * z
    cosa = 1.0 / np.sqrt(1.0 + k * k)
    d_lat = np.abs(np.hypot(px, py) - rz) * cosa
    lat = np.stack([px, py, -k * rz], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        lat = np.nan_to_num(lat / np.linalg.norm(lat, axis=-1, keepdims=True))
    n = np.where((d_lat <= np.minimum(np.abs(z), np.abs(z - hh)))[:, None], lat, 0.0)
    cap = d_lat > np.minimum(np.abs(z), np.abs(z - hh))
    n[cap, 2] = np.where(np.abs(z[cap]) < np.abs(z[cap] - hh), -1.0, 1.0)
    return n


def _seg_dist2(px, py, ax, ay, bx, by):
    ex, ey = bx - ax, by - ay
    ll = np.maximum(ex * ex + ey * ey, 1e-300)
    t = np.clip(((px - ax) * ex + (py - ay) * ey) / ll, 0.0, 1.0)
    dx, dy = px - ax - t * ex, py - ay - t * ey
    return dx * dx + dy * dy


def frustum_dist(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    """Exact distance from points (..., 3) to frusta (..., 6): distance in the (ρ, z)
    half-plane to the trapezoid (0,0)-(r0,0)-(r1,H)-(0,H) (the solid is convex and
    rotationally symmetric, so the nearest point lies in the point's half-plane)."""
    rho = np.hypot(p[..., 0] - prm[..., 0], p[..., 1] - prm[..., 1])
    z = p[..., 2] - prm[..., 2]
    hh = prm[..., 3] - prm[..., 2]
    r0, r1 = prm[..., 4], prm[..., 5]
    inside = (z >= 0) & (z <= hh) & (rho <= r0 + (r1 - r0) * z / hh)
    zero = np.zeros_like(rho)
    d2 = np.minimum(np.minimum(_seg_dist2(rho, z, zero, zero, r0, zero),
                               _seg_dist2(rho, z, r0, zero, r1, hh)),
                    _seg_dist2(rho, z, r1, hh, zero, hh))
    return np.where(inside, 0.0, np.sqrt(d2))


def frustum_contains(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    rho = np.hypot(p[..., 0] - prm[..., 0], p[..., 1] - prm[..., 1])
    z = p[..., 2] - prm[..., 2]
    hh = prm[..., 3] - prm[..., 2]
    return (z >= 0) & (z <= hh) & (rho <= prm[..., 4] + (prm[..., 5] - prm[..., 4]) * z / hh)


# ----------------------------------------------------------------------------- spheres


def sphere_hit(o: np.ndarray, d: tuple[np.ndarray, np.ndarray, np.ndarray], prm: np.ndarray) -> np.ndarray:
    ocx, ocy, ocz = o[0] - prm[0], o[1] - prm[1], o[2] - prm[2]
    dx, dy, dz = d
    a = dx * dx + dy * dy + dz * dz
    b = 2.0 * (ocx * dx + ocy * dy + ocz * dz)
    cc = ocx * ocx + ocy * ocy + ocz * ocz - prm[3] * prm[3]
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(b * b - 4 * a * cc)) / (2 * a)
    return np.where(t > _EPS_T, t, np.inf)


def sphere_normal(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    return (p - prm[0:3]) / prm[3]


def sphere_dist(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    return np.maximum(np.linalg.norm(p - prm[..., 0:3], axis=-1) - prm[..., 3], 0.0)


def sphere_contains(p: np.ndarray, prm: np.ndarray) -> np.ndarray:
    return np.sum((p - prm[..., 0:3]) ** 2, axis=-1) <= prm[..., 3] ** 2


HIT = {KIND_BOX: box_hit, KIND_FRUSTUM: frustum_hit, KIND_SPHERE: sphere_hit}
NORMAL = {KIND_BOX: box_normal, KIND_FRUSTUM: frustum_normal, KIND_SPHERE: sphere_normal}
DIST = {KIND_BOX: box_dist, KIND_FRUSTUM: frustum_dist, KIND_SPHERE: sphere_dist}
CONTAINS = {KIND_BOX: box_contains, KIND_FRUSTUM: frustum_contains, KIND_SPHERE: sphere_contains}
