"""Depth geometry and exact voxel traversal vs independent brute force."""
import numpy as np
import torch

from common.conventions import voxel_index
from common.geometry import intrinsics_from_fov, look_at
from semantic_map.depth_geometry import aggregate_samples, erode_out_of_range, frame_geometry, sample_image
from semantic_map.traversal import segment_cells, unique_cells


def _slab_cells(o, e, vox, exclude_end=False):
    """Exact brute force: every voxel of the segment's bbox whose box the segment [o, e) hits
    with positive length (float64 slab test)."""
    lo = np.floor(np.minimum(o, e) / vox).astype(int) - 1
    hi = np.floor(np.maximum(o, e) / vox).astype(int) + 1
    g = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)], indexing="ij"),
                 -1).reshape(-1, 3)
    bmin, bmax = g * vox, (g + 1) * vox
    d = e - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (bmin - o) / d
        t2 = (bmax - o) / d
    tmin = np.where(d == 0, np.where((o >= bmin) & (o < bmax), -np.inf, np.inf), np.minimum(t1, t2))
    tmax = np.where(d == 0, np.where((o >= bmin) & (o < bmax), np.inf, -np.inf), np.maximum(t1, t2))
    a = np.maximum(tmin.max(1), 0.0)
    b = np.minimum(tmax.min(1), 1.0)
    cells = {tuple(c) for c in g[b - a > 1e-9]}
    cells.add(tuple(np.floor(o / vox).astype(int)))
    if exclude_end:
        cells.discard(tuple(np.floor(e / vox).astype(int)))
    return cells


def test_traversal_matches_slab_bruteforce():
    rng = np.random.default_rng(0)
    for vox in (0.3, 1.0):
        o = rng.uniform(-3, 3, (60, 3))
        e = o + rng.normal(size=(60, 3)) * rng.uniform(0.1, 8, (60, 1))
        rid, ijk = segment_cells(torch.tensor(o), torch.tensor(e), vox, chunk=97)
        for i in range(60):
            got = {tuple(c) for c in ijk[rid == i].tolist()}
            assert len(got) == int((rid == i).sum())  # each cell once per segment
            assert got == _slab_cells(o[i], e[i], vox), i


def test_unique_cells_dense_and_sparse_paths_agree():
    rng = np.random.default_rng(1)
    o = torch.tensor(rng.uniform(-1, 1, (40, 3)))
    e = o + torch.tensor(rng.normal(size=(40, 3)) * 5)
    excl = torch.tensor(rng.uniform(size=40) < 0.5)
    a = unique_cells(o, e, 0.4, exclude_end=excl)
    b = unique_cells(o, e, 0.4, exclude_end=excl, max_dense=0)
    assert torch.equal(a, b)


def _frame(h=12, w=16, seed=0):
    rng = np.random.default_rng(seed)
    K = intrinsics_from_fov(80, h, w)
    pose = look_at([0.3, -0.2, 1.1], [5, 1, 0.8])
    depth = rng.uniform(0.5, 6, (h, w)).astype(np.float32)
    depth[rng.uniform(size=(h, w)) < 0.2] = np.inf
    depth[rng.uniform(size=(h, w)) < 0.1] = np.nan
    return pose, K, depth


def _unproject(pose, K, h, w, z):
    v, u = np.mgrid[0:h, 0:w] + 0.5
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    return pose[:3, 3] + (cam * z.reshape(-1, 1)) @ pose[:3, :3].T


def test_frame_geometry_matches_bruteforce():
    pose, K, depth = _frame()
    h, w = depth.shape
    vox, rng_m = 0.5, 7.0
    g = frame_geometry(pose, K, depth, vox, max_depth_sensing=rng_m, occ_thickness=2)
    flat = depth.reshape(-1)
    occ, free = set(), set()
    z_end = np.where(np.isposinf(flat), rng_m, flat)
    ends = _unproject(pose, K, h, w, z_end)
    offs = np.array([-0.25, 0.25]) * vox
    for i, z in enumerate(flat):
        if np.isnan(z):
            continue
        if np.isfinite(z):
            for dz in offs:
                p = _unproject(pose, K, h, w, np.full(h * w, z + dz))[i]
                occ.add(tuple(np.floor(p / vox).astype(int)))
        free |= _slab_cells(pose[:3, 3], ends[i], vox, exclude_end=bool(np.isfinite(z)))
    free -= occ
    assert {tuple(c) for c in g.occ_ijk.tolist()} == occ
    assert {tuple(c) for c in g.free_ijk.tolist()} == free
    # a fine-step march of each pixel ray only finds cells of the exact set
    for i in np.nonzero(~np.isnan(flat))[0][::7]:
        ts = np.linspace(0, 1, 4000, endpoint=False)
        pts = pose[:3, 3] + ts[:, None] * (ends[i] - pose[:3, 3])
        cells = {tuple(c) for c in np.floor(pts / vox).astype(int)}
        assert cells - {tuple(np.floor(ends[i] / vox).astype(int))} <= free | occ
    # semantic points are the unprojected finite pixels
    fin = np.isfinite(flat)
    assert g.pts_pix.numel() == fin.sum()
    np.testing.assert_allclose(g.pts_xyz.numpy(), _unproject(pose, K, h, w, np.where(fin, flat, 0))[g.pts_pix.numpy()],
                               atol=1e-4)


