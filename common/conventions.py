"""Conventions shared by every part (docs/conventions.md), in one place.

* Pose: 4×4 **camera-to-world**, camera axes **OpenCV RDF** (x right, y down, z forward).
* World: gravity-aligned where the source allows it, **z up** (ENU-like: x east, y north).
  Ray angle bins are defined on these world axes.
* Depth: planar z in metres. ``NaN`` = no measurement (ignored). ``+inf`` = beyond range:
  carves free space up to the sensing range and is the only source of semantic rays.
  ``-inf``, ``0`` and negative values are "no measurement" and become ``NaN`` at the source.
* Intrinsics: 3×3 at the depth image's resolution. Image sizes are ``(height, width)``.
* Voxel index: ``floor(xyz / vox)``: :func:`voxel_index` in Python; the C++ kernels
  (semantic_map/csrc) apply the same floor and are tested equal to it.

Axis conventions are named by three letters, one per axis, for the direction the
positive axis points: R/L (right/left), U/D (up/down), F/B (forward/backward) for bodies
and E/W, N/S, U/D for worlds. Conversions from other conventions (ROS FLU bodies, NED
worlds with FRD bodies) happen once, at the source, with the functions below. Unlike the
reference implementation (which conjugates the whole pose and so rotates the world too),
:func:`convert_pose` re-expresses the body and the world separately, so a NED source
still yields a z-up world.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeGuard, overload

import numpy as np

if TYPE_CHECKING:
    import torch
    from numpy.typing import ArrayLike

# Unit vectors of each axis letter, in a common "physical" frame used only to build the
# signed permutation matrices: body letters (R, D, F) and world letters (E, N, U).
_BODY_LETTERS = {
    "R": (1, 0, 0), "L": (-1, 0, 0),
    "D": (0, 1, 0), "U": (0, -1, 0),
    "F": (0, 0, 1), "B": (0, 0, -1),
}
_WORLD_LETTERS = {
    "E": (1, 0, 0), "W": (-1, 0, 0),
    "N": (0, 1, 0), "S": (0, -1, 0),
    "U": (0, 0, 1), "D": (0, 0, -1),
}


def _axes(conv: str, letters: dict) -> np.ndarray:
    conv = conv.upper()
    if len(conv) != 3 or any(c not in letters for c in conv):
        raise ValueError(f"unknown axis convention {conv!r}; use three of {''.join(letters)}")
    m = np.array([letters[c] for c in conv], dtype=np.float64)  # rows: axes in physical frame
    if abs(np.linalg.det(m)) != 1.0:
        raise ValueError(f"axis convention {conv!r} repeats an axis")
    return m


def body_axes_matrix(src: str, dst: str = "RDF") -> np.ndarray:
    """3×3 matrix M with ``v_dst = M @ v_src`` for a vector in body (camera) axes."""
    a, b = _axes(src, _BODY_LETTERS), _axes(dst, _BODY_LETTERS)
    return b @ a.T


def world_axes_matrix(src: str, dst: str = "ENU") -> np.ndarray:
    """3×3 matrix M with ``v_dst = M @ v_src`` for a vector in world axes."""
    a, b = _axes(src, _WORLD_LETTERS), _axes(dst, _WORLD_LETTERS)
    return b @ a.T


def convert_pose(pose: np.ndarray, body: str = "RDF", world: str = "ENU") -> np.ndarray:
    """Camera-to-world pose with body axes ``body`` in a world with axes ``world`` →
    the same physical pose with an RDF body in an ENU (z-up) world.

    ``P' = W · P · B⁻¹`` with ``W`` the world re-expression and ``B`` mapping RDF body
    vectors to ``body`` vectors (so ``B⁻¹`` maps them back)."""
    pose = np.asarray(pose, dtype=np.float64)
    w = np.eye(4)
    w[:3, :3] = world_axes_matrix(world, "ENU")
    b = np.eye(4)
    b[:3, :3] = body_axes_matrix("RDF", body)  # RDF vector -> body vector
    return w @ pose @ b


def is_rigid(pose: ArrayLike, tol: float = 1e-3) -> bool:
    """True if ``pose`` is a finite 4×4 rigid transform (proper rotation, last row 0001)."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (4, 4) or not np.all(np.isfinite(p)):
        return False
    r = p[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=tol):
        return False
    if abs(np.linalg.det(r) - 1.0) > tol:
        return False
    return bool(np.allclose(p[3], [0, 0, 0, 1], atol=tol))


def _is_torch(x: Any) -> TypeGuard[torch.Tensor]:
    return type(x).__module__.startswith("torch")


@overload
def voxel_index(xyz: torch.Tensor, vox: float) -> torch.Tensor: ...
@overload
def voxel_index(xyz: np.ndarray, vox: float) -> np.ndarray: ...
def voxel_index(xyz: np.ndarray | torch.Tensor, vox: float) -> np.ndarray | torch.Tensor:
    """Integer voxel index ``floor(xyz / vox)`` (int64), for numpy arrays or torch tensors.

    Inserts, queries, pruning and ray tracing in Python all call it; the C++ kernels use
    the same floor (tests/test_mapper_perf_kernels.py holds them equal)."""
    if vox <= 0:
        raise ValueError(f"voxel size must be > 0, got {vox}")
    if _is_torch(xyz):
        import torch

        return torch.floor(xyz / vox).to(torch.int64)
    return np.floor(np.asarray(xyz) / vox).astype(np.int64)


@overload
def voxel_center(ijk: torch.Tensor, vox: float) -> torch.Tensor: ...
@overload
def voxel_center(ijk: np.ndarray, vox: float) -> np.ndarray: ...
def voxel_center(ijk: np.ndarray | torch.Tensor, vox: float) -> np.ndarray | torch.Tensor:
    """World centre of voxel ``ijk``: ``(ijk + 0.5) * vox`` (float32 for torch, float64 numpy)."""
    if _is_torch(ijk):
        import torch

        return (ijk.to(torch.float32) + 0.5) * vox
    return (np.asarray(ijk, dtype=np.float64) + 0.5) * vox


@overload
def sanitize_depth(depth: torch.Tensor, depth_limit: float | None = None) -> torch.Tensor: ...
@overload
def sanitize_depth(depth: np.ndarray, depth_limit: float | None = None) -> np.ndarray: ...
def sanitize_depth(depth: np.ndarray | torch.Tensor,
                   depth_limit: float | None = None) -> np.ndarray | torch.Tensor:
    """Apply the depth conventions: ``-inf``/``<=0`` → NaN; finite values above
    ``depth_limit`` (if given, >0) → ``+inf`` (simulates a shorter sensor). A limit of 0
    turns every finite value into ``+inf`` (the paper's 0 m setting). Returns float32."""
    if _is_torch(depth):
        import torch

        d = depth.to(torch.float32).clone()
        d[(d <= 0) | torch.isneginf(d)] = float("nan")
        if depth_limit is not None and depth_limit >= 0:
            d[torch.isfinite(d) & (d > depth_limit)] = float("inf")
        return d
    a = np.array(depth, dtype=np.float32, copy=True)
    with np.errstate(invalid="ignore"):
        a[(a <= 0) | np.isneginf(a)] = np.nan
        if depth_limit is not None and depth_limit >= 0:
            a[np.isfinite(a) & (a > depth_limit)] = np.inf
    return a
