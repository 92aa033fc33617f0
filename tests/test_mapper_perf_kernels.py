"""C++ kernels (semantic_map._rfkernels) vs their torch twins vs independent brute force.

Every kernel-backed function is run twice, with the kernels enabled and disabled
(:func:`semantic_map.kernels.disabled`), and the results must be identical (``torch.equal``);
where an independent reference exists (brute-force association, slab traversal, dense
unique), both are compared with it too. Without the extension each test checks the torch
path against the references first and then *skips* (reported with the reason, never a
silent pass: :func:`assert_same` refuses ``None``); under ``CI=true`` such a skip fails
``.ci/run`` (tests/ci_skip_allowlist.txt does not list it).
"""
import math

import numpy as np
import pytest
import torch

from common.conventions import sanitize_depth, voxel_index
from semantic_map import cell_keys, kernels
from semantic_map.config import map_config
from semantic_map.depth_geometry import aggregate_samples, erode_out_of_range, frame_geometry, sample_image
from semantic_map.map import RayFrontsMap
from semantic_map.ray_frontiers import associate, associate_bruteforce
from semantic_map.traversal import segment_cells, unique_cells

needs_kernels = pytest.mark.skipif(not kernels.available(),
                                   reason=f"semantic_map._rfkernels not built: {kernels.IMPORT_ERROR}")


def both(fn):
    """(kernel result, torch result) of ``fn()``; kernel result is None without the module."""
    k = fn() if kernels.available() else None
    with kernels.disabled():
        t = fn()
    return k, t


def kernel_same(*pairs):
    """Kernel result == torch result for each ``(k, t)``; called last in a test: without the
    kernel module (``k is None``) the test is skipped here, after its torch checks ran."""
    if any(k is None for k, _ in pairs):
        pytest.skip(f"semantic_map._rfkernels not built ({kernels.IMPORT_ERROR}): only the torch path was checked")
    for k, t in pairs:
        assert_same(k, t)


def assert_same(a, b):
    assert a is not None and b is not None, "nothing to compare (a result is None)"
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert torch.equal(a, b)
        return
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert_same(x, y)


def test_switch_and_env():
    assert kernels.enabled() == (kernels.available() and kernels._enabled)
    with kernels.disabled():
        assert not kernels.enabled()
    old = kernels.set_enabled(True)
    assert kernels.set_enabled(old) is True


