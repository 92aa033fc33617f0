"""Occupancy grid: both backends against independent references (sequential Python
clamping, brute-force neighbour counts, a fine-step ray march) and against each other."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from common.conventions import voxel_index
from semantic_map.occupancy import TorchOccupancy, VdbOccupancy, backend_name, from_state, make_occupancy, vdb_available

BACKENDS = [
    "torch",
    pytest.param("vdb", marks=pytest.mark.skipif(
        not vdb_available(), reason="semantic_map._vdbocc not built (OpenVDB missing)")),
]


@pytest.fixture(params=BACKENDS)
def backend(request):
    return request.param


# ---------------------------------------------------------------- references
def seq_reference(updates, lo, hi):
    """dict ijk -> value after applying (ijk, inc) batches row by row (the definition)."""
    ref = {}
    for ijk, inc in updates:
        inc = np.broadcast_to(np.asarray(inc), (len(ijk),))
        for row, a in zip(np.asarray(ijk).tolist(), inc.tolist(), strict=True):
            key = tuple(row)
            ref[key] = min(max(ref.get(key, 0) + int(a), lo), hi)
    return ref


def dense_of(ijk: np.ndarray, vals: np.ndarray, pad: int):
    lo = ijk.min(0) - pad
    shape = tuple(ijk.max(0) - lo + pad + 1)
    vol = np.zeros(shape, dtype=np.int16)
    vol[tuple((ijk - lo).T)] = vals
    return vol, lo


def brute_frontiers(ijk, vals, mu, mf, mo=0, r=1, bbox=None):
    """Frontier set by explicit neighbour loops on a dense copy (independent of backends)."""
    ijk, vals = np.asarray(ijk), np.asarray(vals)
    if len(ijk) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    vol, lo = dense_of(ijk, vals, r + 1)
    cand = ijk[vals < 0]
    if bbox is not None:
        cand = cand[np.all((cand >= bbox[0]) & (cand <= bbox[1]), axis=1)]
    c = cand - lo
    nun = np.zeros(len(c), int)
    nfr = np.zeros(len(c), int)
    noc = np.zeros(len(c), int)
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            for dz in range(-r, r + 1):
                v = vol[c[:, 0] + dx, c[:, 1] + dy, c[:, 2] + dz]
                nun += v == 0
                nfr += v < 0
                noc += v > 0
    keep = (nun >= mu) & (nfr >= mf) & (noc >= mo)
    out = cand[keep]
    return out[np.lexsort((out[:, 2], out[:, 1], out[:, 0]))]


def as_set(t):
    return {tuple(r) for r in np.asarray(t).tolist()}


def cube(n, origin=(0, 0, 0)):
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g + np.asarray(origin)


def grid_from(backend, ijk, vals, vox=0.1, lo=-5, hi=30):
    g = make_occupancy(vox, lo, hi, backend=backend)
    g.update(np.asarray(ijk, dtype=np.int64), np.asarray(vals, dtype=np.int64))
    return g


# ---------------------------------------------------------------- factory
def test_factory_and_names():
    assert backend_name("torch") == "torch"
    assert backend_name() in ("vdb", "torch")
    assert isinstance(make_occupancy(0.1, backend="torch"), TorchOccupancy)
    if vdb_available():
        assert backend_name() == "vdb"
        assert isinstance(make_occupancy(0.1), VdbOccupancy)
    with pytest.raises(ValueError, match="unknown occupancy backend"):
        make_occupancy(0.1, backend="octomap")
    with pytest.raises(ValueError, match="int8"):
        make_occupancy(0.1, -5, 200)
    with pytest.raises(ValueError, match="voxel size"):
        make_occupancy(0.0)


def test_bad_inputs(backend):
    g = make_occupancy(0.1, backend=backend)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        g.update(np.zeros((4, 2), np.int32), 1)
    with pytest.raises(TypeError, match="integer"):
        g.update(np.zeros((4, 3), np.float32), 1)
    with pytest.raises(ValueError, match="shape"):
        g.update(np.zeros((4, 3), np.int32), np.ones(3, np.int32))
    with pytest.raises(ValueError, match="voxel indices must lie"):
        g.query(np.array([[0, 0, 1 << 22]]))
    with pytest.raises(ValueError, match="tolerance"):
        g.prune(-1)
    with pytest.raises(ValueError, match="non-zero"):
        g.first_blocked(np.zeros((1, 3)), np.zeros((1, 3)), 1.0)
    with pytest.raises(ValueError, match="radius"):
        g.frontiers(1, 0, radius=0)
    assert g.num_active == 0  # nothing was applied by the failed calls


# ---------------------------------------------------------------- update / query
def test_clamping_sequences(backend):
    lo, hi = -5, 30
    g = make_occupancy(0.1, lo, hi, backend=backend)
    a, b, c = [0, 0, 0], [1, -2, 3], [-7, 0, 2]
    # a: +6 x6 -> 30 (saturates at 36), then -1 x40 -> -5 (saturates), then +6 -> 1
    rows = [a] * 6 + [a] * 40 + [a]
    incs = [6] * 6 + [-1] * 40 + [6]
    # b: -1 x8 -> -5, +6 -> 1, -1, -1 -> -1
    rows += [b] * 8 + [b] + [b, b]
    incs += [-1] * 8 + [6] + [-1, -1]
    # c: +4 -1 -1 -1 -1 -> 0 (active, unobserved value)
    rows += [c, c, c, c, c]
    incs += [4, -1, -1, -1, -1]
    perm = np.random.default_rng(0).permutation(len(rows))  # interleave, keep per-voxel order
    rows_np, incs_np = np.array(rows), np.array(incs)
    # any interleaving that keeps the relative order of each voxel's rows is equivalent
    by_voxel = {}
    for i in range(len(rows)):
        by_voxel.setdefault(tuple(rows[i]), []).append(i)
    sched = sorted(range(len(rows)), key=lambda i: perm[i])
    seq = {k: iter(v) for k, v in by_voxel.items()}
    idx = [next(seq[tuple(rows[i])]) for i in sched]
    g.update(rows_np[idx].astype(np.int32), torch.from_numpy(incs_np[idx]))
    q = g.query(torch.tensor([a, b, c, [5, 5, 5]], dtype=torch.int32))
    assert q.dtype == torch.int8
    assert q.tolist() == [1, -1, 0, 0]
    assert g.num_active == 3
    ijk, vals = g.active()
    assert ijk.dtype == torch.int64 and vals.dtype == torch.int8
    assert ijk.tolist() == sorted([a, b, c])


def test_int8_range_and_scalar_inc(backend):
    g = make_occupancy(0.1, -128, 127, backend=backend)
    g.update(np.zeros((300, 3), np.int64), 1)
    g.update(np.ones((3, 3), np.int64), 1000)
    g.update(-np.ones((3, 3), np.int64), -1000)
    assert g.query(np.array([[0, 0, 0], [1, 1, 1], [-1, -1, -1]])).tolist() == [127, 127, -128]


def test_random_updates_match_sequential_reference(backend):
    rng = np.random.default_rng(1)
    lo, hi = -5, 12
    g = make_occupancy(0.05, lo, hi, backend=backend)
    updates = []
    for _ in range(6):
        n = 3000
        ijk = rng.integers(-6, 6, size=(n, 3))  # ~1728 voxels -> many duplicates
        inc = rng.choice([-1, -1, -1, 6, 2, -3], size=n)
        updates.append((ijk, inc))
        g.update(ijk.astype(np.int32), inc)
    ref = seq_reference(updates, lo, hi)
    ijk, vals = g.active()
    assert len(ref) == g.num_active == ijk.shape[0]
    got = dict(zip(map(tuple, ijk.tolist()), vals.tolist(), strict=True))
    assert got == ref
    probe = rng.integers(-8, 8, size=(500, 3))
    q = g.query(probe)
    assert q.tolist() == [ref.get(tuple(p), 0) for p in probe.tolist()]


def test_negative_floor_indexing(backend):
    """ijk = floor(xyz / vox): -0.05 m at 0.1 m is voxel -1, not 0."""
    vox = 0.1
    xyz = np.array([[-0.05, 0.05, -0.15], [0.0, -1e-9, 0.29]])
    ijk = voxel_index(xyz, vox)
    assert ijk.tolist() == [[-1, 0, -2], [0, -1, 2]]
    g = make_occupancy(vox, backend=backend)
    g.update(ijk, np.array([6, -1]))
    assert g.query(np.array([[-1, 0, -2], [0, 0, -2], [0, -1, 2]])).tolist() == [6, 0, -1]
    # first_blocked starts in the origin's floor voxel: origin in voxel -1 (occupied) -> 0
    free = cube(6, (-3, -3, -3))
    g2 = grid_from(backend, free, -np.ones(len(free), int), vox)
    g2.update(np.array([[-1, 0, 0]]), 7)  # occupied voxel x in [-0.1, 0)
    d = g2.first_blocked(np.array([[-0.05, 0.05, 0.05], [0.05, 0.05, 0.05]]),
                         np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]), 10.0)
    assert d[0].item() == 0.0
    assert d[1].item() == pytest.approx(0.05, abs=1e-12)


# ---------------------------------------------------------------- frontiers
def test_frontiers_free_cube(backend):
    c = cube(5)
    g = grid_from(backend, c, -np.ones(len(c), int))
    f = g.frontiers(min_unobserved=1, min_free=0)
    assert f.dtype == torch.int64 and f.shape == (98, 3)
    ref = brute_frontiers(c, -np.ones(len(c)), 1, 0)
    assert f.tolist() == ref.tolist()  # same rows, sorted lexicographically
    assert g.frontiers(10, 0).shape[0] == 44   # edges + corners
    corners = g.frontiers(16, 0)
    assert as_set(corners) == {(x, y, z) for x in (0, 4) for y in (0, 4) for z in (0, 4)}
    assert g.frontiers(20, 0).shape[0] == 0
    assert g.frontiers(0, 27).shape[0] == 27     # interior: all 27 free (self included)
    assert g.frontiers(0, 0).shape[0] == 125
    # bbox limits candidates only (neighbours outside it are read)
    fb = g.frontiers(1, 0, bbox=((0, 0, 0), (4, 4, 0)))
    assert as_set(fb) == {(x, y, 0) for x in range(5) for y in range(5)}
    fb = g.frontiers(1, 0, bbox=(np.array([1, 1, 1]), np.array([3, 3, 3])))
    assert fb.shape[0] == 0
    # radius 2: only the centre's 5^3 neighbourhood lies inside the cube
    assert g.frontiers(1, 0, radius=2).shape[0] == 124


def test_frontiers_occupied_wall(backend):
    c = cube(5)
    wall = np.array([[5, y, z] for y in range(5) for z in range(5)])
    ijk = np.concatenate([c, wall])
    vals = np.concatenate([-np.ones(len(c), int), np.full(len(wall), 6)])
    g = grid_from(backend, ijk, vals)
    f = g.frontiers(1, 0)
    assert f.shape[0] == 89   # the 3x3 interior of the face at x=4 sees only cube + wall
    assert f.tolist() == brute_frontiers(ijk, vals, 1, 0).tolist()
    fo = g.frontiers(1, 0, min_occupied=1)
    assert fo.shape[0] == 16 and bool((fo[:, 0] == 4).all())
    assert fo.tolist() == brute_frontiers(ijk, vals, 1, 0, 1).tolist()
    # zero-valued active voxels count as unobserved
    g.update(np.array([[2, 2, 5]]), 0)
    assert g.query(np.array([[2, 2, 5]])).tolist() == [0]
    assert g.frontiers(1, 0).shape[0] == 89


def test_frontiers_random_vs_bruteforce(backend):
    rng = np.random.default_rng(2)
    g = make_occupancy(0.1, -5, 30, backend=backend)
    ijk = rng.integers(-20, 20, size=(30000, 3))
    ijk[:, 2] //= 3  # denser in z
    inc = rng.choice([-1, -1, -1, -1, 6], size=len(ijk))
    g.update(ijk, inc)
    a_ijk, a_val = g.active()
    for mu, mf, mo, r, bbox in [(4, 2, 0, 1, None), (1, 0, 0, 1, None), (9, 4, 1, 1, None),
                                (30, 10, 0, 2, None), (4, 2, 0, 1, ((-5, -5, -3), (10, 3, 4)))]:
        f = g.frontiers(mu, mf, mo, r, bbox)
        ref = brute_frontiers(a_ijk.numpy(), a_val.numpy(), mu, mf, mo, r,
                              None if bbox is None else (np.array(bbox[0]), np.array(bbox[1])))
        assert f.tolist() == ref.tolist(), (mu, mf, mo, r, bbox)
        assert len(ref) > 0


# ---------------------------------------------------------------- prune
def test_prune_leaf_tolerance_and_median(backend):
    leaf = cube(8)                      # one OpenVDB leaf (8^3, aligned)
    vals = -np.ones(512, int)
    vals[100] = 0
    g = grid_from(backend, leaf, vals)
    g.prune(0)
    assert g.query(leaf).tolist() == vals.tolist()   # max-min = 1 > 0: unchanged
    g.prune(1)
    assert g.query(leaf).tolist() == [-1] * 512       # collapsed: median -1
    assert g.num_active == 512
    # lower median: 256 x -3 and 256 x -1 -> sorted[(512-1)>>1] = -3
    v2 = np.where(np.arange(512) % 2 == 0, -3, -1)
    g2 = grid_from(backend, leaf + [8, 0, 0], v2)
    g2.prune(1)
    assert g2.query(leaf + [8, 0, 0]).tolist() == v2.tolist()  # spread 2 > 1
    g2.prune(2)
    assert set(g2.query(leaf + [8, 0, 0]).tolist()) == {-3}
    v3 = v2.copy()
    v3[0] = -1                          # 255 x -3, 257 x -1 -> -1
    g3 = grid_from(backend, leaf, v3)
    g3.prune(2)
    assert set(g3.query(leaf).tolist()) == {-1}


def test_prune_partial_leaf_and_mixed_states(backend):
    leaf = cube(8)
    g = grid_from(backend, leaf[:-1], -np.ones(511, int))   # one inactive voxel
    g.prune(5)
    assert g.num_active == 511
    assert g.query(leaf[-1:]).tolist() == [0]
    # unaligned cube spanning 8 leaves: none is full, nothing changes
    c = cube(8, (4, 4, 4))
    vals = np.random.default_rng(3).choice([-1, -2], size=512)
    g = grid_from(backend, c, vals)
    g.prune(3)
    assert g.query(c).tolist() == vals.tolist()


def test_prune_frontiers_tile_shell_and_redensify(backend):
    # two adjacent leaves (16x8x8), values -1/-2 (and one 0) -> two tiles after prune(1)
    blk = np.concatenate([cube(8), cube(8) + [8, 0, 0]])
    blk = np.unique(np.concatenate([blk, cube(8, (0, 8, 0))]), axis=0)  # 3 leaves, L-shape
    rng = np.random.default_rng(4)
    vals = rng.choice([-1, -2], size=len(blk))
    g = grid_from(backend, blk, vals)
    before = g.frontiers(1, 0)
    assert before.tolist() == brute_frontiers(blk, vals, 1, 0).tolist()
    g.prune(2)
    ijk, pv = g.active()
    assert ijk.shape[0] == len(blk)
    assert len(set(pv.tolist())) <= 3 and not np.array_equal(pv.numpy(), vals)
    after = g.frontiers(1, 0)
    assert after.tolist() == brute_frontiers(ijk.numpy(), pv.numpy(), 1, 0).tolist()
    assert after.tolist() == before.tolist()  # still all free: same frontier set
    assert g.frontiers(0, 0).shape[0] == len(blk)   # interior tile voxels are candidates
    assert g.frontiers(5, 3, 0, 2).tolist() == brute_frontiers(ijk.numpy(), pv.numpy(), 5, 3,
                                                               0, 2).tolist()
    # a write inside a tile re-densifies it; other voxels keep the tile value
    tile_val = g.query(np.array([[3, 3, 3]])).item()
    g.update(np.array([[3, 3, 3]]), 6)
    q = g.query(np.array([[3, 3, 3], [3, 3, 4], [0, 0, 0]]))
    assert q.tolist() == [min(tile_val + 6, 30), tile_val, tile_val]
    assert g.num_active == len(blk)


def test_frontiers_bbox_across_tiles_of_every_level(backend):
    """A bbox search visits only the box's leaf-sized chunks: tiles of a 128^3 internal node
    and of single leaves, leaves, negative coordinates and boxes cutting through tiles all
    give the brute-force frontier set of the box."""
    rng = np.random.default_rng(9)
    big = cube(128) + [-128, 0, -128]                   # one level-1 tile after prune
    small = cube(8) + [8, 8, 0]                          # one leaf-sized tile
    speck = rng.integers(-140, 30, size=(4000, 3))     # leaves around them, free and occupied
    speck = speck[~np.isin(speck @ [1 << 40, 1 << 20, 1], np.concatenate([big, small]) @ [1 << 40, 1 << 20, 1])]
    ijk = np.concatenate([big, small, speck])
    vals = np.concatenate([np.full(len(big), -1), np.full(len(small), -2), rng.choice([-1, 3], size=len(speck))])
    g = grid_from(backend, ijk, vals, lo=-5)
    g.prune(0)
    a_ijk, a_val = g.active()
    assert a_ijk.shape[0] == len(ijk)
    boxes = [((-140, -20, -20), (30, 20, 20)),           # across the big tile's face, end to end
             ((-60, 40, -60), (-40, 60, -40)),           # inside the big tile
             ((-3, -3, -3), (12, 12, 4)),                # the big tile's corner, the small tile, leaves
             ((9, 9, 1), (14, 14, 6)),                   # inside the small tile
             ((-200, 100, -200), (-150, 120, -150))]     # empty
    for mu, mf, mo, r in [(1, 0, 0, 1), (0, 0, 0, 1), (4, 2, 0, 2)]:
        for lo, hi in boxes:
            got = g.frontiers(mu, mf, mo, r, (lo, hi))
            ref = brute_frontiers(a_ijk.numpy(), a_val.numpy(), mu, mf, mo, r, (np.array(lo), np.array(hi)))
            assert got.tolist() == ref.tolist(), (mu, mf, mo, r, lo, hi)
    # the interior box with mu = 0 holds every free voxel of it (tile interior emitted directly)
    assert g.frontiers(0, 0, 0, 1, boxes[1]).shape[0] == 21 ** 3
    # a box with far more leaf-sized chunks than the tree has leaves: the tree is iterated
    huge = ((-3000, -3000, -400), (3000, 3000, 400))
    assert g.frontiers(1, 0, 0, 1, huge).tolist() == g.frontiers(1, 0, 0, 1).tolist() == brute_frontiers(
        a_ijk.numpy(), a_val.numpy(), 1, 0, 0, 1).tolist()


@pytest.mark.parametrize("with_hole", [False, True])
def test_prune_internal_node_median_of_medians(backend, with_hole):
    """16^3 leaves (128^3 voxels) collapse into one level-1 tile holding the lower median
    of the 4096 leaf medians; one missing voxel blocks the level-1 collapse only."""
    n = 128
    c = cube(n)
    leaf_id = (c // 8) @ np.array([256, 16, 1])
    # leaf medians: 2048 leaves at -2, 2048 at -1 -> sorted[(4096-1)>>1] = -2 (lower median)
    leaf_val = np.where(np.arange(4096) < 2048, -2, -1)
    vals = leaf_val[leaf_id].copy()
    # perturb voxels within tolerance without changing leaf medians (1 of 512 per leaf)
    vals[(c % 8 == 0).all(1) & (leaf_val[leaf_id] == -2)] = -3
    if with_hole:
        keep = ~(c == [127, 127, 127]).all(1)
        c, vals = c[keep], vals[keep]
    g = grid_from(backend, c, vals, lo=-5)
    g.prune(1)
    q = g.query(c)
    if with_hole:
        lid = (c // 8) @ np.array([256, 16, 1])
        exp = leaf_val[lid].copy()
        last = lid == 4095   # the leaf with the hole stays as it was
        exp[last] = vals[last]
        assert q.numpy().tolist() == exp.tolist()
    else:
        assert set(q.tolist()) == {-2}
    assert g.num_active == len(c)


# ---------------------------------------------------------------- rays
def march(g_vals: dict, o, d, max_dist, vox, h=2e-5):
    """Fine-step march + bisection: (distance, voxel) of the first voxel with value >= 0."""
    ts = np.arange(0.0, max_dist + h, h)
    pts = o[None, :] + ts[:, None] * d[None, :]
    ijk = np.floor(pts / vox).astype(np.int64)
    blocked = np.array([g_vals.get(tuple(v), 0) >= 0 for v in ijk.tolist()])
    if not blocked.any():
        return math.inf, None
    i = int(np.argmax(blocked))
    if i == 0:
        return 0.0, tuple(ijk[0])
    a, b = ts[i - 1], ts[i]
    target = tuple(ijk[i])
    for _ in range(60):
        m = 0.5 * (a + b)
        if tuple(np.floor((o + m * d) / vox).astype(np.int64)) == target:
            b = m
        else:
            a = m
    return b, target


def test_first_blocked_vs_march(backend):
    rng = np.random.default_rng(5)
    vox = 0.1
    box = cube(16, (-8, -8, -8))
    vals = rng.choice([-1, -1, -1, -1, -1, -1, -1, -1, -2, 6, 0], size=len(box))
    keep = rng.random(len(box)) > 0.03     # some never-observed holes
    box, vals = box[keep], vals[keep]
    g = grid_from(backend, box, vals, vox)
    ref_vals = dict(zip(map(tuple, box.tolist()), vals.tolist(), strict=True))
    n = 40
    o = rng.uniform(-0.5, 0.5, size=(n, 3))
    d = rng.normal(size=(n, 3))
    d[:5, 1:] = 0.0        # axis-aligned rays (zero components)
    d[5:10, 2] = 0.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    max_dist = 1.2
    got = g.first_blocked(o, torch.from_numpy(d), max_dist)
    assert got.dtype == torch.float64 and got.shape == (n,)
    hits = 0
    for i in range(n):
        t_ref, v_ref = march(ref_vals, o[i], d[i], max_dist, vox)
        if math.isinf(t_ref):
            assert math.isinf(got[i].item()), i
            continue
        hits += 1
        assert got[i].item() == pytest.approx(t_ref, abs=1e-4), i
        # the voxel just past the reported entry point is the one the march found
        p = o[i] + (got[i].item() + 1e-7) * d[i]
        assert tuple(np.floor(p / vox).astype(int)) == v_ref
    assert hits > n // 2


def test_first_blocked_axis_aligned_exact(backend):
    vox = 0.1
    free = cube(10)
    vals = -np.ones(len(free), int)
    vals[(free == [7, 2, 2]).all(1)] = 3
    g = grid_from(backend, free, vals, vox)
    d = g.first_blocked(np.array([[0.05, 0.25, 0.25]] * 3),
                        np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                        np.float64(5.0))
    assert d[0].item() == pytest.approx(0.65, abs=1e-12)
    assert d[1].item() == pytest.approx(0.65, abs=1e-12)   # directions are normalised
    assert d[2].item() == pytest.approx(0.75, abs=1e-12)   # leaves the free cube at z=1.0
    short = g.first_blocked(np.array([[0.05, 0.25, 0.25]]), np.array([[1.0, 0, 0]]), 0.6)
    assert math.isinf(short[0].item())
    assert g.first_blocked(np.zeros((0, 3)), np.zeros((0, 3)), 1.0).shape == (0,)


# ---------------------------------------------------------------- state
def test_state_round_trip(backend):
    rng = np.random.default_rng(6)
    g = make_occupancy(0.07, -4, 9, backend=backend)
    g.update(rng.integers(-30, 30, size=(5000, 3)), rng.choice([-1, 3], size=5000))
    g.update(cube(8), -1)
    g.prune(1)
    st = g.state()
    assert set(st) == {"vox", "lo", "hi", "ijk", "values"}
    assert st["ijk"].dtype == np.int64 and st["values"].dtype == np.int8
    for target in ["torch"] + (["vdb"] if vdb_available() else []):
        h = from_state(st, backend=target)
        assert (h.vox, h.lo, h.hi) == (0.07, -4, 9)
        ijk1, v1 = g.active()
        ijk2, v2 = h.active()
        assert torch.equal(ijk1, ijk2) and torch.equal(v1, v2)
        assert torch.equal(g.frontiers(4, 2), h.frontiers(4, 2))
    with pytest.raises(ValueError, match="lacks"):
        from_state({"vox": 0.1})
