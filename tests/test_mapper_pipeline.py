"""Two-stage integration (mapper.pipeline) builds exactly the map the sequential path builds.

The synthetic world is rendered at a small size with a 12 m sensor range (so frames carry
out-of-range rays), the throughput and online presets are shrunk to short periods so many
voxel / ray blocks (prunes, re-casts with ray tracing) happen in a few frames, and every
array of the map's state is compared: semantic voxels (keys, rgb, features, counts, in row
order), occupancy (all active cells and values), frontier table, ray store (every field, in
order), counters, pending buffers and the random generator's state.
"""
import gc
import threading
import weakref

import numpy as np
import pytest
import torch

from mapper.pipeline import MapPipeline
from mapper.snapshot import load_map, save_map
from semantic_map.config import map_config
from semantic_map.map import RayFrontsMap
from synthetic_world import World

HW = (48, 64)


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def frames():
    w = World.generate(3)
    poses = w.trajectory("ground", 240, seed=3)[:20]
    K = w.camera(HW, 90.0)
    g = torch.Generator().manual_seed(0)
    out = []
    for p in poses:
        r = w.render(p, K, HW)
        out.append((p, K, r.depth.astype(np.float32), r.rgb, torch.randn(8, 3, 4, generator=g).to(torch.float16)))
    return out


def _cfg(preset, **kw):
    base = dict(depth_limit=12.0, vox_accum_period=2, ray_accum_period=3, ray_accum_phase=1,
                occ_pruning_period=4, sem_pruning_period=4)
    base.update(kw)
    return map_config(preset, base)


def _state(m: RayFrontsMap) -> dict:
    """Every array of the map's exact state (``export_state``: voxels, occupancy, frontiers,
    rays, pending buffers, the generator after the last committed frame) as tensors, and the
    generator after every prepared frame."""
    arrays, _ = m.export_state()
    st = {k: torch.as_tensor(np.asarray(v)) if not isinstance(v, torch.Tensor) else v for k, v in arrays.items()}
    st["rng_prepared"] = m.prepared_rng_state()
    return st


def _assert_same(a: RayFrontsMap, b: RayFrontsMap) -> None:
    assert a.export_state()[1] == b.export_state()[1]       # counters, field of view, buffer counts
    sa, sb = _state(a), _state(b)
    assert {"occ_ijk", "sem_feat", "front_keys", "ray_feat", "rng_state"} <= sa.keys()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert sa[k].shape == sb[k].shape and sa[k].dtype == sb[k].dtype, k
        assert torch.equal(sa[k], sb[k]), k


def _sequential(cfg, frames, skip=()):
    m = RayFrontsMap(cfg, 8, "t")
    for i, f in enumerate(frames):
        if i in skip:
            with pytest.raises(ValueError):
                m.integrate(*f)
            continue
        m.integrate(*f)
    return m


@pytest.mark.parametrize("preset,kw", [("throughput", {}), ("online", {"vox_size": 0.5, "ray_erosion": 2}),
                                       ("throughput", {"ray_tracing": True, "max_empty_pts_per_frame": 500})])
@pytest.mark.parametrize("depth", [1, 3])
def test_pipeline_map_identical_to_sequential(frames, preset, kw, depth):
    cfg = _cfg(preset, **kw)
    ref = _sequential(cfg, frames)
    assert ref.n_rays() > 0 and ref.n_voxels() > 0 and ref.schedule_counters()["ray_blocks"] >= 4
    m = RayFrontsMap(cfg, 8, "t")
    done = []
    with MapPipeline(m, depth=depth) as pp:
        for i, f in enumerate(frames):
            done += pp.submit(*f, tag=i)
            assert len(pp) <= depth
        done += pp.drain()
    assert [c.tag for c in done] == list(range(len(frames)))
    assert all(c.error is None and c.timings["total"] > 0 for c in done)
    _assert_same(ref, m)
    ref.flush()
    m.flush()
    _assert_same(ref, m)


def test_pipeline_bad_frame_reported_and_skipped(frames):
    cfg = _cfg("throughput")
    bad = list(frames[:10])
    p, K, d, rgb, f = bad[4]
    bad[4] = (p, K, d, rgb, torch.randn(5, 3, 4))  # wrong channel count
    bad[7] = (np.eye(4) * 2, K, d, rgb, f)          # not rigid
    ref = _sequential(cfg, bad, skip=(4, 7))
    m = RayFrontsMap(cfg, 8, "t")
    lock = threading.Lock()
    with MapPipeline(m, lock=lock) as pp:
        done = [c for i, fr in enumerate(bad) for c in pp.submit(*fr, tag=i)] + pp.drain()
    errs = {c.tag: c.error for c in done if c.error is not None}
    assert sorted(errs) == [4, 7] and all(isinstance(e, ValueError) for e in errs.values())
    assert "C=8" in str(errs[4]) and "rigid" in str(errs[7])
    _assert_same(ref, m)


def test_prepare_commit_equals_integrate_and_prepare_leaves_map_alone(frames):
    cfg = _cfg("throughput")
    a = RayFrontsMap(cfg, 8, "t")
    b = RayFrontsMap(cfg, 8, "t")
    for f in frames[:6]:
        a.integrate(*f)
        before = _state(b)
        prep = b.prepare(*f)
        after = _state(b)
        moved = {"rng_state", "rng_prepared"}                                      # only the generator moved
        assert all(torch.equal(before[k], after[k]) for k in before if k not in moved)
        tm = b.commit(prep)
        assert {"validate", "geometry", "sample", "commit", "total"} <= set(tm)
    _assert_same(a, b)


def test_pipeline_rejects_use_after_close(frames):
    m = RayFrontsMap(_cfg("throughput"), 8, "t")
    pp = MapPipeline(m)
    pp.submit(*frames[0])
    assert [c.error for c in pp.close()] == [None]
    assert m.schedule_counters()["frames"] == 1
    with pytest.raises(RuntimeError):
        pp.submit(*frames[1])
    with pytest.raises(ValueError):
        MapPipeline(m, depth=0)


def test_snapshot_with_frames_in_flight_equals_sequential(frames, tmp_path):
    """A snapshot taken while a prepared frame waits saves the state after the last committed
    frame (generator included), and the restored map continues exactly like the sequential one."""
    cfg = _cfg("throughput", max_empty_pts_per_frame=500)
    ref = _sequential(cfg, frames[:9])
    m = RayFrontsMap(cfg, 8, "t")
    with MapPipeline(m, depth=2) as pp:
        for f in frames[:11]:
            pp.submit(*f)
        assert len(pp) == 2 and m.schedule_counters()["frames"] == 9
        pp._inflight[-1][1].result()  # both in-flight prepares have drawn their random numbers
        assert not torch.equal(m.prepared_rng_state(), ref.prepared_rng_state())
        assert torch.equal(m.rng_state(), ref.prepared_rng_state())
        save_map(m, tmp_path / "snap")
        closed = weakref.ref(pp)
    del pp
    gc.collect()
    assert closed() is None                  # the closed pipeline let go of the map's rng state
    assert torch.equal(m.rng_state(), m.prepared_rng_state())
    restored = load_map(tmp_path / "snap", RayFrontsMap)
    _assert_same(ref, restored)
    for f in frames[9:]:
        ref.integrate(*f)
        restored.integrate(*f)
    _assert_same(ref, restored)