# ------------------------------------------------------------------------- association
def _rays(seed, n_rays, n_front, spread, far=5.0):
    g = torch.Generator().manual_seed(seed)
    fr = torch.unique(torch.randint(-spread, spread, (n_front, 3), generator=g), dim=0)
    o = (torch.rand(n_rays, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * far
    o[: n_rays // 2] = o[0]
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g, dtype=torch.float64), dim=1)
    # axis-aligned and planar directions (zero components), origins on cell boundaries
    d[1:40:3] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    d[2:40:3] = torch.nn.functional.normalize(torch.tensor([[0.0, -1.0, 1.0]], dtype=torch.float64), dim=1)
    o[3:40:3] = torch.round(o[3:40:3])
    return o, d, fr


@pytest.mark.parametrize("seed,beta,max_dist,close,block", [
    (0, 1.0, -1.0, False, 4), (1, 1.2, 15.0, False, 1), (2, 0.5, 8.0, True, 2), (3, 2.0, -1.0, True, 7),
    (4, 0.3, 6.0, False, 3)])
def test_associate_kernel_torch_bruteforce(seed, beta, max_dist, close, block):
    o, d, fr = _rays(seed, 400, 600, 14)
    k, t = both(lambda: associate(o, d, fr, beta, max_dist=max_dist, reject_close=close, block=block))
    ref = associate_bruteforce(o, d, fr, beta, max_dist=max_dist, reject_close=close)
    assert t[0].numel() > 20
    assert_same(t, ref)
    kernel_same((k, t))


def test_associate_far_from_origin_and_float32_rays():
    # world coordinates ~ 3 km from the origin: the float32 metrics are relative to a base
    o, d, fr = _rays(5, 300, 500, 12)
    shift = torch.tensor([2500, -3100, 40])
    fr = fr + shift
    o = o + shift.to(torch.float64) * 1.0
    k, t = both(lambda: associate(o, d.to(torch.float32), fr, 1.0, max_dist=20.0))
    ref = associate_bruteforce(o, d.to(torch.float32), fr, 1.0, max_dist=20.0)
    assert t[0].numel() > 20
    assert_same(t, ref)
    kernel_same((k, t))


def test_associate_many_rays_uses_one_base_point(monkeypatch):
    # more rays than the torch path's ray chunk (8192) and the kernel's (set to 2500): all
    # chunks share the base point, so the result is the brute force's exactly
    import semantic_map.ray_frontiers as RF
    monkeypatch.setattr(RF, "KERNEL_RAY_CHUNK", 2500)
    o, d, fr = _rays(6, 9000, 300, 8, far=3.0)
    o[:4500] += torch.tensor([30.0, 0, 0], dtype=torch.float64)
    fr = torch.cat([fr, fr + torch.tensor([25, 0, 0])])
    k, t = both(lambda: associate(o, d, fr, 1.0, max_dist=12.0))
    ref = associate_bruteforce(o, d, fr, 1.0, max_dist=12.0)
    assert t[0].numel() > 1000
    assert_same(t, ref)
    kernel_same((k, t))


def test_associate_frontiers_far_apart():
    # two frontier clusters ~12 km apart: the kernel's block range is too large for its dense
    # block grid (it hashes the blocks instead); rays near each cluster
    o, d, fr = _rays(8, 400, 500, 12)
    shift = torch.tensor([10000, 7000, 0])
    fr = torch.cat([fr, fr + shift])
    o[200:] += shift.to(torch.float64)
    k, t = both(lambda: associate(o, d, fr, 1.0, max_dist=15.0))
    ref = associate_bruteforce(o, d, fr, 1.0, max_dist=15.0)
    assert t[0].numel() > 40 and bool((t[1] >= 500).any()) and bool((t[1] < 500).any())
    assert_same(t, ref)
    kernel_same((k, t))


def _fan_rays(seed, centres, per, jitter, n_front, spread):
    """Rays of a ray block: ``per`` rays from each of a few origins (``centres`` plus up to
    ``jitter`` m), with straight up / down and +-pi azimuth directions among them, and
    frontiers all around (some within a cell of an origin)."""
    g = torch.Generator().manual_seed(seed)
    c = torch.as_tensor(centres, dtype=torch.float64)
    o = (c + (torch.rand(c.shape, generator=g, dtype=torch.float64) - 0.5) * 2 * jitter).repeat_interleave(per, 0)
    d = torch.nn.functional.normalize(torch.randn(o.shape[0], 3, generator=g, dtype=torch.float64), dim=1)
    d[0:60:6] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    d[1:60:6] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    d[2:60:6] = torch.nn.functional.normalize(torch.tensor([[-1.0, 1e-12, 0.0]], dtype=torch.float64), dim=1)
    d[3:60:6] = torch.nn.functional.normalize(torch.tensor([[-1.0, -1e-12, 0.02]], dtype=torch.float64), dim=1)
    d[4:60:6] = torch.nn.functional.normalize(torch.tensor([[0.01, 0.0, 1.0]], dtype=torch.float64), dim=1)
    fr = torch.randint(-spread, spread, (n_front, 3), generator=g)
    near_o = torch.floor(o[::per] / 1.0).to(torch.int64)       # frontiers at the origins' own cells
    return o, d, torch.unique(torch.cat([fr, near_o, near_o + 1]), dim=0)


@needs_kernels
@pytest.mark.parametrize("case", ["one fan", "origins apart", "close, absolute", "float32 dirs"])
def test_associate_fan_equals_the_walk_and_the_brute_force(case):
    """The fan kernel (rays binned by direction per origin or per fan of nearby origins) gives
    the walk's and the brute force's pairs, frontiers and costs bit for bit: one fan of 8
    jittered origins, 5 origins 14 m apart (a fan each), reject_close with the absolute cost,
    float32 directions; poles, the azimuth seam and frontiers at the origins included. 17
    origins apart are refused (the caller walks)."""
    beta, max_dist, close, cost = 1.0, 12.0, False, "paper"
    if case == "origins apart":
        o, d, fr = _fan_rays(11, [[14.0 * i, 0.0, 0.0] for i in range(5)], 600, 0.0, 9000, 30)
    else:
        o, d, fr = _fan_rays(10, [[0.0, 0.0, 0.0]] * 8, 500, 0.35, 6000, 14)
    if case == "close, absolute":
        close, cost = True, "absolute"
    if case == "float32 dirs":
        d = d.to(torch.float32)
    base = torch.round(o.mean(0))
    assert kernels.associate_rays_fan(o, d, fr, beta, base, max_dist, close) is not None   # the fan serves it
    fan = associate(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost=cost)
    walk = associate(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost=cost, fan_off=True)
    ref = associate_bruteforce(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost=cost)
    assert fan[0].numel() > o.shape[0] // 3
    assert_same(walk, ref)
    assert_same(fan, ref)
    many, dm, fm = _fan_rays(12, [[3.0 * i, 0.0, 0.0] for i in range(17)], 20, 0.0, 500, 30)
    assert kernels.associate_rays_fan(many, dm, fm, beta, torch.zeros(3, dtype=torch.float64), max_dist, False) is None
    bent = d.to(torch.float64) * 1.001                  # not unit: the fan's cones would not hold
    assert kernels.associate_rays_fan(o, bent, fr, beta, base, max_dist, close) is None


def test_associate_degenerate_inputs():
    o, d, fr = _rays(7, 10, 20, 4)
    e = torch.empty((0, 3), dtype=torch.int64)
    pairs = []
    for args in ((o[:0], d[:0], fr), (o, d, e)):
        k, t = both(lambda args=args: associate(*args, 1.0, max_dist=5.0))
        assert t[0].numel() == 0
        pairs.append((k, t))
    # a single frontier straight ahead: cost 0.5 (ortho term 0, distance term 1)
    fr1 = torch.tensor([[3, 0, 0]])
    o1 = torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64)
    d1 = torch.tensor([[1.0, 0, 0]], dtype=torch.float64)
    k, t = both(lambda: associate(o1, d1, fr1, 1.0))
    assert t[1].tolist() == [0] and float(t[2][0]) == 0.5
    kernel_same(*pairs, (k, t))


