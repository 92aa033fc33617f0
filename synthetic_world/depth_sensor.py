"""A depth camera like a real one, applied to a world's exact planar depth
(docs/pybullet_world.md#the-depth-sensor-model).

A rendered depth image is exact at any range and +inf only where there is no surface (sky).
A real range sensor (stereo, time of flight, a metric depth network) is not: it returns
nothing past its range, for a far building as for the sky, its depth is noisier the farther
the surface, and it loses pixels where the surface is seen at a grazing angle and along depth
edges. :class:`DepthSensorModel` turns the first into the second, per pixel:

1. **Range.** Euclidean range ``r = z·|K⁻¹(u, v, 1)|``. ``r > max_range_m`` (or no surface):
   no return.
2. **Noise.** ``z' = z + ε``, ``ε ~ N(0, σ(z)²)``, ``σ(z) = noise_k · z²`` (the stereo
   law: disparity error constant, depth error ∝ z²; ``noise_k`` in 1/m), clipped at
   ``min_depth_m``.
3. **Grazing dropouts.** With the incidence angle θ between the pixel's ray and the surface
   normal (normal from the depth image's own back-projected neighbours), a pixel off depth
   edges drops out with probability ``clip((θ − grazing_deg) / (90° − grazing_deg), 0, 1)``.
4. **Edge dropouts.** A pixel whose 4-neighbour's depth differs by more than
   ``edge_jump · z`` (or has no surface) lies on a depth edge; it drops out with probability
   ``edge_drop``.

Every pixel without a return (beyond range, no surface, dropped) carries ``no_return``:
``inf`` (default: the conventions' "beyond range", so the map casts rays from it, as
RayFronts does with a real sensor's missing pixels) or ``nan`` ("no measurement"). Draws
come from the ``numpy.random.Generator`` the caller passes (reproducible by its seed).
Depths in metres, planar along the optical axis; angles in degrees.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DepthSensorModel:
    """The model's parameters (module docstring)."""

    max_range_m: float = 20.0
    noise_k: float = 0.001
    grazing_deg: float = 75.0
    edge_jump: float = 0.1
    edge_drop: float = 0.5
    min_depth_m: float = 0.05
    no_return: str = "inf"

    def validate(self) -> "DepthSensorModel":
        if not self.max_range_m > 0 or self.noise_k < 0 or not 0 < self.grazing_deg < 90:
            raise ValueError(f"depth sensor: need max_range_m > 0, noise_k >= 0, 0 < grazing_deg < 90; got "
                             f"{self.max_range_m}, {self.noise_k}, {self.grazing_deg}")
        if not 0 <= self.edge_drop <= 1 or self.edge_jump <= 0:
            raise ValueError(f"depth sensor: need edge_drop in [0, 1] and edge_jump > 0; got {self.edge_drop}, "
                             f"{self.edge_jump}")
        if self.no_return not in ("inf", "nan"):
            raise ValueError(f"depth sensor: no_return must be 'inf' or 'nan', got {self.no_return!r}")
        return self

    def sigma(self, z: np.ndarray | float) -> np.ndarray:
        """Noise standard deviation (m) at planar depth ``z`` (m)."""
        return self.noise_k * np.square(np.asarray(z, np.float64))

    def grazing_drop_p(self, theta_deg: np.ndarray | float) -> np.ndarray:
        """Dropout probability at incidence angle ``theta_deg`` (degrees from the normal)."""
        return np.clip((np.asarray(theta_deg, np.float64) - self.grazing_deg) / (90.0 - self.grazing_deg), 0.0, 1.0)

    def apply(self, depth: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The sensor's (H, W) float32 depth for exact planar ``depth`` (+inf/NaN = no surface)
        seen with intrinsics ``K``."""
        z = np.asarray(depth, np.float64)
        H, W = z.shape
        rays = _ray_dirs(K, H, W)                                  # (H, W, 3), z component 1
        surf = np.isfinite(z) & (z > 0)
        zs = np.where(surf, z, 0.0)
        back = np.linalg.norm(rays, axis=2)
        ret = surf & (zs * back <= self.max_range_m)
        edge = _edges(zs, surf, self.edge_jump)
        theta = np.where(edge, 0.0, _incidence_deg(zs[..., None] * rays, rays, surf))
        drop = rng.random((H, W)) < self.grazing_drop_p(theta)
        drop |= edge & (rng.random((H, W)) < self.edge_drop)
        noisy = zs + rng.standard_normal((H, W)) * self.sigma(zs)
        out = np.full((H, W), np.inf if self.no_return == "inf" else np.nan, np.float32)
        keep = ret & ~drop
        out[keep] = np.maximum(noisy[keep], self.min_depth_m)
        return out


def _ray_dirs(K: np.ndarray, H: int, W: int) -> np.ndarray:
    """(H, W, 3) camera-frame rays ``K⁻¹(u + ½, v + ½, 1)`` (RDF, unit planar depth)."""
    K = np.asarray(K, np.float64)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x = (u + 0.5 - K[0, 2]) / K[0, 0]
    y = (v + 0.5 - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=2)


def _incidence_deg(pts: np.ndarray, rays: np.ndarray, surf: np.ndarray) -> np.ndarray:
    """(H, W) angle (degrees) between each pixel's ray and the surface normal estimated from
    the back-projected points ``pts`` (H, W, 3) of its neighbours (central differences);
    0 where the normal cannot be estimated."""
    du = np.gradient(pts, axis=1)
    dv = np.gradient(pts, axis=0)
    n = np.cross(du, dv)
    nn = np.linalg.norm(n, axis=2) * np.linalg.norm(rays, axis=2)
    ok = surf & (nn > 0)
    cos = np.zeros(surf.shape)
    cos[ok] = np.abs(np.einsum("hwc,hwc->hw", n, rays)[ok]) / nn[ok]
    theta = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
    theta[~ok] = 0.0
    return theta


def _edges(z: np.ndarray, surf: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) pixels with a surface whose 4-neighbour differs by more than ``jump · z`` or
    has no surface (image borders have no neighbour there and do not count)."""
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        za, zb, sa, sb = z[tuple(a)], z[tuple(b)], surf[tuple(a)], surf[tuple(b)]
        thr = jump * np.maximum(za, zb)
        diff = (sa != sb) | (sa & sb & (np.abs(za - zb) > thr))
        edge[tuple(a)] |= diff & sa
        edge[tuple(b)] |= diff & sb
    return edge & surf

