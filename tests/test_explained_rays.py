"""Rays the map explains (planning.explained_rays) against the exact geometry of an
occupied box, on both occupancy backends."""
from __future__ import annotations

import numpy as np
import pytest

from planning.explained_rays import explained_rays
from semantic_map.occupancy import make_occupancy, vdb_available
from semantic_map.occupancy.base import OccupancyView

VOX = 0.5
BOX_LO, BOX_HI = np.array([10.0, -2.0, 0.0]), np.array([12.0, 2.0, 3.0])   # voxel-aligned, occupied


def _slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[float, float]:
    """(t_in, t_out) of the line o + t d through the box (t_in > t_out: it misses)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - o) / d, (hi - o) / d
    t0 = np.where(d == 0, np.where((o >= lo) & (o < hi), -np.inf, np.inf), np.minimum(a, b))
    t1 = np.where(d == 0, np.where((o >= lo) & (o < hi), np.inf, -np.inf), np.maximum(a, b))
    return float(t0.max()), float(t1.min())


@pytest.mark.parametrize("backend", ["torch", "vdb"])
def test_rays_meeting_a_mapped_box_are_explained(backend):
    if backend == "vdb" and not vdb_available():
        pytest.fail("the OpenVDB extension is not built (make setup builds it)")
    g = make_occupancy(VOX, backend=backend)
    ii = np.stack(np.meshgrid(*[np.arange(int(a / VOX), int(b / VOX)) for a, b in zip(BOX_LO, BOX_HI)],
                              indexing="ij"), -1).reshape(-1, 3)
    g.update(ii, 5)
    free = np.stack(np.meshgrid(np.arange(-10, 18), np.arange(-10, 10), np.arange(0, 6), indexing="ij"), -1)
    free = free.reshape(-1, 3)
    free = free[~((free * VOX >= BOX_LO) & (free * VOX < BOX_HI)).all(1)]
    g.update(free, -3)                                  # free space around it: free is not "explained"
    rng = np.random.default_rng(3)
    o = rng.uniform([-8, -8, 0.5], [4, 8, 2.5], (400, 3))
    aim = rng.uniform([9, -5, -1], [13, 5, 5], (400, 3))
    d = (aim - o) / np.linalg.norm(aim - o, axis=1, keepdims=True)
    max_m = 25.0
    got = explained_rays(OccupancyView(g), VOX, o, d, max_m)
    want, sure = np.zeros(len(o), bool), np.zeros(len(o), bool)
    for i in range(len(o)):
        t0, t1 = _slab(o[i], d[i], BOX_LO, BOX_HI)
        t0, t1 = max(t0, VOX), min(t1, max_m)
        want[i] = t1 >= t0
        # clear cases only: the line spends a voxel or more inside, or passes a voxel or more clear
        grown = _slab(o[i], d[i], BOX_LO - VOX, BOX_HI + VOX)
        sure[i] = (t1 - t0 >= VOX) if want[i] else (min(grown[1], max_m) < max(grown[0], VOX))
    assert sure.sum() > 300 and want[sure].sum() > 50 and (~want[sure]).sum() > 50
    assert np.array_equal(got[sure], want[sure])
    # past max_m it is not explained: the same rays, stopped short of the box
    assert not explained_rays(OccupancyView(g), VOX, o, d, 2.0).any()


def test_explained_rays_refuses_mismatched_shapes():
    g = make_occupancy(VOX, backend="torch")
    with pytest.raises(ValueError, match="2 ray origins but 1 directions"):
        explained_rays(OccupancyView(g), VOX, np.zeros((2, 3)), np.ones((1, 3)), 5.0)
