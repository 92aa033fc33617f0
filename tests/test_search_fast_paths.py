"""The search's fast paths against brute force on random inputs: 26-connected components
(sparse graph path, including the packable range's edges), instance tracking (sparse overlaps,
per-group reductions), ray support (cell pre-filter) and the candidate pre-ranking."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

import planning.instances as inst
import planning.look_next as ln
import semantic_map
from common.conventions import voxel_center
from semantic_map import kernels


def _bfs_components(ijk: np.ndarray) -> np.ndarray:
    """Brute-force 26-connected labels numbered by each component's lowest (i, j, k)."""
    pts = [tuple(map(int, p)) for p in ijk]
    where = {p: n for n, p in enumerate(pts)}
    comp = [-1] * len(pts)
    offs = [o for o in itertools.product((-1, 0, 1), repeat=3) if o != (0, 0, 0)]
    groups = []
    for n, p in enumerate(pts):
        if comp[n] >= 0:
            continue
        comp[n] = len(groups)
        stack, members = [p], [p]
        while stack:
            q = stack.pop()
            for o in offs:
                r = (q[0] + o[0], q[1] + o[1], q[2] + o[2])
                m = where.get(r)
                if m is not None and comp[m] < 0:
                    comp[m] = comp[n]
                    stack.append(r)
                    members.append(r)
        groups.append(min(members))
    rank = {g: r for r, g in enumerate(sorted(range(len(groups)), key=lambda g: groups[g]))}
    return np.array([rank[c] for c in comp], np.int64)