def test_nan_ignored_inf_carves_to_range_and_empty_frame():
    pose = look_at([0.1, 0.1, 1.0], [10, 0.1, 1.0])
    K = intrinsics_from_fov(60, 4, 4)
    d = np.full((4, 4), np.nan, np.float32)
    g = frame_geometry(pose, K, d, 0.5, max_depth_sensing=5.0)
    cam = voxel_index(pose[:3, 3], 0.5)
    assert g.occ_ijk.shape[0] == 0 and g.free_ijk.tolist() == [cam.tolist()]
    # all +inf but no range: only the camera cell (0 m depth setting), rays still cast
    d[:] = np.inf
    g = frame_geometry(pose, K, d, 0.5, max_depth_sensing=0.0)
    assert g.free_ijk.tolist() == [cam.tolist()] and g.ray_dirs.shape[0] == 16
    # with a range, +inf carves up to it (planar depth 5 m along x)
    g = frame_geometry(pose, K, d, 0.5, max_depth_sensing=5.0)
    xs = (g.free_ijk[:, 0].float() + 0.5) * 0.5
    assert float(xs.max()) <= 0.1 + 5.0 * 1.1 and float(xs.max()) >= 4.5
    torch.testing.assert_close(g.ray_dirs.norm(dim=1), torch.ones(16))


def test_erosion_lets_border_pixels_cast():
    m = torch.zeros(10, 12, dtype=torch.bool)
    m[:, :6] = True  # left half out of range, touching the border
    e = erode_out_of_range(m, 2)
    # brute force with outside = out of range
    pad = torch.ones(14, 16, dtype=torch.bool)
    pad[2:12, 2:14] = m
    ref = torch.zeros_like(m)
    for r in range(10):
        for c in range(12):
            ref[r, c] = bool(pad[r:r + 5, c:c + 5].all())
    assert torch.equal(e, ref)
    assert bool(e[0, 0]) and not bool(e[:, 4:].any())


def test_budgets_are_seeded_and_respected():
    pose, K, depth = _frame(seed=3)
    a = frame_geometry(pose, K, depth, 0.5, max_depth_sensing=7, max_pts=20, max_rays=5, max_empty_pts=50,
                       generator=torch.Generator().manual_seed(5))
    b = frame_geometry(pose, K, depth, 0.5, max_depth_sensing=7, max_pts=20, max_rays=5, max_empty_pts=50,
                       generator=torch.Generator().manual_seed(5))
    assert a.pts_pix.numel() == 20 and a.ray_pix.numel() == 5
    assert torch.equal(a.free_ijk, b.free_ijk) and torch.equal(a.pts_pix, b.pts_pix)
    assert 0 < a.free_ijk.shape[0] <= 51          # some free cells to check below, within the budget
    full = frame_geometry(pose, K, depth, 0.5, max_depth_sensing=7)
    fk = {tuple(c) for c in full.free_ijk.tolist()} | {tuple(c) for c in full.occ_ijk.tolist()}
    assert {tuple(c) for c in a.free_ijk.tolist()} <= fk


def test_feature_sampling_and_aggregation():
    g = torch.Generator().manual_seed(0)
    img = torch.randn(5, 3, 4, generator=g)
    H, W = 12, 16
    pix = torch.arange(H * W)
    s = sample_image(img, pix, (H, W))
    ref = torch.nn.functional.interpolate(img[None], size=(H, W), mode="bilinear", align_corners=False)[0]
    torch.testing.assert_close(s, ref.reshape(5, -1).T, atol=1e-5, rtol=1e-5)
    grp = torch.randint(0, 7, (H * W,), generator=g)
    agg = aggregate_samples(img, pix, (H, W), grp, 7)
    ref2 = torch.zeros(7, 5).index_add_(0, grp, s)
    torch.testing.assert_close(agg, ref2, atol=1e-4, rtol=1e-4)
    agg2 = aggregate_samples(img, pix, (H, W), grp, 7, max_dense=0)
    torch.testing.assert_close(agg2, ref2, atol=1e-4, rtol=1e-4)
