"""Per-frame geometry: occupied / free voxels, semantic sample points, out-of-range rays.

Inputs follow the conventions (:mod:`common.conventions`): pose 4×4 camera-to-world with
RDF camera axes, K at depth resolution, planar depth in metres with ``NaN`` = ignore and
``+inf`` = beyond range. Pixel ``(row r, col c)`` looks through ``(c + 0.5, r + 0.5)``.

* **Occupied**: each kept surface pixel gives ``occ_thickness`` samples along its ray at
  planar depths ``d + (k - (n-1)/2) * vox/2``; a voxel holding any occupied sample of the
  frame is occupied (never free in that frame).
* **Free**: every non-NaN pixel ray is traversed exactly (:mod:`semantic_map.traversal`) from the
  camera to its surface, the surface voxel excluded; ``+inf`` pixels carve up to the sensing
  range (planar depth ``range``). With a free budget smaller than the traversal, that many
  points are drawn uniformly along the free segments instead (a random subset of ray
  samples, as the reference's budget does). Without a usable range and without finite depth the
  frame marks only the camera cell free.
* **Rays**: ``isposinf(depth)`` eroded with a (2r+1)² box where pixels outside the image
  count as out of range (unlike the reference's zero padding, border pixels can cast),
  subsampled to ``max_rays``; unit world directions.

Budgets use a caller-provided seeded ``torch.Generator`` (or confidence, descending).

Hot loops (surface samples + de-duplication, free-space traversal, the sampling matrix of
:func:`aggregate_samples`) run in the optional C++ kernels (:mod:`semantic_map.kernels`) with the
same arithmetic as the torch code here, so results are identical with or without them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import numpy as np
import numpy.typing as npt
import torch

from common.conventions import voxel_index
from semantic_map import cell_keys, kernels
from semantic_map.traversal import crossing_counts, unique_cells

#: a frame input: a torch tensor or anything numpy converts to an array (array, nested lists)
ArrayOrTensor = Union[torch.Tensor, npt.ArrayLike]


@dataclass
class FrameGeometry:
    origin: torch.Tensor        # (3,) float64 camera centre
    occ_ijk: torch.Tensor       # (Mo, 3) int64 unique occupied voxels
    free_ijk: torch.Tensor      # (Mf, 3) int64 unique free voxels (disjoint from occ_ijk)
    pts_xyz: torch.Tensor       # (P, 3) float32 surface points (semantic samples)
    pts_pix: torch.Tensor       # (P,) int64 flat pixel index (row * W + col)
    ray_dirs: torch.Tensor      # (R, 3) float32 unit world directions
    ray_pix: torch.Tensor       # (R,) int64 flat pixel index


def _t(x, dtype, device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)


def pixel_directions(K: torch.Tensor, pose: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(H*W, 3) float64 world vectors ``R @ [x, y, 1]`` (planar depth 1) per pixel."""
    dev = K.device
    v, u = torch.meshgrid(torch.arange(h, device=dev, dtype=torch.float64) + 0.5,
                          torch.arange(w, device=dev, dtype=torch.float64) + 0.5, indexing="ij")
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    cam = torch.stack([x.reshape(-1), y.reshape(-1), torch.ones(h * w, dtype=torch.float64, device=dev)], 1)
    return cam @ pose[:3, :3].T


def erode_out_of_range(mask: torch.Tensor, r: int) -> torch.Tensor:
    """Keep pixels whose whole (2r+1)² window is ``True``; outside the image counts as True.

    O(H·W): window counts of the *complement*, separably (row prefix sums, then column
    prefix sums), with whole-row / whole-column gathers only."""
    if r <= 0:
        return mask.clone()
    h, w = mask.shape
    dev = mask.device
    bad = (~mask).to(torch.int32)
    cs = torch.zeros((h, w + 1), dtype=torch.int32, device=dev)
    torch.cumsum(bad, 1, out=cs[:, 1:])
    cols = torch.arange(w, device=dev)
    c0 = (cols - r).clamp(min=0)
    c1 = (cols + r + 1).clamp(max=w)
    row_win = cs.index_select(1, c1) - cs.index_select(1, c0)        # (h, w) bad count per row window
    rs = torch.zeros((h + 1, w), dtype=torch.int32, device=dev)
    torch.cumsum(row_win, 0, out=rs[1:])
    rows = torch.arange(h, device=dev)
    r0 = (rows - r).clamp(min=0)
    r1 = (rows + r + 1).clamp(max=h)
    s = rs.index_select(0, r1) - rs.index_select(0, r0)
    return mask & (s == 0)


