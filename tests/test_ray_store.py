"""The append-only ray store (rows + tombstones + sorted index runs) equals the sorted-array
store it replaced (:class:`tests.support.ray_store_ref.SortedRayStore`, full scans and a
re-sort per merge) on random sequences of merges, prunes, direction overwrites and
state round trips: every field of the canonical view (values, dtypes and order), the
re-cast rays of every prune, origins and directions. Compaction thresholds are lowered so
that row compaction, index compaction, run merges and revived bins all occur."""
import pytest
import torch

from semantic_map import cell_keys, kernels
from semantic_map.ray_frontiers import RayStore, associate, associate_near, frontiers_in_box
from tests.support.ray_store_ref import SortedRayStore

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _same(ref, new):
    assert len(ref) == len(new)
    for f in ref._fields():
        x, y = getattr(ref, f), getattr(new, f)
        assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), f
    assert torch.equal(ref.origins(), new.origins())
    assert torch.equal(ref.directions(), new.directions())


def _same_out(a, b):
    assert (a is None) == (b is None)
    if a is not None and b is not None:
        for x, y in zip(a, b, strict=True):
            assert x.dtype == y.dtype and torch.equal(x, y)


class _Counting(RayStore):
    """RayStore with low compaction thresholds that records what its bookkeeping did."""
    _MIN_COMPACT = 8

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.seen = dict(row_compactions=0, index_compactions=0, revived=0, max_runs=0)

    def _compact_rows(self):
        self.seen["row_compactions"] += 1
        super()._compact_rows()

    def _compact_index(self):
        if len(self._runs) > 1 or self._n_tomb:
            self.seen["index_compactions"] += 1
        super()._compact_index()

    def _add_run(self, run):
        super()._add_run(run)
        self.seen["max_runs"] = max(self.seen["max_runs"], len(self._runs))


def _rays(g, table, n, dim):
    fk = table[torch.randint(0, table.numel(), (n,), generator=g)]
    d = torch.nn.functional.normalize(torch.randn((n, 3), generator=g), dim=1)
    return fk, d, torch.randn((n, dim), generator=g), torch.rand(n, generator=g) + 0.05


@pytest.mark.parametrize("psi,dtype,seed", [(30.0, torch.float16, 0), (360.0, torch.float32, 1),
                                            (7.0, torch.float32, 2)])
def test_store_equals_sorted_reference(psi, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    dim = 5
    ref, new = SortedRayStore(1.2, psi, dim, dtype), _Counting(1.2, psi, dim, dtype)
    table = torch.unique(cell_keys.pack(torch.randint(-5, 5, (60, 3), generator=g)))
    for step in range(60):
        # frontiers vanish (most come back later: the key range is small) and appear
        drop = torch.rand(table.numel(), generator=g) < 0.2
        table = torch.unique(torch.cat([table[~drop], cell_keys.pack(torch.randint(-5, 5, (10, 3), generator=g))]))
        requeue = bool(step % 3)
        if step % 11 == 5:  # history unknown: full-table prune
            _same_out(ref.prune(table, requeue), new.prune(table, requeue))
        else:
            gone = torch.unique(ref.fkey[~torch.isin(ref.fkey, table)])
            _same_out(ref.prune_keys(gone, requeue), new.prune_keys(gone, requeue))
        _same(ref, new)
        fk, d, fe, w = _rays(g, table, int(torch.randint(1, 150, (1,), generator=g)), dim)
        n0 = len(new)
        ref.merge(fk, table, d, fe, w)
        new.merge(fk, table, d, fe, w)
        assert len(new) >= n0
        if step % 7 == 3:  # unidirectional baseline: overwrite the directions of some frontiers
            uk = torch.unique(ref.fkey)[::2].contiguous()
            dirs = torch.nn.functional.normalize(torch.randn((uk.numel(), 3), generator=g), dim=1)
            ref.set_frontier_directions(uk, dirs)
            new.set_frontier_directions(uk, dirs)
        if step % 13 == 12:  # snapshot round trip, then keep going from the loaded store
            st = new.state()
            for f, t in ref.state().items():
                assert torch.equal(st[f], t), f
            seen = new.seen
            new = _Counting(1.2, psi, dim, dtype)
            new.load_state(st)
            new.seen = seen
        if step % 2:
            _same(ref, new)   # reading the view between steps must not change what follows
    _same(ref, new)
    assert len(new) > 40
    s = new.seen
    assert s["row_compactions"] > 0 and s["index_compactions"] > 0 and s["max_runs"] >= 2, s


def test_revived_bin_reuses_its_entry_and_merge_appends():
    """A pruned bin that comes back is fused from scratch (its old value is gone); a merge
    writes new bins after the existing rows and leaves those rows' storage in place."""
    rs = RayStore(2.0, 360.0, 2)
    keys = cell_keys.pack(torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0]]))
    x = torch.tensor([[1.0, 0.0, 0.0]])
    rs.merge(keys[:1], keys, x, torch.tensor([[1.0, 1.0]]), torch.ones(1))
    rs.merge(keys[1:2], keys, x, torch.tensor([[3.0, 3.0]]), torch.ones(1))
    ptr = rs._rf.data_ptr()
    rs.prune_keys(keys[:1], requeue=False)
    assert rs._n_tomb == 1 and len(rs) == 1
    rs.merge(keys[:1], keys, x, torch.tensor([[5.0, 7.0]]), torch.tensor([0.5]))
    assert rs._n_tomb == 0 and rs._rf.data_ptr() == ptr
    assert rs.fkey.tolist() == keys[:2].tolist()
    assert rs.feat.tolist() == [[5.0, 7.0], [3.0, 3.0]] and rs.weight.tolist() == [0.5, 1.0]
    with pytest.raises(ValueError):
        rs.load_state({"fkey": keys[[0, 0]], "tbin": torch.zeros(2, dtype=torch.int64),
                       "pbin": torch.zeros(2, dtype=torch.int64), "feat": torch.zeros((2, 2)),
                       "weight": torch.ones(2), "dsum": torch.zeros((2, 3))})


