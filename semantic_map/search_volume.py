"""Search volumes from semantic rays: true cones and frontier balls rasterised on voxels.

A cone ``(o, d, alpha)`` holds point ``x`` when ``t = (x - o)·d`` satisfies
``near <= t <= far`` and the angle between ``x - o`` and ``d`` is at most ``alpha``
(``t >= |x - o| cos(alpha)``). A ball ``(c, r)`` holds ``x`` when ``|x - c| <= r``.

Rasterisation (:func:`membership_counts`) groups the candidate voxels into cubic blocks,
tests every shape against each block's bounding sphere (conservative), and runs the exact
per-voxel test only for the surviving (block, shape) pairs, in chunks. Other shapes (e.g.
the reference's hexagonal pyramids, docs/method.md#evaluation) plug in through ``block_test`` /
``exact_test`` callables — that is the hook the evaluation uses.

``half_angle_deg`` default in the map: the config's ``cone_half_angle_deg``, or max(FoV)/2
(the paper's reasoning: an out-of-range pixel's object lies somewhere in the camera view).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import torch

if TYPE_CHECKING:
    from semantic_map.depth_geometry import ArrayOrTensor

# (B,3) centres, radius, shape idx (S,) -> (B,S) bool
BlockTest = Callable[[torch.Tensor, float, torch.Tensor], torch.Tensor]
ExactTest = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]          # (P,3) points, shape idx (P,) -> (P,) bool


def _blocks(x: torch.Tensor, block: float | None, target: int = 256
            ) -> tuple[torch.Tensor, float, torch.Tensor, torch.Tensor, torch.Tensor]:
    lo = x.min(0).values
    hi = x.max(0).values
    if block is None:
        vol = float((hi - lo).clamp_min(1e-6).prod())
        block = max((vol * target / max(1, x.shape[0])) ** (1 / 3), 1e-6)
    bi = torch.floor((x - lo) / block).to(torch.int64)
    ext = bi.max(0).values + 1
    key = (bi[:, 0] * ext[1] + bi[:, 1]) * ext[2] + bi[:, 2]
    uk, inv, cnt = torch.unique(key, return_inverse=True, return_counts=True)
    order = torch.argsort(inv, stable=True)
    start = torch.cumsum(cnt, 0) - cnt
    bk = torch.stack([uk // (ext[1] * ext[2]), (uk // ext[2]) % ext[1], uk % ext[2]], 1)
    centres = lo + (bk.to(x.dtype) + 0.5) * block
    radius = block * math.sqrt(3) / 2
    return centres, radius, order, start, cnt


def membership_counts(points: ArrayOrTensor, n_shapes: int, block_test: BlockTest, exact_test: ExactTest,
                      weights: torch.Tensor | None = None, block: float | None = None,
                      chunk: int = 1 << 22) -> torch.Tensor:
    """(V,) number of shapes (or sum of shape ``weights``) containing each point."""
    x = torch.as_tensor(points).to(torch.float64)
    V = x.shape[0]
    out = torch.zeros(V, dtype=torch.float64 if weights is not None else torch.int64)
    if V == 0 or n_shapes == 0:
        return out
    bc, rad, order, start, cnt = _blocks(x, block)
    nb = bc.shape[0]
    sh_step = max(1, chunk // max(1, nb))
    for s0 in range(0, n_shapes, sh_step):
        sidx = torch.arange(s0, min(n_shapes, s0 + sh_step))
        hit = block_test(bc, rad, sidx)  # (nb, S)
        b, s = torch.nonzero(hit, as_tuple=True)
        if b.numel() == 0:
            continue
        s = sidx[s]
        n = cnt[b]
        # expand (block, shape) pairs to (voxel, shape) in chunks of `chunk` pairs
        csum = torch.cumsum(n, 0)
        lo = 0
        while lo < b.numel():
            base = csum[lo - 1] if lo > 0 else 0
            hi = int(torch.searchsorted(csum, base + chunk, right=True))
            hi = max(hi, lo + 1)
            bb, ss, nn = b[lo:hi], s[lo:hi], n[lo:hi]
            tot = int(nn.sum())
            ps = torch.repeat_interleave(ss, nn)
            st = torch.repeat_interleave(start[bb] - (torch.cumsum(nn, 0) - nn), nn)
            vi = order[torch.arange(tot) + st]
            ok = exact_test(x[vi], ps)
            if weights is None:
                out.index_add_(0, vi[ok], torch.ones(int(ok.sum()), dtype=torch.int64))
            else:
                out.index_add_(0, vi[ok], torch.as_tensor(weights, dtype=torch.float64)[ps[ok]])
            lo = hi
    return out


def cone_tests(origins: ArrayOrTensor, dirs: ArrayOrTensor, half_angle_deg: float, near: float = 0.0,
               far: float = math.inf) -> tuple[BlockTest, ExactTest]:
    """``(block_test, exact_test)`` of the cones ``(origins, dirs, half_angle_deg)`` cut to
    ``near <= t <= far`` (see :func:`membership_counts`)."""
    o = torch.as_tensor(origins).to(torch.float64)
    d = torch.nn.functional.normalize(torch.as_tensor(dirs).to(torch.float64), dim=1)
    a = math.radians(half_angle_deg)
    ca = math.cos(a)

    def block_test(bc: torch.Tensor, rho: float, sidx: torch.Tensor) -> torch.Tensor:
        v = bc[:, None, :] - o[sidx][None]            # (B, S, 3)
        L = v.norm(dim=2)
        t = (v * d[sidx][None]).sum(2)
        cos_t = t / L.clamp_min(1e-12)
        ang = torch.acos(cos_t.clamp(-1, 1))
        spread = torch.asin((rho / L.clamp_min(1e-12)).clamp(max=1.0))
        inside = (L <= rho) | (ang <= a + spread)
        return inside & (t + rho >= near) & (t - rho <= far)

    def exact_test(x: torch.Tensor, si: torch.Tensor) -> torch.Tensor:
        v = x - o[si]
        t = (v * d[si]).sum(1)
        return (t >= near) & (t <= far) & (t >= v.norm(dim=1) * ca)

    return block_test, exact_test


def cone_membership_counts(voxel_centres: ArrayOrTensor, origins: ArrayOrTensor, dirs: ArrayOrTensor,
                           half_angle_deg: float, near: float = 0.0, far: float = math.inf,
                           weights: torch.Tensor | None = None, block: float | None = None,
                           chunk: int = 1 << 22) -> torch.Tensor:
    """(V,) number of cones (or sum of their ``weights``) containing each voxel centre."""
    bt, et = cone_tests(origins, dirs, half_angle_deg, near, far)
    return membership_counts(voxel_centres, int(torch.as_tensor(origins).shape[0]), bt, et, weights, block, chunk)


def ball_membership_counts(voxel_centres: ArrayOrTensor, centres: ArrayOrTensor, radii: ArrayOrTensor | float,
                           weights: torch.Tensor | None = None, block: float | None = None,
                           chunk: int = 1 << 22) -> torch.Tensor:
    """(V,) number of balls ``(centres (B, 3), radii (B,) or scalar)`` containing each voxel centre."""
    c = torch.as_tensor(centres).to(torch.float64)
    r = torch.as_tensor(radii, dtype=torch.float64)
    if r.ndim == 0:
        r = r.expand(c.shape[0])

    def block_test(bc: torch.Tensor, rho: float, sidx: torch.Tensor) -> torch.Tensor:
        return (bc[:, None, :] - c[sidx][None]).norm(dim=2) <= r[sidx][None] + rho

    def exact_test(x: torch.Tensor, si: torch.Tensor) -> torch.Tensor:
        return (x - c[si]).norm(dim=1) <= r[si]

    return membership_counts(voxel_centres, c.shape[0], block_test, exact_test, weights, block, chunk)


def frontier_ball_radii(centres: torch.Tensor, default: float) -> torch.Tensor:
    """Spherical baseline: radius = distance to the nearest other centre, ``default`` if alone."""
    c = torch.as_tensor(centres).to(torch.float64)
    if c.shape[0] < 2:
        return torch.full((c.shape[0],), float(default), dtype=torch.float64)
    out = torch.empty(c.shape[0], dtype=torch.float64)
    for s in range(0, c.shape[0], 4096):
        d = torch.cdist(c[s:s + 4096], c)
        d[torch.arange(d.shape[0]), torch.arange(s, s + d.shape[0])] = math.inf
        out[s:s + 4096] = d.min(1).values
    return out


def search_volume_mask(counts: torch.Tensor, thresh: float = 0.05) -> torch.Tensor:
    """Voxels whose count normalised by the maximum count exceeds ``thresh`` (paper: 0.05)."""
    c = counts.to(torch.float64)
    mx = float(c.max()) if c.numel() else 0.0
    if mx <= 0:
        return torch.zeros(c.shape, dtype=torch.bool)
    return c / mx > thresh
