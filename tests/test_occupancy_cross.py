"""The OpenVDB extension against the torch backend (the oracle) on random frames, prune
at all node levels, tiles, and the .vdb file round trip."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic_map.occupancy import TorchOccupancy, vdb_available

pytestmark = pytest.mark.skipif(not vdb_available(),
                                reason="semantic_map._vdbocc not built (OpenVDB missing)")


def pair(vox=0.1, lo=-5, hi=30):
    from semantic_map.occupancy import VdbOccupancy
    return TorchOccupancy(vox, lo, hi), VdbOccupancy(vox, lo, hi)


def assert_same(t, v, rng, frontier_args=((4, 2, 0, 1, None), (1, 0, 0, 1, None))):
    ti, tv = t.active()
    vi, vv = v.active()
    assert torch.equal(ti, vi) and torch.equal(tv, vv)
    assert t.num_active == v.num_active == ti.shape[0]
    lo, hi = ti.min(0).values - 3, ti.max(0).values + 3
    probe = torch.cat([ti[rng.integers(0, len(ti), 2000)],
                       torch.from_numpy(rng.integers(lo.numpy(), hi.numpy() + 1, size=(2000, 3)))])
    assert torch.equal(t.query(probe), v.query(probe.to(torch.int32)))
    for mu, mf, mo, r, bbox in frontier_args:
        ft, fv = t.frontiers(mu, mf, mo, r, bbox), v.frontiers(mu, mf, mo, r, bbox)
        assert torch.equal(ft, fv), (mu, mf, mo, r, bbox)


def random_frame(rng, center, n_free=8000, n_occ=1500):
    """A 'depth frame': a dense free slab swept repeatedly (many duplicates) and noisy
    occupied points, some of them inside the free region (mixed signs per voxel)."""
    free = rng.integers(center - 14, center + 14, size=(n_free, 3))
    occ = rng.integers(center - 18, center + 18, size=(n_occ, 3))
    ijk = np.concatenate([free, occ, free[: n_free // 4]])
    inc = np.concatenate([np.full(n_free, -1), np.full(n_occ, 6), np.full(n_free // 4, -1)])
    perm = rng.permutation(len(ijk))
    return ijk[perm], inc[perm]


def test_random_frames_with_prune():
    rng = np.random.default_rng(10)
    t, v = pair()
    for f in range(6):
        center = np.array([f * 6 - 20, 3 - f, -f])
        ijk, inc = random_frame(rng, center)
        t.update(ijk, inc)
        v.update(torch.from_numpy(ijk.astype(np.int32)), torch.from_numpy(inc))
        # a block that saturates to lo: whole leaves become constant and collapse
        blk = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1).reshape(-1, 3)
        blk = blk + np.array([64, 8 * f, 0])
        for _ in range(6):
            t.update(blk, -1)
            v.update(blk, -1)
        if f % 3 == 2:
            t.prune(2)
            v.prune(2)
            assert v.tile_count > 0
        bbox = (tuple(int(c) for c in center - 10), tuple(int(c) for c in center + 10))
        args = [(4, 2, 0, 1, None), (9, 4, 1, 1, bbox)]
        args.append((20, 10, 0, 2, None) if f % 2 else (0, 0, 0, 1, bbox))
        assert_same(t, v, rng, args)
        # rays from free voxels (anywhere) and from inside the dense free block
        ti, tv = t.active()
        free = ti[tv < 0].numpy()
        starts = np.concatenate([free[rng.integers(0, len(free), 200)],
                                 blk[rng.integers(0, len(blk), 100)]])
        o = (starts + rng.uniform(0, 1, size=starts.shape)) * t.vox
        d = rng.normal(size=o.shape)
        d[:30, 0] = 0
        d[30:40, 1:] = 0
        for max_dist in (4.0, 0.6):
            bt, bv = t.first_blocked(o, d, max_dist), v.first_blocked(o, d, max_dist)
            assert torch.equal(bt, bv)   # same float64 arithmetic, bit for bit
            assert bool(torch.isfinite(bt).any()) and bool((bt > 0).any())
        assert bool(torch.isinf(bt).any())


def test_prune_level1_tile_frontiers_and_redensify():
    """A 128^3 free block collapses to one level-1 tile; its shell is the frontier."""
    t, v = pair()
    n = 128
    c = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    c = c + np.array([-128, 0, 128])                   # aligned on 128 at negative coords
    vals = np.where((c % 3 == 0).all(1), -2, -1)      # leaf medians -1, spread 1
    for g in (t, v):
        g.update(c, vals)
        g.prune(1)
    assert v.leaf_count == 0 and v.tile_count == 1
    assert v.memory_bytes() < 1_000_000 < t.memory_bytes()  # one 32^3 node table
    assert set(v.query(c[::997]).tolist()) == {-1}
    rng = np.random.default_rng(11)
    bbox = ((-140, 5, 120), (-100, 300, 140))        # cuts through the tile
    assert_same(t, v, rng, ((1, 0, 0, 1, bbox), (0, 0, 0, 2, bbox), (30, 10, 0, 2, bbox)))
    assert v.frontiers(1, 0).shape[0] == n ** 3 - (n - 2) ** 3   # the whole shell
    # write inside the tile: VDB re-densifies one leaf, values elsewhere stay -1
    w = np.array([[-64, 64, 192]])
    for g in (t, v):
        g.update(w, 7)
    assert v.leaf_count == 1
    assert t.query(w).tolist() == v.query(w).tolist() == [6]
    near = ((-70, 58, 186), (-58, 70, 198))
    assert_same(t, v, rng, ((1, 0, 0, 1, near), (1, 0, 1, 1, near)))
    assert v.frontiers(0, 0, 1, bbox=near).shape[0] == 26   # the neighbours of the write


def test_prune_twice_and_rewrite_matches():
    rng = np.random.default_rng(12)
    t, v = pair(lo=-8, hi=8)
    blk = np.stack(np.meshgrid(*[np.arange(40)] * 3, indexing="ij"), -1).reshape(-1, 3)
    for tol in (0, 1, 3, 2):
        inc = rng.choice([-1, -1, -1, 0, 1], size=len(blk))
        for g in (t, v):
            g.update(blk, inc)
            g.prune(tol)
        assert_same(t, v, rng)


def test_vdb_file_round_trip(tmp_path):
    from semantic_map.occupancy import VdbOccupancy
    rng = np.random.default_rng(13)
    _, v = pair(vox=0.05, lo=-4, hi=20)
    v.update(rng.integers(-50, 50, size=(20000, 3)), rng.choice([-1, 5], size=20000))
    blk = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1).reshape(-1, 3)
    v.update(blk + 100, -1)   # two uniform leaves, away from the random voxels
    v.prune(0)
    assert v.tile_count > 0
    path = tmp_path / "occ.vdb"
    v.save(path)
    w = VdbOccupancy.load(path)
    assert (w.vox, w.lo, w.hi) == (0.05, -4, 20)
    assert w.tile_count == v.tile_count and w.leaf_count == v.leaf_count
    a, b = v.active(), w.active()
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert torch.equal(v.frontiers(4, 2), w.frontiers(4, 2))
    with pytest.raises(FileNotFoundError):
        VdbOccupancy.load(tmp_path / "missing.vdb")
    bad = tmp_path / "bad.vdb"
    bad.write_bytes(b"not a vdb file at all")
    with pytest.raises(ValueError, match="cannot read"):
        VdbOccupancy.load(bad)
