"""Method-fidelity regressions from the audit (issue 14): B1 re-cast direction, B2 cost
modes, B3 subsampling 1, B5 int8 bound of the occupancy weight."""
import math

import pytest
import torch

from mapper import keys as K_
from mapper.ray_frontiers import RayStore, bin_centre_dirs


def _unit(v):
    v = torch.tensor(v, dtype=torch.float32)
    return v / v.norm()


@pytest.mark.parametrize("psi", [360.0, 30.0])
def test_b1_requeue_uses_stored_mean_direction(psi):
    """Re-queued rays of a vanished frontier keep the bin's weighted mean direction, not the
    bin centre (which for the single 360° bin is always +x)."""
    fk = K_.pack(torch.tensor([[3, -2, 1], [0, 0, 5]]))
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


def test_b1_requeue_in_map_keeps_direction():
    """End to end on the map: a spherical-baseline map with ray tracing on re-casts the rays
    of a vanished frontier along their mean direction (audit: 40/40 went along +x)."""
    from mapper.config import map_config
    from mapper.map import RayFrontsMap
    cfg = map_config("online", {"vox_size": 1.0, "ray_tracing": True, "depth_limit": 10.0},
                     "spherical_semfronts")
    m = RayFrontsMap(cfg, 4, occupancy_backend="torch")
    fk = K_.pack(torch.tensor([[2, 5, 0]]))
    m.ray_store.merge(fk, fk, _unit([0.0, 1.0, 0.2])[None], torch.eye(4)[:1], torch.ones(1))
    out = m.ray_store.prune(torch.empty(0, dtype=torch.int64), requeue=True)
    assert out is not None and out[1].shape == (1, 3)
    assert math.degrees(math.acos(float(out[1][0] @ _unit([0.0, 1.0, 0.2])))) < 1e-3
