"""Incremental frontier-table replacement and ray prune / merge equal the full-scan versions.

The references below are the previous whole-table algorithms (kept here as the oracle):
replace_region = drop every key inside the box, append the new cells, sort; prune = keep
the bins whose frontier key is in the table (``isin``); merge = look up every stored bin's
frontier index, concatenate new bins and re-sort the whole store. Checked on random
sequences (values and order of every field) and on a map run with ray tracing (re-cast rays).
"""
import numpy as np
import pytest
import torch

from common.conventions import voxel_center
from semantic_map import cell_keys
from semantic_map.config import map_config
from semantic_map.frontiers import FrontierTable
from semantic_map.map import RayFrontsMap
from semantic_map.ray_frontiers import RayStore
from synthetic_world import World
from tests.support.ray_store_ref import SortedRayStore

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _ref_replace(keys, counts, clo, chi, fine, s, min_fronti):
    if keys.numel():
        c = cell_keys.unpack(keys)
        inside = ((c >= clo) & (c <= chi)).all(1)
        keys, counts = keys[~inside], counts[~inside]
    if fine.numel():
        uk, cnt = torch.unique(cell_keys.pack(torch.div(fine, s, rounding_mode="floor")), return_counts=True)
        keep = cnt > min_fronti
        k = torch.cat([keys, uk[keep]])
        n = torch.cat([counts, cnt[keep]])
        o = torch.argsort(k)
        keys, counts = k[o], n[o]
    return keys, counts


def test_replace_region_matches_full_scan_and_logs_removals():
    g = torch.Generator().manual_seed(1)
    t = FrontierTable(0.3, 3, 2)
    keys = torch.empty(0, dtype=torch.int64)
    counts = torch.empty(0, dtype=torch.int64)
    removed_ref: set[int] = set()
    for step in range(60):
        clo = torch.randint(-12, 6, (3,), generator=g)
        chi = clo + torch.randint(0, 8, (3,), generator=g)
        if step % 7 == 3:
            chi = clo - 1  # empty box
        lo_f, hi_f = clo * 3, chi * 3 + 2
        n = int(torch.randint(0, 400, (1,), generator=g))
        fine = (torch.rand((n, 3), generator=g) * (hi_f - lo_f + 1).clamp_min(1) + lo_f).floor().to(torch.int64)
        fine = fine[((fine >= lo_f) & (fine <= hi_f)).all(1)] if chi[0] >= clo[0] else fine[:0]
        before = set(keys.tolist())
        keys, counts = _ref_replace(keys, counts, clo, chi, fine, 3, 2)
        removed_ref |= before - set(keys.tolist())
        t.replace_region(clo, chi, fine)
        assert torch.equal(t.keys, keys) and torch.equal(t.counts, counts), step
        if step % 5 == 4:
            got = t.take_removed()
            assert got.tolist() == sorted(got.tolist())
            # every key that left the table since the last call is logged (some may be back)
            assert removed_ref <= set(got.tolist()) <= removed_ref | set(keys.tolist()) | before
            removed_ref = set()
    assert len(keys) > 20
    t.load_state(t.state())
    assert t.take_removed() is None and t.take_removed().numel() == 0


#: the previous full-scan prune / sort-based merge
_RefStore = SortedRayStore


def _same_store(a, b):
    for f in a._fields():
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), f


@pytest.mark.parametrize("psi,dtype", [(30.0, torch.float16), (360.0, torch.float32), (7.0, torch.float32)])
def test_ray_store_prune_keys_and_merge_match_full_scan(psi, dtype):
    g = torch.Generator().manual_seed(int(psi))
    new, ref = RayStore(1.2, psi, 6, dtype), _RefStore(1.2, psi, 6, dtype)
    table = torch.unique(cell_keys.pack(torch.randint(-6, 6, (40, 3), generator=g)))
    for _ in range(40):
        # frontiers vanish and appear
        drop = torch.rand(table.numel(), generator=g) < 0.15
        gone = table[drop]
        table = torch.unique(torch.cat([table[~drop], cell_keys.pack(torch.randint(-6, 6, (8, 3), generator=g))]))
        gone = gone[~torch.isin(gone, table)]
        ra = ref.prune(table, requeue=True)
        rb = new.prune_keys(torch.unique(gone), requeue=True)
        assert (ra is None) == (rb is None)
        if ra is not None and rb is not None:
            for x, y in zip(ra, rb, strict=True):
                assert torch.equal(x, y)
        _same_store(ref, new)
        n = int(torch.randint(1, 200, (1,), generator=g))
        fk = table[torch.randint(0, table.numel(), (n,), generator=g)]
        d = torch.nn.functional.normalize(torch.randn((n, 3), generator=g), dim=1)
        fe = torch.randn((n, 6), generator=g)
        w = torch.rand(n, generator=g) + 0.05
        ref.merge(fk, table, d, fe, w)
        new.merge(fk, table, d, fe, w)
        _same_store(ref, new)
    assert len(new) > 30
    with pytest.raises(ValueError):
        new.merge(torch.tensor([cell_keys.pack(torch.tensor([[99, 99, 99]]))[0]]), table, d[:1], fe[:1], w[:1])


@pytest.fixture(scope="module")
def frames():
    w = World.generate(5)
    hw = (48, 64)
    K = w.camera(hw, 90.0)
    g = torch.Generator().manual_seed(0)
    out = []
    for p in w.trajectory("ground", 200, seed=5)[:24]:
        r = w.render(p, K, hw)
        out.append((p, K, r.depth.astype(np.float32), r.rgb, torch.randn(8, 3, 4, generator=g)))
    return out


@pytest.mark.parametrize("kw", [dict(ray_tracing=True), dict(ray_tracing=False, angle_bin_size=360.0)])
def test_map_with_incremental_rays_equals_full_scan(frames, kw):
    cfg = map_config("throughput", dict(depth_limit=12.0, vox_accum_period=2, ray_accum_period=2,
                                        ray_accum_phase=1, **kw))
    a = RayFrontsMap(cfg, 8, "t")
    b = RayFrontsMap(cfg, 8, "t")
    b.ray_store = _RefStore(cfg.beta, cfg.angle_bin_size, 8, b.ray_store.dtype)
    b.fronts.take_removed = lambda: None  # always the full-table prune
    requeued = 0
    orig = a.ray_store.prune_keys

    def counting(gone, requeue):
        nonlocal requeued
        out = orig(gone, requeue)
        requeued += 0 if out is None else out[0].shape[0]
        return out
    a.ray_store.prune_keys = counting
    for f in frames:
        a.integrate(*f)
        b.integrate(*f)
        _same_store(b.ray_store, a.ray_store)
        assert torch.equal(a.fronts.keys, b.fronts.keys)
    a.flush()
    b.flush()
    _same_store(b.ray_store, a.ray_store)
    assert len(a.ray_store) > 0 and a.counters["ray_blocks"] >= 8
    if cfg.ray_tracing:
        assert requeued > 0  # frontiers vanished under rays, which were re-cast
    assert torch.equal(voxel_center(cell_keys.unpack(a.ray_store.fkey), cfg.beta), a.rays().origins)
