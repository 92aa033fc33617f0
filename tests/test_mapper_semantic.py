"""Semantic voxel fusion and pruning; frontier subsampling."""
import torch

from common.conventions import voxel_index
from semantic_map import cell_keys
from semantic_map.frontiers import FrontierTable, subsample
from semantic_map.occupancy import make_occupancy
from semantic_map.semantic_voxels import SemanticVoxels


def test_fusion_equals_bruteforce_weighted_mean_with_removals():
    g = torch.Generator().manual_seed(0)
    sv = SemanticVoxels(0.5, 6)
    allp, allc, allf = [], [], []
    for step in range(12):
        n = int(torch.randint(1, 400, (1,), generator=g))
        x = torch.rand(n, 3, generator=g) * 4 - 2
        c = torch.rand(n, 3, generator=g)
        f = torch.randn(n, 6, generator=g)
        sv.fuse(x, c, f)
        allp.append(x), allc.append(c), allf.append(f)
        if step == 6:  # remove some voxels: they restart from scratch afterwards
            k = sv.keys[::3].clone()
            assert sv.remove(k) == k.numel()
            keys_all = cell_keys.pack(voxel_index(torch.cat(allp).double(), 0.5))
            keep = ~torch.isin(keys_all, k)
            allp, allc, allf = [torch.cat(allp)[keep]], [torch.cat(allc)[keep]], [torch.cat(allf)[keep]]
    P, C, F = torch.cat(allp), torch.cat(allc), torch.cat(allf)
    keys = cell_keys.pack(voxel_index(P.double(), 0.5))
    uk, inv, cnt = torch.unique(keys, return_inverse=True, return_counts=True)
    ref_f = torch.zeros(uk.numel(), 6).index_add_(0, inv, F) / cnt[:, None]
    ref_c = torch.zeros(uk.numel(), 3).index_add_(0, inv, C) / cnt[:, None]
    assert len(sv) == uk.numel()
    rows = sv.index.lookup(uk)
    assert bool((rows >= 0).all())
    torch.testing.assert_close(sv.feat[rows], ref_f, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(sv.rgb[rows], ref_c, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(sv.count[rows], cnt.float())
    assert torch.equal(torch.sort(sv.keys).values, uk)


def test_float16_storage():
    sv = SemanticVoxels(1.0, 4, torch.float16)
    x = torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.3, 0.4], [5.0, 5, 5]])
    f = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0]])
    sv.fuse(x, torch.zeros(3, 3), f)
    assert sv.feat.dtype == torch.float16
    r = sv.index.lookup(cell_keys.pack(torch.tensor([[0, 0, 0]])))
    torch.testing.assert_close(sv.feat[r].float(), torch.tensor([[0.5, 0.5, 0, 0]]))


def test_map_pruning_removes_exactly_voxels_at_or_below_threshold():
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap

    cfg = map_config("default", dict(vox_size=1.0, vox_accum_period=1, sem_pruning_period=1,
                                     occ_pruning_period=-1, sem_pruning_thresh=2, semantic_rays=False))
    m = RayFrontsMap(cfg, 3, occupancy_backend="torch")
    g = torch.Generator().manual_seed(0)
    m.sem.fuse(torch.rand(50, 3, generator=g) * 6, torch.zeros(50, 3), torch.randn(50, 3, generator=g))
    ijk = m.sem.ijk()
    vals = torch.randint(-5, 6, (ijk.shape[0],), generator=g)
    m.occupancy.update(ijk, vals)
    touched = ijk[::2]
    m._pending_prune = [cell_keys.pack(touched)]
    before = set(map(tuple, ijk.tolist()))
    m.prune_semantic()
    after = set(map(tuple, m.sem.ijk().tolist()))
    q = m.occupancy.query(touched)
    removed = {tuple(c) for c, v in zip(touched.tolist(), q.tolist(), strict=True) if v <= 2}
    assert after == before - removed and removed


def test_frontier_subsampling_strict_and_incremental_region():
    fine = torch.tensor([[0, 0, 0], [1, 0, 0], [2, 1, 3], [4, 4, 4], [5, 4, 4], [6, 6, 6], [7, 7, 7], [-1, 0, 0]])
    c, n = subsample(fine, 4, 2)
    assert c.tolist() == [[0, 0, 0], [1, 1, 1]] and n.tolist() == [3, 4]
    # hand-made grid: free slab next to unobserved space
    grid = make_occupancy(1.0, -5, 30, backend="torch")
    free = torch.stack(torch.meshgrid(torch.arange(0, 8), torch.arange(0, 8), torch.arange(0, 3), indexing="ij"),
                       -1).reshape(-1, 3)
    grid.update(free, -1)
    ft = FrontierTable(1.0, 4, 3)
    ft.update(grid, free.min(0).values, free.max(0).values, min_unobserved=9, min_free=4)
    full = subsample(grid.frontiers(9, 4), 4, 3)[0]
    assert torch.equal(cell_keys.unpack(ft.keys), full)
    # extend the free region: incremental update must equal recomputation from scratch
    more = free + torch.tensor([0, 0, 3])
    grid.update(more, -1)
    ft.update(grid, more.min(0).values, more.max(0).values, min_unobserved=9, min_free=4)
    full = subsample(grid.frontiers(9, 4), 4, 3)[0]
    assert torch.equal(cell_keys.unpack(ft.keys), full)


def test_frontier_incremental_random_updates_match_full_recompute():
    g = torch.Generator().manual_seed(2)
    grid = make_occupancy(0.5, -3, 5, backend="torch")
    ft = FrontierTable(0.5, 3, 1)
    for _ in range(6):
        c = torch.randint(-6, 6, (1, 3), generator=g)
        ijk = c + torch.randint(-3, 4, (60, 3), generator=g)
        inc = torch.where(torch.rand(60, generator=g) < 0.8, -1, 4)
        grid.update(ijk, inc)
        ft.update(grid, ijk.min(0).values, ijk.max(0).values, min_unobserved=4, min_free=2, min_occupied=0)
        full = subsample(grid.frontiers(4, 2, 0), 3, 1)[0]
        assert torch.equal(cell_keys.unpack(ft.keys), full)
        # the kept centres (issue 46) follow every change of the table: equal to a fresh computation
        assert len(full) and torch.equal(ft.centres(), (full.to(torch.float32) + 0.5) * 1.5)


def test_frontier_centres_follow_replaced_and_written_keys():
    ft = FrontierTable(0.5, 2, 0)
    ft.keys = cell_keys.pack(torch.tensor([[0, 0, 0], [1, 2, 3]]))
    a = ft.centres()
    a += 100.0                                            # a caller's copy: the table's stays
    assert torch.equal(ft.centres(), torch.tensor([[0.5, 0.5, 0.5], [1.5, 2.5, 3.5]]))
    ft.keys[1] = cell_keys.pack(torch.tensor([[4, 4, 4]]))[0]       # written in place
    assert torch.equal(ft.centres(), torch.tensor([[0.5, 0.5, 0.5], [4.5, 4.5, 4.5]]))
    ft.keys = cell_keys.pack(torch.tensor([[2, 0, 0]]))             # replaced
    assert torch.equal(ft.centres(), torch.tensor([[2.5, 0.5, 0.5]]))
