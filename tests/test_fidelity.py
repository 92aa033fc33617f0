"""Method-fidelity regressions (docs/method.md): re-cast direction, cost scales,
subsampling 1, int8 bound of the occupancy weight."""
import math

import pytest
import torch

from semantic_map import cell_keys
from semantic_map.ray_frontiers import RayStore, bin_centre_dirs


def _unit(v):
    v = torch.tensor(v, dtype=torch.float32)
    return v / v.norm()


@pytest.mark.parametrize("psi", [360.0, 30.0])
def test_requeue_uses_stored_mean_direction(psi):
    """Re-queued rays of a vanished frontier keep the bin's weighted mean direction, not the
    bin centre (which for the single 360° bin is always +x)."""
    fk = cell_keys.pack(torch.tensor([[3, -2, 1], [0, 0, 5]]))
    fk, _ = torch.sort(fk)
    rs = RayStore(beta=2.0, psi=psi, feature_dim=4)
    d = torch.stack([_unit([0.1, 1.0, 0.05]), _unit([-0.1, 1.0, 0.1]), _unit([0.0, -0.3, 1.0])])
    f = torch.eye(4)[:3]
    w = torch.tensor([1.0, 3.0, 2.0])
    keys = torch.stack([fk[0], fk[0], fk[1]])
    rs.merge(keys, fk, d, f, w)
    assert len(rs) == 2                           # one bin per frontier in both cases
    out = rs.prune(fk[1:], requeue=True)          # frontier fk[0] vanishes
    assert out is not None
    o, dd, feats = out
    assert dd.shape == (1, 3)
    want = (d[0] * 1.0 + d[1] * 3.0)
    want = want / want.norm()
    assert torch.allclose(dd[0], want, atol=1e-6)
    # the old behaviour (bin centre) differs by far more than the tolerance
    tb = rs.tbin.new_zeros(1) if psi >= 360 else None
    if tb is not None:
        assert torch.allclose(bin_centre_dirs(tb, tb, psi)[0], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)
        assert float(dd[0] @ torch.tensor([1.0, 0.0, 0.0])) < 0.1
    assert torch.allclose(feats[0], (f[0] * 1 + f[1] * 3) / 4)
    # the surviving bin is untouched
    assert len(rs) == 1 and int(rs.fkey[0]) == int(fk[1])


def test_requeue_in_map_keeps_direction():
    """End to end on the map: a spherical-baseline map with ray tracing on re-casts the rays
    of a vanished frontier along their mean direction (the bin centre sent every one along +x)."""
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    cfg = map_config("online", {"vox_size": 1.0, "ray_tracing": True, "depth_limit": 10.0},
                     "spherical_semfronts")
    m = RayFrontsMap(cfg, 4, occupancy_backend="torch")
    fk = cell_keys.pack(torch.tensor([[2, 5, 0]]))
    m.ray_store.merge(fk, fk, _unit([0.0, 1.0, 0.2])[None], torch.eye(4)[:1], torch.ones(1))
    out = m.ray_store.prune(torch.empty(0, dtype=torch.int64), requeue=True)
    assert out is not None and out[1].shape == (1, 3)
    assert math.degrees(math.acos(float(out[1][0] @ _unit([0.0, 1.0, 0.2])))) < 1e-3