def _select(idx: torch.Tensor, budget: int, gen: torch.Generator | None, conf: torch.Tensor | None) -> torch.Tensor:
    if budget < 0 or idx.numel() <= budget:
        return idx
    if conf is not None:
        order = torch.argsort(conf[idx], descending=True, stable=True)
        return idx[order[:budget]]
    perm = torch.randperm(idx.numel(), generator=gen, device="cpu").to(idx.device)
    return idx[perm[:budget]]


def frame_geometry(pose: ArrayOrTensor, K: ArrayOrTensor, depth: ArrayOrTensor, vox: float, *,
                   max_depth_sensing: float = -1.0, occ_thickness: int = 1, max_pts: int = -1,
                   max_empty_pts: int = -1, max_rays: int = -1, ray_erosion: int = 0, want_rays: bool = True,
                   generator: torch.Generator | None = None, confidence: ArrayOrTensor | None = None,
                   free_stride: int = 1, device: str | torch.device = "cpu") -> FrameGeometry:
    """Geometry of one frame (see module docstring). ``max_depth_sensing <= 0`` = unknown
    range: +inf pixels then carve up to the frame's largest finite depth (reference).

    ``free_stride`` k > 1 traverses free space only from every k-th pixel row/column (the
    pixel at each k×k block centre): an approximation for large images; ``-1`` picks the
    largest k whose neighbouring rays stay within vox/2 of each other at the range."""
    dev = torch.device(device)
    pose_t = _t(pose, torch.float64, dev)
    K_t = _t(K, torch.float64, dev)
    d = _t(depth, torch.float32, dev)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {tuple(d.shape)}")
    if pose_t.shape != (4, 4) or K_t.shape != (3, 3):
        raise ValueError("pose must be 4x4 and intrinsics 3x3")
    h, w = d.shape
    conf = None if confidence is None else _t(confidence, torch.float32, dev).reshape(-1)
    flat = d.reshape(-1)
    origin = pose_t[:3, 3].clone()
    finite = torch.isfinite(flat) & (flat > 0)
    posinf = torch.isposinf(flat)
    rng = float(max_depth_sensing)
    if rng <= 0:
        rng = float(flat[finite].max()) if bool(finite.any()) else -1.0
    need_dirs = bool(finite.any()) or bool(posinf.any())
    D = pixel_directions(K_t, pose_t, h, w) if need_dirs else None

    occ_pix, pts, occ_ijk = _occupied_samples(origin, D, flat, finite, vox, occ_thickness, max_pts, generator,
                                              conf, dev)
    ray_idx = _free_space_pixels(finite, posinf, rng, K_t, vox, (h, w), free_stride, dev)
    free_ijk = _free_cells(origin, D, flat, ray_idx, rng, vox, max_empty_pts, generator, dev)
    if occ_ijk.numel() and free_ijk.numel():
        free_ijk = free_ijk[~torch.isin(cell_keys.pack(free_ijk), cell_keys.pack(occ_ijk))]
    rpix, dirs = _out_of_range_rays(D, posinf, (h, w), want_rays, ray_erosion, max_rays, generator, conf, dev)
    return FrameGeometry(origin, occ_ijk, free_ijk, pts, occ_pix, dirs, rpix)