def _random_voxels(rng, n: int, side: int, spread: int = 0) -> np.ndarray:
    """Distinct voxels: a dense random block, plus (``spread``) a few far away (sparse path)."""
    ijk = rng.integers(0, side, (n, 3))
    if spread:
        far = rng.integers(-spread, spread, (n // 4, 3))
        ijk = np.concatenate([ijk, far, far[: len(far) // 2] + rng.integers(-1, 2, (len(far) // 2, 3))])
    return np.unique(ijk, axis=0)[rng.permutation(len(np.unique(ijk, axis=0)))]


@pytest.fixture(params=["kernel", "numpy"])
def labelling(request):
    """connected_26 with the map's C++ labelling kernel (sets of KERNEL_MIN_VOXELS or more),
    then with the kernels off (the numpy paths: dense grid, split boxes, sorted searches)."""
    if request.param == "kernel":
        assert kernels.available(), f"the C++ kernels are not built: {kernels.IMPORT_ERROR}"
        yield request.param
    else:
        with kernels.disabled():
            yield request.param


@pytest.mark.parametrize("seed", range(6))
def test_connected_26_matches_bfs(seed: int, labelling: str):
    rng = np.random.default_rng(seed)
    ijk = _random_voxels(rng, 600, 12, spread=0 if seed % 2 else 5000)
    assert np.array_equal(inst.connected_26(ijk), _bfs_components(ijk))


_RANGE_ENDS = [[0, 0, (1 << 20) - 1], [0, 1, -(1 << 20)], [0, 0, -(1 << 20)], [0, -1, (1 << 20) - 1],
               [5, (1 << 20) - 1, 0], [6, -(1 << 20), 0], [(1 << 20) - 1, 3, 3], [(1 << 20) - 1, 4, 4],
               [-(1 << 20), 3, 3], [7, 7, 7], [7, 8, 8]]


def test_connected_26_no_edge_across_the_packable_range(labelling: str):
    """Voxels at the range's ends: ``key + delta`` would carry into the next axis there."""
    ijk = np.array(_RANGE_ENDS, np.int64)
    assert np.array_equal(inst.connected_26(ijk), _bfs_components(ijk))


@pytest.mark.parametrize("seed", range(4))
def test_labelling_kernel_on_sorted_keys_matches_bfs(seed: int):
    """The kernel itself (``semantic_map.voxel_components_26``) on any set size, with the
    range's ends mixed in (a neighbouring row past the range must not wrap), and its refusal
    of keys that are not strictly ascending."""
    assert kernels.available(), f"the C++ kernels are not built: {kernels.IMPORT_ERROR}"
    rng = np.random.default_rng(70 + seed)
    ijk = np.unique(np.concatenate([_random_voxels(rng, 40 + 200 * seed, 8, spread=50 * seed),
                                    np.array(_RANGE_ENDS, np.int64)]), axis=0)
    keys = inst.pack_ijk(ijk)
    order = np.argsort(keys)
    got = semantic_map.voxel_components_26(keys[order])
    assert got is not None and got.dtype == np.int64
    assert np.array_equal(got, _bfs_components(ijk[order]))
    with pytest.raises(ValueError, match="strictly ascending"):
        semantic_map.voxel_components_26(keys[order][::-1].copy())
    with pytest.raises(ValueError, match="strictly ascending"):
        semantic_map.voxel_components_26(np.repeat(keys[order][:3], 2))


@pytest.mark.parametrize("threads", [1, 2])
def test_key_order_kernel_equals_numpy_argsort(threads: int):
    """The radix sort (``semantic_map.voxel_key_order``) against ``np.argsort(kind="stable")``:
    shuffled keys of small and of largest 32-bit spans on one and two threads (each pass's
    parts meet at a cut), repeated keys keeping their order, one key, none; refused (None,
    numpy sorts) past 32 bits, where :func:`planning.instances.key_order` is still numpy's."""
    import torch

    assert kernels.available(), f"the C++ kernels are not built: {kernels.IMPORT_ERROR}"
    rng = np.random.default_rng(11)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for hi in [(5, 5, 5), (300, 40, 60), (2047, 2047, 1023), (1, 0, 4_000_000 // 1000)]:
            n = 200_000 if hi[0] > 5 else 100
            ijk = np.stack([rng.integers(-7, -7 + hi[a] + 1, n) for a in range(3)], 1)
            ijk[0], ijk[1] = [-7, -7, -7], [-7 + h for h in hi]          # the whole span
            keys = inst.pack_ijk(ijk)                                    # repeats among them
            got = semantic_map.voxel_key_order(keys)
            want = np.argsort(keys, kind="stable")
            assert got is not None and got[0].dtype == np.int64 and got[1].dtype == np.int64
            assert np.array_equal(got[0], want) and np.array_equal(got[1], keys[want])
        for keys in (np.zeros((0,), np.int64), inst.pack_ijk(np.array([[3, -4, 5]]))):
            got = semantic_map.voxel_key_order(keys)
            assert np.array_equal(got[0], np.arange(len(keys))) and np.array_equal(got[1], keys)
        wide = inst.pack_ijk(np.stack([rng.integers(0, 5000, 300), rng.integers(0, 5000, 300),
                                       rng.integers(0, 5000, 300)], 1))
        assert semantic_map.voxel_key_order(wide) is None
        order, sk = inst.key_order(wide)
        assert np.array_equal(order, np.argsort(wide, kind="stable")) and np.array_equal(sk, np.sort(wide))
    finally:
        torch.set_num_threads(old)


class _ReferenceTracker:
    """The tracking rules (module docstring of planning.instances) with dense (P, C)
    overlaps, per-group loops and brute-force components."""

    def __init__(self, vox: float, min_voxels: int):
        self.vox, self.min_voxels, self.next_id, self.instances = vox, min_voxels, 1, {}

    def update(self, target, ijk, conf, frame):
        lab = _bfs_components(ijk)
        groups = [np.flatnonzero(lab == c) for c in range(int(lab.max()) + 1 if len(lab) else 0)]
        groups = [g for g in groups if len(g) >= self.min_voxels]
        keys = inst.pack_ijk(ijk)
        gsets = [set(keys[g].tolist()) for g in groups]
        prev = self.instances.get(target, [])
        ov = np.array([[len(set(p["keys"]) & s) for s in gsets] for p in prev], np.int64).reshape(len(prev),
                                                                                                  len(groups))
        sizes = np.array([len(g) for g in groups])
        goes_to = [int(np.flatnonzero(r)[np.argmax(sizes[np.flatnonzero(r)])]) if r.any() else -1 for r in ov]
        events, out = [], []
        for j, g in enumerate(groups):
            c = voxel_center(ijk[g], self.vox)
            d = dict(target=target, centroid=c.mean(0), box_min=c.min(0), box_max=c.max(0),
                     confidence=float(conf[g].max()), voxels=len(g), observations=1, first_seen=frame,
                     last_seen=frame, keys=sorted(keys[g].tolist()))
            heirs = sorted((prev[i] for i in range(len(prev)) if goes_to[i] == j),
                           key=lambda p: (p["first_seen"], p["id"]))
            if heirs:
                d.update(id=heirs[0]["id"], first_seen=heirs[0]["first_seen"],
                         observations=heirs[0]["observations"] + (frame != heirs[0]["last_seen"]))
                if len(heirs) > 1:
                    events.append(dict(kind="merge", id=d["id"], target=target, frame=frame,
                                       merged=[h["id"] for h in heirs[1:]]))
                elif len(g) > heirs[0]["voxels"]:
                    events.append(dict(kind="grow", id=d["id"], target=target, frame=frame, voxels=len(g)))
            else:
                d["id"] = self.next_id
                self.next_id += 1
                par = np.flatnonzero(ov[:, j]) if len(prev) else []
                if len(par):
                    events.append(dict(kind="split", id=d["id"], target=target, frame=frame,
                                       parent=prev[par[np.argmax(ov[par, j])]]["id"]))
                else:
                    events.append(dict(kind="new", id=d["id"], target=target, frame=frame))
            out.append(d)
        events += [dict(kind="lost", id=p["id"], target=target, frame=frame) for i, p in enumerate(prev)
                   if not ov[i].any()]
        self.instances[target] = sorted(out, key=lambda d: d["id"])
        return events


@pytest.mark.parametrize("seed", range(4))
def test_tracker_matches_reference(seed: int, labelling: str):
    rng = np.random.default_rng(100 + seed)
    fast, ref = inst.InstanceTracker(0.2, 2), _ReferenceTracker(0.2, 2)
    base = _random_voxels(rng, 500, 11, spread=0 if seed % 2 else 300)
    for frame in range(7):
        if frame != 3:                                         # frame 3: the same voxels again (cached components)
            keep = rng.random(len(base)) < rng.uniform(0.5, 0.95)    # grows, shrinks, splits, merges
        ijk = base[keep]
        conf = rng.random(len(ijk))
        ev = [e.as_dict() for e in fast.update("t", ijk, conf, frame // 2)]
        assert ev == ref.update("t", ijk, conf, frame // 2)
        got, want = fast.current("t"), ref.instances["t"]
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=True):
            assert np.allclose(g.centroid, w["centroid"], rtol=0, atol=1e-9)
            assert np.array_equal(g.box_min, w["box_min"]) and np.array_equal(g.box_max, w["box_max"])
            assert (g.id, g.confidence, g.voxels, g.observations, g.first_seen, g.last_seen) == (
                w["id"], w["confidence"], w["voxels"], w["observations"], w["first_seen"], w["last_seen"])
            assert g.keys.tolist() == w["keys"]


@pytest.mark.parametrize("seed", range(4))
def test_group_kernel_equals_the_numpy_group_step(seed: int):
    """The tracker's group step (kept groups, their order, index sums / minima / maxima and max
    confidence) in C++ (``semantic_map.voxel_instance_groups``) and in numpy, on labelled
    random sets with groups below ``min_voxels`` among them, and on an empty set."""
    assert kernels.available(), f"the C++ kernels are not built: {kernels.IMPORT_ERROR}"
    rng = np.random.default_rng(300 + seed)
    ijk = _random_voxels(rng, 200 + 900 * seed, 14, spread=0 if seed % 2 else 400)
    lone = np.stack([100 + 3 * np.arange(9), np.full(9, 100), np.full(9, -100)], 1)     # groups of one
    keys = np.sort(inst.pack_ijk(np.concatenate([ijk, lone])))
    labels = inst.labels_of_sorted(keys)
    conf = rng.random(len(keys))
    for min_voxels in (1, 3, 20):
        got = semantic_map.voxel_instance_groups(keys, labels, conf, min_voxels)
        with kernels.disabled():
            want = inst._groups(keys, labels, conf, min_voxels)
        assert len(want[3]) > 0 and (min_voxels == 1 or len(want[0]) < len(keys))
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and np.array_equal(g, w)
    empty = np.zeros((0,), np.int64)
    got = semantic_map.voxel_instance_groups(empty, empty, np.zeros(0), 3)
    assert [len(a) for a in got] == [0] * 8


@pytest.mark.parametrize("dense", [True, False])
def test_ray_support_matches_brute_force(dense: bool, monkeypatch):
    if not dense:
        monkeypatch.setattr(ln, "NEAR_DENSE_CELLS", 0)
    rng = np.random.default_rng(7)
    for _ in range(15):
        f = rng.uniform(-40, 40, (int(rng.integers(1, 800)), 3))
        o = rng.uniform(-25, 25, (int(rng.integers(1, 200)), 3))
        o[:5] = f[rng.integers(0, len(f), 5)] + rng.normal(0, 0.7, (5, 3))
        s = rng.random((len(o), 2))
        r = float(rng.uniform(0.3, 4.0))
        d = np.linalg.norm(f[:, None] - o[None], axis=2) <= r
        want = np.stack([np.where(d, s[None, :, t], 0).max(1) for t in range(2)], 1)
        assert np.array_equal(ln.ray_support(f, o, s, r), want)


def test_best_first_is_the_lexsort_prefix():
    rng = np.random.default_rng(3)
    for t in range(200):
        n, k = int(rng.integers(1, 300)), int(rng.integers(0, 350))
        sc = rng.integers(0, 4, n) / 4.0 if t % 2 else rng.random(n)        # many score ties
        d = rng.integers(0, 5, n).astype(float) if t % 3 else rng.random(n)  # distance ties too
        assert np.array_equal(ln._best_first(sc, d, k), np.lexsort((d, -sc))[:k])


def test_candidates_equal_the_three_lexsort_prefixes():
    """Look-next's candidate lists from one pass over the frontiers (issue 46) against each
    list sorted in full: by score, by ray_z, by distance (ties by index throughout)."""
    rng = np.random.default_rng(5)
    compared = 0
    for t in range(300):
        n, k = int(rng.integers(1, 400)), int(rng.integers(1, 80))
        sc = np.where(rng.random(n) < rng.uniform(0, 0.5), rng.integers(1, 4, n) / 4.0, 0.0)   # few > 0, ties
        z = np.where(rng.random(n) < rng.uniform(0, 0.3), rng.random(n), 0.0)
        if t % 7 == 0:
            z[rng.integers(0, n)] = -0.5                         # a negative value: the full path
        d = rng.integers(0, 6, n).astype(float) if t % 2 else rng.random(n)          # distance ties
        got = ln._candidates(sc, z, d, k)
        want = [np.lexsort((d, -sc))[:k], np.lexsort((d, -z))[:k], np.lexsort((d, np.zeros(n)))[:k]]
        for g, w in zip(got, want, strict=True):
            assert np.array_equal(g, w), t
        compared += int(0 < (sc > 0).sum() < k)
    assert compared > 50                                         # the path mixing both parts ran


@pytest.mark.parametrize("seed", range(6))
def test_connected_26_split_into_dense_boxes_matches_bfs(seed: int, monkeypatch, labelling: str):
    """A spread-out set with dense blobs (issue 46: the bench map's cube among a world's
    scattered voxels): the blobs' boxes labelled on dense grids, the rest by sorted searches,
    joined by the edges between them (lines leading out of the blobs, voxels on the boxes'
    faces), against brute force; also blobs whose boxes touch (the split declines)."""
    monkeypatch.setattr(inst, "SPLIT_SHIFT", 2)              # blocks of 4^3 voxels
    monkeypatch.setattr(inst, "SPLIT_DENSE_VOXELS", 12)
    ran = []
    real = inst._split_labels
    monkeypatch.setattr(inst, "_split_labels", lambda ijk: ran.append(real(ijk) is not None) or real(ijk))
    rng = np.random.default_rng(300 + seed)
    parts = []
    for b in range(int(rng.integers(1, 4))):
        at = rng.integers(-40, 40, 3) if seed % 3 else np.array([b * 9, 0, 0])      # seed % 3 == 0: touching
        parts.append(at + np.argwhere(rng.random((9, 9, 9)) < 0.35))
        line = at + np.cumsum(rng.integers(-1, 2, (int(rng.integers(3, 12)), 3)), 0)   # a walk out of the blob
        parts.append(line)
    parts.append(rng.integers(-3000, 3000, (200, 3)))         # scattered far away
    parts.append(rng.integers(-60, 60, (150, 3)))             # scattered near the blobs
    ijk = np.unique(np.concatenate(parts), axis=0)
    ijk = ijk[rng.permutation(len(ijk))]
    assert np.array_equal(inst.connected_26(ijk), _bfs_components(ijk))
    if labelling == "numpy":
        assert ran and (ran[0] if seed % 3 else True)         # the split labelled it (apart from touching boxes)
    else:
        assert not ran                                        # the kernel labelled it whole


def test_connected_26_split_declines_boxes_that_overlap(monkeypatch, labelling: str):
    """An L of dense blocks whose box holds another dense block linked to the L by a chain of
    voxels: two boxes over the same voxels would label the chain twice, apart."""
    monkeypatch.setattr(inst, "SPLIT_SHIFT", 2)
    monkeypatch.setattr(inst, "SPLIT_DENSE_VOXELS", 12)
    cube = np.argwhere(np.ones((4, 4, 4), bool))
    L = [(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0), (0, 1, 0), (0, 2, 0), (0, 3, 0)]
    parts = [cube + 4 * np.array(b) for b in L] + [cube + 4 * np.array((3, 3, 0))]
    parts.append(np.array([[12, y, 2] for y in range(4, 12)]))                # the chain: block (3, 3) to (3, 0)
    parts.append(np.array([[5000, 0, 0], [-5000, 7, 1]]))     # far away: no dense grid for the whole
    ijk = np.unique(np.concatenate(parts), axis=0)
    want = _bfs_components(ijk)
    assert want.max() == 2                                    # the L, the block and its chain, two far voxels
    assert np.array_equal(inst.connected_26(ijk), want)


def test_labelling_kernel_on_two_threads_equals_one_and_numpy():
    """The labelling kernel splits a large set into spans of whole i-slabs, one per thread,
    then joins the edges across the cuts: on a set large enough for two spans (components
    crossing the cut among them) the labels equal one thread's and the numpy path's."""
    from semantic_map import _rfkernels

    assert kernels.available(), f"the C++ kernels are not built: {kernels.IMPORT_ERROR}"
    rng = np.random.default_rng(9)
    ijk = np.unique(rng.integers(0, 90, (260_000, 3)), axis=0)          # ~30 % dense: large components
    keys = np.sort(inst.pack_ijk(ijk))
    one = _rfkernels.components_26_sorted(keys, 1)
    two = _rfkernels.components_26_sorted(keys, 2)
    assert len(keys) >= 2 * 65536 and one.max() > 10
    assert np.array_equal(one, two)
    with kernels.disabled():
        assert np.array_equal(inst.connected_26(inst.unpack_keys(keys)), two)
