"""Ray ↔ frontier association, binning, merging, pruning and the baseline modes."""
import math

import pytest
import torch

from semantic_map import cell_keys
from semantic_map.ray_frontiers import (
    RayStore,
    angle_bins,
    associate,
    associate_bruteforce,
    bin_centre_dirs,
    infer_directions,
)


def _rand_case(seed, n_rays=300, n_front=400, spread=12):
    g = torch.Generator().manual_seed(seed)
    fr = torch.unique(torch.randint(-spread, spread, (n_front, 3), generator=g), dim=0)
    o = (torch.rand(n_rays, 3, generator=g, dtype=torch.float64) - 0.5) * 10
    o[: n_rays // 2] = o[0]  # many rays share a camera centre, as in a frame
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g, dtype=torch.float64), dim=1)
    return o, d, fr


@pytest.mark.parametrize("seed,beta,max_dist,close", [(0, 1.0, -1.0, False), (1, 1.2, 15.0, False),
                                                      (2, 0.5, 8.0, True), (3, 2.0, -1.0, True)])
def test_associate_matches_bruteforce(seed, beta, max_dist, close):
    o, d, fr = _rand_case(seed)
    a = associate(o, d, fr, beta, max_dist=max_dist, reject_close=close, chunk=5000)
    b = associate_bruteforce(o, d, fr, beta, max_dist=max_dist, reject_close=close)
    assert a[0].numel() > 20
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


def test_associate_sparse_lookup_path_matches():
    o, d, fr = _rand_case(4, spread=3000, n_front=3000)  # frontier box too large for the dense table
    fr = torch.cat([fr, torch.randint(-5, 5, (300, 3), generator=torch.Generator().manual_seed(9))]).unique(dim=0)
    a = associate(o, d, fr, 1.0, max_dist=30.0)
    b = associate_bruteforce(o, d, fr, 1.0, max_dist=30.0)
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


def test_cost_uses_per_ray_maxima():
    o = torch.zeros(1, 3, dtype=torch.float64)
    d = torch.tensor([[1.0, 0, 0]], dtype=torch.float64)
    # coarse cells of size 1 -> centres at +0.5; A: 10 m away, 0.8 off-axis; B: 20 m, on the axis
    fr = torch.tensor([[9, 0, 0], [19, -1, -1], [-10, -1, -1], [5, 6, 0]])
    o[:] = torch.tensor([0.0, -0.5, -0.5])  # so that B's centre (19.5,-0.5,-0.5) is on the ray
    fr[0] = torch.tensor([9, 0, 0])           # A centre (9.5, 0.5, 0.5): ortho = sqrt(2) > 1 -> not a candidate
    ri, fi, cost = associate(o, d, fr, 1.0)
    assert fi.tolist() == [1] and abs(float(cost[0]) - 0.5) < 1e-6  # lone candidate on the axis: ortho term 0
    fr2 = torch.tensor([[9, -1, -1], [19, -1, -1]])
    o2 = torch.tensor([[0.0, -0.9, -0.5]], dtype=torch.float64)  # A: d_ortho 0.4, B: d_ortho 0.4
    ri, fi, cost = associate(o2, d, fr2, 1.0)
    # both ortho 0.4 -> ortho terms 1; d_orig 9.5 vs 19.5 -> A wins with cost (1 + 9.5/19.5)/2
    assert fi.tolist() == [0]
    assert abs(float(cost[0]) - (1 + math.hypot(9.5, 0.4) / math.hypot(19.5, 0.4)) / 2) < 1e-5


def test_zero_depth_nearest_frontier():
    g = torch.Generator().manual_seed(5)
    fr = torch.randint(-10, 10, (50, 3), generator=g).unique(dim=0)
    o = torch.randn(7, 3, generator=g, dtype=torch.float64) * 4
    d = torch.nn.functional.normalize(torch.randn(7, 3, generator=g, dtype=torch.float64), dim=1)
    ri, fi, cost = associate(o, d, fr, 2.0, zero_depth=True)
    p = (fr.double() + 0.5) * 2.0
    ref = torch.cdist(o, p).argmin(1)
    assert ri.tolist() == list(range(7)) and torch.equal(fi, ref)


def test_theta_wraps_and_bins():
    d = torch.tensor([[math.cos(math.radians(a)) * math.sin(math.radians(80)),
                       math.sin(math.radians(a)) * math.sin(math.radians(80)),
                       math.cos(math.radians(80))] for a in (179.9, -179.9, 0.1, -0.1, 14.0, 16.0)])
    tb, pb = angle_bins(d, 30.0)
    assert tb[0] == tb[1] == 6 and tb[2] == tb[3] == 0 and tb[4] == 0 and tb[5] == 1
    assert bool((pb == 2).all())
    c = bin_centre_dirs(tb, pb, 30.0)
    assert float((c * d).sum(1).min()) > math.cos(math.radians(25))
    tb, pb = angle_bins(d, 360.0)
    assert bool((tb == 0).all() and (pb == 0).all())


def test_weighted_merge_and_prune_requeue():
    keys = cell_keys.pack(torch.tensor([[0, 0, 0], [3, 0, 0]]))
    rs = RayStore(beta=2.0, psi=30.0, feature_dim=2)
    d = torch.tensor([[1.0, 0, 0], [1.0, 0.01, 0], [0, 0, 1.0], [1.0, 0, 0]])
    d = torch.nn.functional.normalize(d, dim=1)
    f = torch.tensor([[1.0, 0], [0, 1.0], [1.0, 1.0], [2.0, 2.0]])
    w = torch.tensor([0.5, 0.25, 1.0, 0.8])
    fk = keys[[0, 0, 0, 1]]
    rs.merge(fk[:2], keys, d[:2], f[:2], w[:2])      # first cast: plain weighted mean
    rs.merge(fk[2:], keys, d[2:], f[2:], w[2:])
    rs.merge(fk[:1], keys, d[:1], torch.tensor([[4.0, 4.0]]), torch.tensor([0.25]))
    assert len(rs) == 3
    i = int(((rs.fkey == keys[0]) & (rs.pbin == 3)).nonzero()[0])  # horizontal bin of frontier 0
    ref = (0.5 * f[0] + 0.25 * f[1] + 0.25 * torch.tensor([4.0, 4.0])) / 1.0
    torch.testing.assert_close(rs.feat[i], ref)
    assert abs(float(rs.weight[i]) - 1.0) < 1e-6
    # frontier 0 disappears: its two bins are re-queued from its centre with the bin-centre direction
    out = rs.prune(keys[1:], requeue=True)
    assert len(rs) == 1 and out[0].shape[0] == 2
    torch.testing.assert_close(out[0], torch.full((2, 3), 1.0))
    assert bool((out[2] == ref).all(1).any())
    assert rs.prune(keys[:0], requeue=False) is None and len(rs) == 0


def test_infer_direction_points_to_unobserved():
    from semantic_map.occupancy import make_occupancy

    grid = make_occupancy(1.0, -5, 30, backend="torch")
    # observed (free) half-space x < 2; neighbours sampled at +-beta around the centre
    ijk = torch.stack(torch.meshgrid(torch.arange(-8, 2), torch.arange(-8, 16), torch.arange(-8, 16), indexing="ij"),
                      -1).reshape(-1, 3)
    grid.update(ijk, -1)
    fk = cell_keys.pack(torch.tensor([[0, 1, 1]]))  # coarse cell (0,1,1) of beta 2 -> centre (1, 3, 3)
    d = infer_directions(grid, fk, beta=2.0, vox=1.0, scale="coarse")
    torch.testing.assert_close(d, torch.tensor([[1.0, 0, 0]]))