# ------------------------------------------------------------------------- keys / unique
@needs_kernels
def test_unique_keys_matches_torch_unique():
    g = torch.Generator().manual_seed(0)
    for n, hi in ((0, 5), (1, 5), (1000, 7), (50000, 1 << 40), (20000, 30000)):
        x = torch.randint(-hi, hi, (n,), generator=g)
        a = kernels.unique_keys(x)
        b = torch.unique(x, sorted=True, return_inverse=True, return_counts=True)
        assert_same(a, tuple(b))


def test_voxel_keys_and_range_errors():
    g = torch.Generator().manual_seed(1)
    x = (torch.rand(5000, 3, generator=g, dtype=torch.float64) - 0.5) * 200
    x[:100] = torch.round(x[:100] / 0.3) * 0.3  # on (or next to) voxel boundaries
    pairs = []
    for xx in (x, x.to(torch.float32)):
        k, t = both(lambda xx=xx: kernels.voxel_keys(xx, 0.3))
        assert torch.equal(t, cell_keys.pack(voxel_index(xx.to(torch.float64), 0.3)))
        pairs.append((k, t))
    far = torch.tensor([[4e6, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="packable range"):
        kernels.voxel_keys(far, 1.0)
    with kernels.disabled(), pytest.raises(ValueError, match="packable range"):
        kernels.voxel_keys(far, 1.0)
    kernel_same(*pairs)


# ------------------------------------------------------------------------- traversal
def test_unique_cells_kernel_torch_dense_sparse():
    rng = np.random.default_rng(2)
    o = torch.tensor(rng.uniform(-1, 1, (120, 3)))
    o[:60] = o[0]
    e = o + torch.tensor(rng.normal(size=(120, 3)) * 6)
    e[:20] = torch.round(e[:20] * 2) / 2  # ends on cell boundaries (0.5 m cells)
    e[20:40, 2] = o[20:40, 2]              # planar segments
    excl = torch.tensor(rng.uniform(size=120) < 0.5)
    pairs = []
    for chunk in (397, 1 << 22):
        k, t = both(lambda chunk=chunk: unique_cells(o, e, 0.5, exclude_end=excl, chunk=chunk))
        with kernels.disabled():
            sparse = unique_cells(o, e, 0.5, exclude_end=excl, chunk=chunk, max_dense=0)
        pairs.append((k, t))
        assert torch.equal(t, sparse)
        # independent: union of the per-segment pairs
        rid, c = segment_cells(o, e, 0.5, exclude_end=excl, chunk=chunk)
        ref = cell_keys.unpack(torch.unique(cell_keys.pack(c)))
        assert torch.equal(t, ref)
    kernel_same(*pairs)


# ------------------------------------------------------------------------- frame geometry
def _world_frames(n, hw, seed=0):
    from synthetic_world import World
    w = World.generate(seed)
    poses = w.trajectory("ground", n, seed=seed)
    K = w.camera(hw, 90.0)
    out = []
    for p in poses:
        r = w.render(p, K, hw)
        out.append((p, K, r.depth.astype(np.float32), r.rgb))
    return out


@pytest.mark.parametrize("vox,thick,stride,budgets", [(1.0, 2, -1, False), (0.3, 1, 1, True), (0.1, 3, 2, False)])
def test_frame_geometry_kernel_equals_torch(vox, thick, stride, budgets):
    fields = ("origin", "occ_ijk", "free_ijk", "pts_xyz", "pts_pix", "ray_dirs", "ray_pix")
    pairs = []
    for pose, K, depth, _ in _world_frames(3, (72, 96)):
        d = sanitize_depth(torch.as_tensor(depth), 20.0)
        kw = dict(max_depth_sensing=20.0, occ_thickness=thick, ray_erosion=3, free_stride=stride)
        if budgets:
            kw.update(max_pts=500, max_empty_pts=800, max_rays=50)
        k, t = both(lambda pose=pose, K=K, d=d, kw=kw: frame_geometry(pose, K, d, vox,
                                                                     generator=torch.Generator().manual_seed(3), **kw))
        assert t.occ_ijk.shape[0] > 10 and t.free_ijk.shape[0] > 10
        pairs.append((None if k is None else tuple(getattr(k, f) for f in fields),
                      tuple(getattr(t, f) for f in fields)))
    kernel_same(*pairs)


def test_erosion_random_masks_vs_pooling():
    g = torch.Generator().manual_seed(4)
    for h, w, r in ((40, 56, 3), (17, 9, 6), (64, 64, 32), (5, 7, 1)):
        m = torch.rand(h, w, generator=g) < 0.95
        m[: h // 3] = True
        pad = torch.ones(h + 2 * r, w + 2 * r, dtype=torch.bool)
        pad[r:r + h, r:r + w] = m
        ref = torch.nn.functional.max_pool2d((~pad).float()[None, None], 2 * r + 1, stride=1)[0, 0] == 0
        assert torch.equal(erode_out_of_range(m, r), ref)


# ------------------------------------------------------------------------- feature sampling
@pytest.mark.parametrize("src_hw,dtype,mode", [((5, 7), torch.float16, "bilinear"),
                                               ((5, 7), torch.float32, "nearest"),
                                               ((30, 40), torch.float32, "bilinear"),
                                               ((30, 40), torch.float32, "nearest"),
                                               ((12, 40), torch.float32, "bilinear")])
def test_aggregate_kernel_torch_and_reference(src_hw, dtype, mode):
    g = torch.Generator().manual_seed(5)
    H, W = 30, 40
    img = torch.randn(6, *src_hw, generator=g).to(dtype)
    pix = torch.randperm(H * W, generator=g)[:900]
    grp = torch.randint(0, 37, (900,), generator=g)
    k, t = both(lambda: aggregate_samples(img, pix, (H, W), grp, 37, mode))
    ref = torch.zeros(37, 6).index_add_(0, grp, sample_image(img, pix, (H, W), mode))
    torch.testing.assert_close(t, ref, atol=1e-4, rtol=1e-4)
    if mode == "bilinear":
        up = torch.nn.functional.interpolate(img.float()[None], size=(H, W), mode="bilinear", align_corners=False)[0]
        ref2 = torch.zeros(37, 6).index_add_(0, grp, up.reshape(6, -1).T[pix])
        torch.testing.assert_close(t, ref2, atol=1e-4, rtol=1e-4)
    with kernels.disabled():
        sparse = aggregate_samples(img, pix, (H, W), grp, 37, mode, max_dense=0)
    torch.testing.assert_close(sparse, t, atol=1e-5, rtol=1e-5)
    kernel_same((k, t))


@needs_kernels
def test_kernel_bad_inputs_raise():
    from semantic_map import _rfkernels as R
    with pytest.raises(IndexError):
        R.sample_pairs(np.array([0, 5]), np.array([0, 1]), 4, 4, 2, 2, False, 3)  # group 5 >= 3
    with pytest.raises(IndexError):
        R.sample_pairs(np.array([0, 1]), np.array([0, 16]), 4, 4, 2, 2, False, 3)  # pixel 16 >= 4*4
    with pytest.raises(ValueError):
        R.associate_rays(np.zeros((2, 3)), np.zeros((1, 3)), np.zeros(2), np.zeros((1, 3), np.int64), 1.0, 4,
                         np.zeros(3), -1.0, False)


# ------------------------------------------------------------------------- whole map
def test_map_kernel_equals_torch_end_to_end():
    frames = _world_frames(12, (48, 64), seed=2)
    cfg = map_config("online", dict(vox_size=0.5, vox_accum_period=2, ray_accum_period=3, ray_accum_phase=1,
                                    max_rays_per_frame=300, ray_erosion=2, fronti_subsampling_min_fronti=2))
    g = torch.Generator().manual_seed(0)
    feats = [torch.randn(5, 6, 8, generator=g).to(torch.float16) for _ in frames]

    def run():
        m = RayFrontsMap(cfg, 5, "t")
        for (p, K, d, rgb), f in zip(frames, feats, strict=True):
            m.integrate(p, K, d, rgb, f)
        m.flush()
        return m

    k, t = both(run)
    st = t.stats()
    assert st["n_voxels"] > 100 and st["n_frontiers"] > 0 and st["n_rays"] > 0
    assert math.isfinite(float(t.rays().weights.sum()))

    def layers(m):
        v, r = m.voxels(), m.rays()
        return (tuple(getattr(v, f) for f in ("xyz", "rgb", "features", "counts")) + (m.frontiers().keys,)
                + tuple(getattr(r, f) for f in ("origins", "directions", "features", "weights", "frontier_keys"))
                + tuple(m.occupancy_view().active()))
    kernel_same((None if k is None else layers(k), layers(t)))