# --------------------------------------------------------------------------- cost modes
def _one_ray():
    o = torch.zeros(1, 3, dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    return o, d


def test_paper_cost_lone_candidate_and_second_candidate():
    """Paper mode: a lone candidate costs 1; a worse second candidate lowers the chosen one's
    cost (its weight jumps from the 0.05 floor). Absolute mode: the chosen cost is the same
    hand-computed value with or without the second candidate."""
    from semantic_map.ray_frontiers import associate
    beta, D = 2.0, 40.0
    o, d = _one_ray()
    near = torch.tensor([[3, 0, 0]])                  # centre (7, 1, 1): d_ortho = sqrt(2), d_orig = sqrt(51)
    far = torch.tensor([[8, 0, 0]])                   # centre (17, 1, 1)
    both = torch.cat([near, far])
    _, f1, c1 = associate(o, d, near, beta, max_dist=D, cost="paper")
    _, f2, c2 = associate(o, d, both, beta, max_dist=D, cost="paper")
    assert f1.tolist() == [0] and float(c1[0]) == 1.0
    assert f2.tolist() == [0] and float(c2[0]) < 0.8       # changed by an unrelated candidate
    want = (math.sqrt(2) / beta + math.sqrt(51) / D) / 2
    _, a1, e1 = associate(o, d, near, beta, max_dist=D, cost="absolute")
    _, a2, e2 = associate(o, d, both, beta, max_dist=D, cost="absolute")
    assert a1.tolist() == [0] and a2.tolist() == [0]
    assert abs(float(e1[0]) - want) < 1e-6 and float(e1[0]) == float(e2[0])


def test_absolute_cost_can_pick_a_different_frontier():
    """The two scales rank candidates differently. Ray from (0, .4, .4) along +x, beta 1,
    max_dist 100: A = centre (2.5, .5, -.5) (d_ortho .906, d_orig 2.658), B = centre
    (29.5, .5, .5) (d_ortho .141, d_orig 29.5). Paper: A (1 + .090)/2 = .545 < B (.156 + 1)/2
    = .578 -> A. Absolute: A (.906 + .027)/2 = .466 > B (.141 + .295)/2 = .218 -> B."""
    from semantic_map.ray_frontiers import associate
    o = torch.tensor([[0.0, 0.4, 0.4]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    fr = torch.tensor([[2, 0, -1], [29, 0, 0]])
    _, pf, pc = associate(o, d, fr, 1.0, max_dist=100.0, cost="paper")
    _, af, ac = associate(o, d, fr, 1.0, max_dist=100.0, cost="absolute")
    a_orig = math.sqrt(2.5 ** 2 + 0.1 ** 2 + 0.9 ** 2)
    b_ortho, b_orig = math.hypot(0.1, 0.1), math.sqrt(29.5 ** 2 + 0.02)
    assert pf.tolist() == [0] and af.tolist() == [1]
    assert float(pc[0]) == pytest.approx((1 + a_orig / b_orig) / 2, abs=1e-6)
    # float32 pair metrics (d_ortho² = v·v - t², cancellation at 30 m): ~1e-4 absolute
    assert float(ac[0]) == pytest.approx((b_ortho + b_orig / 100.0) / 2, abs=1e-3)


@pytest.mark.parametrize("seed,beta,max_dist,close", [(0, 1.0, 15.0, False), (1, 0.5, 8.0, True),
                                                      (2, 2.0, -1.0, False)])
def test_absolute_cost_kernel_torch_bruteforce_identical(seed, beta, max_dist, close):
    from semantic_map import kernels
    from semantic_map.ray_frontiers import associate, associate_bruteforce
    g = torch.Generator().manual_seed(seed)
    fr = torch.unique(torch.randint(-12, 12, (500, 3), generator=g), dim=0)
    o = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * 8
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=1)
    assert kernels.available(), f"semantic_map._rfkernels not built: {kernels.IMPORT_ERROR}"
    k = associate(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost="absolute")
    with kernels.disabled():
        t = associate(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost="absolute")
    ref = associate_bruteforce(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost="absolute")
    paper = associate_bruteforce(o, d, fr, beta, max_dist=max_dist, reject_close=close, cost="paper")
    assert t[0].numel() > 20
    for a, b in ((k, t), (t, ref)):
        for x, y in zip(a, b, strict=True):
            assert x.dtype == y.dtype and torch.equal(x, y)
    # same candidate sets, different costs
    assert torch.equal(ref[0], paper[0]) and not torch.equal(ref[2], paper[2])
    if max_dist > 0:
        assert float(ref[2].max()) <= 1.0


def test_map_weights_absolute_no_floor():
    """Map level: absolute mode stores 1 - c (no 0.05 floor); paper mode floors lone candidates."""
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    ws = {}
    for mode in ("paper", "absolute"):
        cfg = map_config("online", {"vox_size": 1.0, "depth_limit": 10.0, "ray_tracing": False,
                                    "ray_cost_norm": mode})
        m = RayFrontsMap(cfg, 4, occupancy_backend="torch")
        m.fronts.keys = torch.sort(cell_keys.pack(torch.tensor([[2, 0, 0]])))[0]     # beta = 4: centre (10, 2, 2)
        o, d = _one_ray()
        d = torch.nn.functional.normalize(torch.tensor([[10.0, 2.0, 1.0]], dtype=torch.float64), dim=1)
        m._cast(o, d.to(torch.float32), torch.eye(4)[:1], 0.0)
        ws[mode] = float(m.ray_store.weight.sum())
    assert ws["paper"] == pytest.approx(0.05)
    v = torch.tensor([10.0, 2.0, 2.0], dtype=torch.float64)
    dd = d[0]
    t = float(v @ dd)
    ortho = math.sqrt(max(float(v @ v) - t * t, 0.0))
    want = 1 - (ortho / 4.0 + float(v.norm()) / 40.0) / 2
    assert ws["absolute"] == pytest.approx(want, rel=1e-5)


# --------------------------------------------------------------------------- subsampling 1, occupancy weight
def _frontier_frames():
    from common.geometry import intrinsics_from_fov, look_at
    K = intrinsics_from_fov(90.0, 32, 32)
    pose = look_at([0.0, 0.0, 0.0], [5.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    depth = torch.full((32, 32), float("inf"))
    depth[:, :10] = 4.0                               # a wall on one side, open space elsewhere
    return pose, K, depth


def test_subsampling_one_keeps_every_fine_frontier():
    """fronti_subsampling=1 with the default min_fronti (12) gave 0 frontiers silently; now,
    as the reference, subsampling is skipped at 1 and every fine frontier voxel is a frontier."""
    import numpy as np

    from semantic_map.config import map_config
    from semantic_map.frontiers import subsample
    from semantic_map.map import RayFrontsMap
    fine = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 0, 0], [5, 5, 5]])
    ijk, cnt = subsample(fine, 1, 12)
    assert sorted(ijk.tolist()) == [[0, 0, 0], [1, 0, 0], [5, 5, 5]] and cnt.tolist() == [1, 2, 1]
    pose, K, depth = _frontier_frames()
    counts = {}
    for s in (1, 2):
        cfg = map_config("default", {"vox_size": 0.5, "fronti_subsampling": s, "depth_limit": 6.0,
                                     "vox_accum_period": 1})
        assert cfg.fronti_subsampling_min_fronti == 12
        m = RayFrontsMap(cfg, 4, occupancy_backend="torch")
        m.integrate(np.asarray(pose), np.asarray(K), depth, features=torch.ones(4, 32, 32))
        m.flush()
        counts[s] = len(m.fronts)
        fine_n = len(m.occupancy.frontiers(cfg.fronti_min_unobserved, cfg.fronti_min_empty,
                                           cfg.fronti_min_occupied, cfg.fronti_neighborhood_r))
        if s == 1:
            assert fine_n > 0 and counts[1] == fine_n
    assert counts[1] > counts[2] >= 0


def test_occ_observ_weight_names_the_int8_bound():
    from common.config import ConfigError
    from semantic_map.config import map_config
    with pytest.raises(ConfigError, match=r"occ_observ_weight must be in 1\.\.128 .*int8.*got 200"):
        map_config("default", {"occ_observ_weight": 200})
    with pytest.raises(ConfigError, match="occ_observ_weight"):
        map_config("default", {"occ_observ_weight": 0})
    # the bound itself is usable: a voxel block with increment +127 runs
    import numpy as np

    from semantic_map.map import RayFrontsMap
    cfg = map_config("default", {"occ_observ_weight": 128, "max_occ_cnt": 127, "vox_accum_period": 1,
                                 "depth_limit": 6.0, "vox_size": 0.5})
    m = RayFrontsMap(cfg, 4, occupancy_backend="torch")
    pose, K, depth = _frontier_frames()
    m.integrate(np.asarray(pose), np.asarray(K), depth, features=torch.ones(4, 32, 32))
    ijk, vals = m.occupancy.active()
    assert int(torch.as_tensor(vals).max()) == 127


def test_srchvol_variants_are_rayfronts_with_overrides():
    """eval srchvol variants (the cost-scale ablation): RayFronts' map config plus the overrides, at
    every depth RayFronts runs (zero-depth mode at 0 m); names may not shadow a method."""
    from apps.evaluation.srchvol import SrchvolConfig, method_map_config
    from common.config import ConfigError, merge
    cfg = merge(SrchvolConfig(), {"variants": {"rf_abs": {"ray_cost_norm": "absolute"}}}).validate()
    assert cfg.all_methods()[-1] == "rf_abs" and cfg.all_methods()[:-1] == cfg.methods
    for d in (0.0, 10.0, 20.0):
        a, b = method_map_config(cfg, "rf_abs", d, 96), method_map_config(cfg, "rayfronts", d, 96)
        assert a.ray_cost_norm == "absolute" and b.ray_cost_norm == "paper"
        assert a.zero_depth_mode == b.zero_depth_mode == (d == 0.0)
        assert {k: v for k, v in a.__dict__.items() if k != "ray_cost_norm"} == \
            {k: v for k, v in b.__dict__.items() if k != "ray_cost_norm"}
    with pytest.raises(ConfigError, match="variant"):
        merge(SrchvolConfig(), {"variants": {"rayfronts": {"ray_cost_norm": "absolute"}}}).validate()
