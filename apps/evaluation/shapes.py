"""Search-volume shapes of the online benchmark, rasterised on voxel centres.

* ``true`` cones: :func:`semantic_map.search_volume.cone_membership_counts` (half-angle α, apex at
  the ray origin, infinite).
* ``reference`` "cones" (docs/method.md#evaluation): the reference evaluation's six-sided open
  pyramid. Local frame: +z along the ray, x/y from the Rodrigues rotation taking +z to the
  ray direction (roll as the reference's ``rays_to_pose_4x4``). Its side faces pass through a
  hexagon of circumradius ``r₀ = vox·s`` at ``z = vox`` and one of circumradius
  ``5·vox·tan α`` at ``z = 5·vox`` (hexagon vertices at angles 2πk/6 in local x/y); near
  plane ``z = vox`` kept, far plane dropped. A point is inside when ``z >= vox`` and its
  local (x, y) lies in the hexagon of radius ``r(z)`` (:func:`metrics.reference_cone_radius`).
* balls around ray-bearing frontiers (Spherical Semantic Frontiers):
  :func:`semantic_map.search_volume.ball_membership_counts` with radii from
  :func:`semantic_map.search_volume.frontier_ball_radii`.

All functions take (V, 3) voxel centres in metres and return (V,) int64 counts.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import torch

from semantic_map import search_volume

if TYPE_CHECKING:
    from semantic_map.depth_geometry import ArrayOrTensor


def rotation_z_to(dirs: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotations taking +z to each unit direction (Rodrigues about z × d; the
    identity for d = +z, a rotation by π about x for d = −z)."""
    d = torch.nn.functional.normalize(torch.as_tensor(dirs, dtype=torch.float64), dim=1)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(d)
    v = torch.linalg.cross(z, d)
    c = d[:, 2]
    s = v.norm(dim=1)
    n = d.shape[0]
    R = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    vx = torch.zeros((n, 3, 3), dtype=torch.float64)
    vx[:, 0, 1], vx[:, 0, 2] = -v[:, 2], v[:, 1]
    vx[:, 1, 0], vx[:, 1, 2] = v[:, 2], -v[:, 0]
    vx[:, 2, 0], vx[:, 2, 1] = -v[:, 1], v[:, 0]
    k = torch.where(s > 1e-12, (1 - c) / (s * s).clamp_min(1e-24), torch.zeros_like(c))
    R = R + vx + vx @ vx * k[:, None, None]
    flip = (s <= 1e-12) & (c < 0)
    if flip.any():
        R[flip] = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]], dtype=torch.float64)
    return R


def reference_pyramid_tests(origins: ArrayOrTensor, dirs: ArrayOrTensor, vox: float, subsampling: float,
                            half_angle_deg: float, num_segs: int = 6
                            ) -> tuple[search_volume.BlockTest, search_volume.ExactTest]:
    """(block_test, exact_test) for :func:`semantic_map.search_volume.membership_counts`."""
    o = torch.as_tensor(origins, dtype=torch.float64).reshape(-1, 3)
    R = rotation_z_to(torch.as_tensor(dirs, dtype=torch.float64).reshape(-1, 3))
    r0 = vox * subsampling
    slope = (5 * vox * math.tan(math.radians(half_angle_deg)) - r0) / (4 * vox)
    ang = 2 * math.pi * (torch.arange(num_segs, dtype=torch.float64) + 0.5) / num_segs
    normals = torch.stack([torch.cos(ang), torch.sin(ang)], 1)      # face normals (apothem directions)
    apo = math.cos(math.pi / num_segs)                                # apothem / circumradius

    def local(x: torch.Tensor, si: torch.Tensor) -> torch.Tensor:
        v = x - o[si]
        return torch.einsum("nji,nj->ni", R[si], v)                    # R^T v

    def exact_test(x: torch.Tensor, si: torch.Tensor) -> torch.Tensor:
        p = local(x, si)
        r = r0 + (p[:, 2] - vox) * slope
        inside = (p[:, :2] @ normals.T <= (r * apo)[:, None] + 1e-12).all(1)
        return inside & (p[:, 2] >= vox)

    def block_test(bc: torch.Tensor, rho: float, sidx: torch.Tensor) -> torch.Tensor:
        v = bc[:, None, :] - o[sidx][None]                            # (B, S, 3)
        p = torch.einsum("sji,bsj->bsi", R[sidx], v)
        z = p[..., 2]
        rad = p[..., :2].norm(dim=2)
        rmax = torch.maximum(r0 + (z - rho - vox) * slope, r0 + (z + rho - vox) * slope)
        return (z + rho >= vox) & (rad <= rmax + rho) & (rmax + rho >= 0)

    return block_test, exact_test


def reference_cone_counts(voxel_centres: ArrayOrTensor, origins: ArrayOrTensor, dirs: ArrayOrTensor, vox: float,
                          subsampling: float, half_angle_deg: float, num_segs: int = 6) -> torch.Tensor:
    """(V,) number of reference pyramids (see module doc) holding each voxel centre."""
    bt, et = reference_pyramid_tests(origins, dirs, vox, subsampling, half_angle_deg, num_segs)
    n = int(torch.as_tensor(origins).reshape(-1, 3).shape[0])
    return search_volume.membership_counts(torch.as_tensor(voxel_centres, dtype=torch.float64), n, bt, et)


def cone_counts(voxel_centres: ArrayOrTensor, origins: ArrayOrTensor, dirs: ArrayOrTensor,
                half_angle_deg: float) -> torch.Tensor:
    """(V,) number of true cones of ``half_angle_deg`` holding each voxel centre."""
    return search_volume.cone_membership_counts(torch.as_tensor(voxel_centres, dtype=torch.float64), origins, dirs,
                                                half_angle_deg)


def ball_counts(voxel_centres: ArrayOrTensor, centres: ArrayOrTensor, radii: ArrayOrTensor | float) -> torch.Tensor:
    """(V,) number of balls holding each voxel centre."""
    return search_volume.ball_membership_counts(torch.as_tensor(voxel_centres, dtype=torch.float64), centres, radii)


def brute_force_reference_inside(points: np.ndarray, origin: npt.ArrayLike, direction: npt.ArrayLike, vox: float,
                                 subsampling: float, half_angle_deg: float, num_segs: int = 6) -> np.ndarray:
    """Independent half-space construction of one reference pyramid (for tests): the
    planes through consecutive hexagon vertices at ``z = vox`` and ``z = 5·vox`` (plus the
    near plane), inside = on the inner side of every plane."""
    R = rotation_z_to(torch.as_tensor(np.asarray(direction, dtype=np.float64)[None]))[0].numpy()
    o = np.asarray(origin, dtype=np.float64)
    r0 = vox * subsampling
    r5 = 5 * vox * math.tan(math.radians(half_angle_deg))
    a = 2 * math.pi * np.arange(num_segs) / num_segs
    near = np.stack([r0 * np.cos(a), r0 * np.sin(a), np.full(num_segs, vox)], 1)
    far = np.stack([r5 * np.cos(a), r5 * np.sin(a), np.full(num_segs, 5 * vox)], 1)
    p = (np.asarray(points, dtype=np.float64) - o) @ R                # local coordinates
    inside = p[:, 2] >= vox
    axis_pt = np.array([0.0, 0.0, vox])
    for k in range(num_segs):
        a0, a1, b0 = near[k], near[(k + 1) % num_segs], far[k]
        n = np.cross(a1 - a0, b0 - a0)
        if np.dot(axis_pt - a0, n) < 0:
            n = -n
        inside &= (p - a0) @ n >= -1e-9
    return inside