def _occupied_samples(origin: torch.Tensor, D: torch.Tensor | None, flat: torch.Tensor, finite: torch.Tensor,
                      vox: float, occ_thickness: int, max_pts: int, generator: torch.Generator | None,
                      conf: torch.Tensor | None, dev: torch.device
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(occ_pix, pts_xyz, occ_ijk)``: the kept surface pixels (budget ``max_pts``), their
    surface points and the unique voxels of their ``occ_thickness`` samples along the ray."""
    occ_pix = _select(torch.nonzero(finite).squeeze(1), max_pts, generator, conf)
    if not occ_pix.numel():
        return (occ_pix, torch.empty((0, 3), dtype=torch.float32, device=dev),
                torch.empty((0, 3), dtype=torch.int64, device=dev))
    assert D is not None  # there are finite pixels, so the directions were computed
    offs = (torch.arange(occ_thickness, dtype=torch.float64, device=dev) - (occ_thickness - 1) / 2) * (vox / 2)
    if kernels.enabled(D, flat):  # same float64 operations in C++, hashed de-duplication
        pts, okeys = kernels.surface_samples(origin, D, flat, occ_pix, offs, vox)
    else:
        z = flat[occ_pix].to(torch.float64)
        Dp = D[occ_pix]
        pts = (origin + Dp * z[:, None]).to(torch.float32)
        zs = z[:, None] + offs[None, :]
        samples = origin + Dp[:, None, :] * zs[..., None]
        samples = samples[zs > 0]
        okeys = torch.unique(cell_keys.pack(voxel_index(samples, vox)))  # 1-D unique: fast
    return occ_pix, pts, cell_keys.unpack(okeys)


def _free_space_pixels(finite: torch.Tensor, posinf: torch.Tensor, rng: float, K_t: torch.Tensor, vox: float,
                       hw: tuple[int, int], free_stride: int, dev: torch.device) -> torch.Tensor:
    """Flat indices of the pixels whose rays carve free space: finite depth, +inf too with a
    usable range, thinned to every ``free_stride``-th row/column (``-1`` = auto)."""
    h, w = hw
    if rng > 0:
        cand = finite | posinf
    else:
        cand = finite
    if free_stride < 0:
        spacing = (rng if rng > 0 else 1.0) / float(min(K_t[0, 0], K_t[1, 1]))
        free_stride = max(1, int((vox / 2) / spacing))
    if free_stride > 1:
        rr = torch.arange(h, device=dev) % free_stride == free_stride // 2
        cc = torch.arange(w, device=dev) % free_stride == free_stride // 2
        cand = cand & (rr[:, None] & cc[None, :]).reshape(-1)
    return torch.nonzero(cand).squeeze(1)


def _free_cells(origin: torch.Tensor, D: torch.Tensor | None, flat: torch.Tensor, ray_idx: torch.Tensor, rng: float,
                vox: float, max_empty_pts: int, generator: torch.Generator | None,
                dev: torch.device) -> torch.Tensor:
    """Unique free voxels of the rays through pixels ``ray_idx`` (exact traversal, or
    ``max_empty_pts`` samples when the traversal is larger), the camera's own cell included."""
    cam_ijk = voxel_index(origin[None], vox)
    if not ray_idx.numel():
        return cam_ijk
    assert D is not None  # there are finite or +inf pixels, so the directions were computed
    z = flat[ray_idx].to(torch.float64)
    surf = torch.isfinite(z)
    zend = torch.where(surf, z, torch.full_like(z, rng))
    if rng > 0:
        zend = torch.minimum(zend, torch.full_like(zend, rng))
    excl = surf & (z <= zend)
    dirs_f = D[ray_idx]
    ends = origin + dirs_f * zend[:, None]
    total = int(crossing_counts(origin.expand_as(ends), ends, vox).sum()) if max_empty_pts >= 0 else 0
    if 0 <= max_empty_pts < total:
        free_ijk = _sampled_free_cells(origin, dirs_f, zend, ends, excl, vox, max_empty_pts, generator, dev)
    else:
        free_ijk = unique_cells(origin.expand_as(ends), ends, vox, exclude_end=excl)
    if not bool((free_ijk == cam_ijk).all(1).any()):  # the camera's own cell is free
        free_ijk = torch.cat([free_ijk, cam_ijk])
    return free_ijk


def _sampled_free_cells(origin: torch.Tensor, dirs_f: torch.Tensor, zend: torch.Tensor, ends: torch.Tensor,
                        excl: torch.Tensor, vox: float, max_empty_pts: int, generator: torch.Generator | None,
                        dev: torch.device) -> torch.Tensor:
    """Budget: ``max_empty_pts`` free samples drawn uniformly along the free segments
    (length-weighted), i.e. a random subset of ray samples as in the reference; their unique
    voxels, an excluded surface voxel dropped."""
    if max_empty_pts <= 0:
        return torch.empty((0, 3), dtype=torch.int64, device=dev)
    ri = torch.multinomial(zend.to(torch.float32), max_empty_pts, replacement=True, generator=generator).to(dev)
    tt = torch.rand(max_empty_pts, generator=generator, dtype=torch.float64).to(dev) * zend[ri]
    sijk = voxel_index(origin + dirs_f[ri] * tt[:, None], vox)
    eijk = voxel_index(ends[ri], vox)
    sijk = sijk[~(excl[ri] & (sijk == eijk).all(1))]
    return cell_keys.unpack(torch.unique(cell_keys.pack(sijk)))


def _out_of_range_rays(D: torch.Tensor | None, posinf: torch.Tensor, hw: tuple[int, int], want_rays: bool,
                       ray_erosion: int, max_rays: int, generator: torch.Generator | None,
                       conf: torch.Tensor | None, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ray_pix, unit float32 directions)`` of the eroded +inf pixels (budget ``max_rays``);
    empty unless ``want_rays``."""
    if want_rays and bool(posinf.any()):
        assert D is not None  # there are +inf pixels, so the directions were computed
        m = erode_out_of_range(posinf.reshape(*hw), ray_erosion).reshape(-1)
        rpix = _select(torch.nonzero(m).squeeze(1), max_rays, generator, conf)
        dirs = D[rpix]
        return rpix, (dirs / dirs.norm(dim=1, keepdim=True)).to(torch.float32)
    return (torch.empty(0, dtype=torch.int64, device=dev),
            torch.empty((0, 3), dtype=torch.float32, device=dev))


def sample_image(img: torch.Tensor, pix: torch.Tensor, hw: tuple[int, int], mode: str = "bilinear") -> torch.Tensor:
    """Sample a (C, h, w) map at the centres of flat pixels ``pix`` of an (H, W) image.

    Pixel centre ``(c + 0.5, r + 0.5)`` maps to ``(c + 0.5) * w / W - 0.5`` in the map's
    pixel coordinates (align_corners=False); bilinear with edge clamping, or nearest.
    Only the requested pixels are computed (no full-resolution upsampling). Returns
    (P, C) float32."""
    C, h, w = img.shape
    idx, wt = _corners(pix, hw, h, w, mode)
    tab = img.reshape(C, h * w).T  # (h*w, C) view
    if h * w <= idx.numel():  # small map: one contiguous float32 copy, then row gathers (same values)
        tab = tab.to(torch.float32).contiguous()
    out = tab[idx[:, 0]].to(torch.float32) * wt[:, :1]
    for k in range(1, idx.shape[1]):
        out += tab[idx[:, k]].to(torch.float32) * wt[:, k:k + 1]
    return out


def _corners(pix: torch.Tensor, hw: tuple[int, int], h: int, w: int, mode: str):
    """Flat source-pixel indices (P, k) and weights (P, k) for sampling at pixel centres."""
    H, W = hw
    r = torch.div(pix, W, rounding_mode="floor")
    c = pix - r * W
    x = (c.to(torch.float32) + 0.5) * (w / W) - 0.5
    y = (r.to(torch.float32) + 0.5) * (h / H) - 0.5
    if mode == "nearest" or (h == H and w == W):
        xi = torch.floor(x + 0.5).clamp(0, w - 1).to(torch.int64)
        yi = torch.floor(y + 0.5).clamp(0, h - 1).to(torch.int64)
        return (yi * w + xi)[:, None], torch.ones((pix.numel(), 1), dtype=torch.float32, device=pix.device)
    x = x.clamp(0, w - 1)
    y = y.clamp(0, h - 1)
    x0 = torch.floor(x).to(torch.int64)
    y0 = torch.floor(y).to(torch.int64)
    x1 = (x0 + 1).clamp(max=w - 1)
    y1 = (y0 + 1).clamp(max=h - 1)
    fx = x - x0.to(torch.float32)
    fy = y - y0.to(torch.float32)
    idx = torch.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], 1)
    wt = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    return idx, wt


def aggregate_samples(img: torch.Tensor, pix: torch.Tensor, hw: tuple[int, int], group: torch.Tensor,
                      n_groups: int, mode: str = "bilinear", max_dense: int = 1 << 24) -> torch.Tensor:
    """Per-group sums of ``img`` (C, h, w) sampled at flat pixels ``pix`` of an (H, W) image:
    ``out[g] = sum_{p: group[p] = g} sample(img, pix[p])`` as (G, C) float32.

    Because sampling is linear in the source pixels, the sum is ``A @ img_pixels`` with a
    sparse (G × h·w) weight matrix ``A``; it is built with one bincount over the P·4
    (point, corner) weights, so the C-channel work is proportional to the non-zeros of A
    (few per voxel when features are coarser than depth), not to P·C."""
    C, h, w = img.shape
    # non-zeros of A (C++ kernel when available, else a dense bincount when A is small)
    if kernels.enabled(pix, group):
        g, src, gw = kernels.sample_pairs(group, pix, hw, h, w, mode, n_groups)
    else:
        idx, wt = _corners(pix, hw, h, w, mode)
        g, src, gw = kernels.group_pairs(group, idx, wt, n_groups, h * w, max_dense)
    out = torch.zeros((n_groups, C), dtype=torch.float32, device=pix.device)
    out.index_add_(0, g, img.reshape(C, h * w).T[src].to(torch.float32) * gw[:, None])
    return out