@pytest.mark.parametrize("cost,kern", [("paper", True), ("absolute", True), ("paper", False)])
def test_association_within_the_rays_box_equals_the_whole_table(cost, kern):
    """Rays cast against the frontiers of the origins' box grown by max_dist (``frontiers_in_box``):
    same pairs, frontiers and costs as against the whole table; the box selection equals a
    brute-force box test over all keys."""
    g = torch.Generator().manual_seed(3)
    beta, max_dist = 1.5, 9.0
    keys = torch.unique(cell_keys.pack(torch.randint(-25, 25, (8000, 3), generator=g)))
    ijk = cell_keys.unpack(keys)
    # three camera positions (a ray block), 100 rays each
    o = ((torch.rand((3, 3), generator=g, dtype=torch.float64) - 0.5) * 4.0).repeat_interleave(100, 0)
    d = torch.nn.functional.normalize(torch.randn((300, 3), generator=g), dim=1)
    near = frontiers_in_box(keys, o.min(0).values - max_dist, o.max(0).values + max_dist, beta)
    lo = torch.floor((o.min(0).values - max_dist) / beta).to(torch.int64) - 1
    hi = torch.floor((o.max(0).values + max_dist) / beta).to(torch.int64) + 1
    box = torch.nonzero(((ijk >= lo) & (ijk <= hi)).all(1)).squeeze(1)
    assert torch.equal(near, box) and 0 < near.numel() < keys.numel() // 10
    old = kernels.set_enabled(kern)
    try:
        full = associate(o, d, ijk, beta, max_dist=max_dist, cost=cost)
        part = associate(o, d, ijk[near], beta, max_dist=max_dist, cost=cost)
    finally:
        kernels.set_enabled(old)
    assert full[0].numel() > 150
    assert torch.equal(full[0], part[0]) and torch.equal(full[1], near[part[1]]) and torch.equal(full[2], part[2])


@pytest.mark.parametrize("cost,kern", [("paper", True), ("absolute", True), ("paper", False)])
def test_association_per_origin_group_equals_the_whole_table(cost, kern):
    """Rays from scattered origins (a ray block's new rays plus rays re-queued from frontiers
    pruned anywhere on the map): cast per origin group against each group's nearby frontiers,
    the pairs, frontiers and costs equal casting all rays against the whole table; one tight
    cluster takes the one-group path and equals it too."""
    g = torch.Generator().manual_seed(5)
    beta, max_dist = 1.5, 6.0
    keys = torch.unique(cell_keys.pack(torch.randint(-50, 50, (60000, 3), generator=g)))
    ijk = cell_keys.unpack(keys)
    spread = ((torch.rand((7, 3), generator=g, dtype=torch.float64) - 0.5) * 140.0).repeat_interleave(60, 0)
    tight = ((torch.rand((3, 3), generator=g, dtype=torch.float64) - 0.5) * 3.0).repeat_interleave(60, 0)
    for o in (spread, tight):
        d = torch.nn.functional.normalize(torch.randn((o.shape[0], 3), generator=g), dim=1)
        old = kernels.set_enabled(kern)
        try:
            full = associate(o, d, ijk, beta, max_dist=max_dist, cost=cost)
            part = associate_near(o, d, keys, beta, max_dist, cost=cost)
        finally:
            kernels.set_enabled(old)
        assert full[0].numel() > o.shape[0] // 6
        assert torch.equal(full[0], part[0]) and torch.equal(full[1], part[1]) and torch.equal(full[2], part[2])
    with pytest.raises(ValueError):
        associate_near(spread, d[:1].expand(spread.shape[0], 3), keys, beta, 0.0)
