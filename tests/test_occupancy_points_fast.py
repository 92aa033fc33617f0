"""Occupancy points' clearance from the grid's occupied cells (issue 46): held exactly equal
to reading every cell of each point's window, on random grids, after updates, with both
backends, and to an independent brute force over all occupied cubes."""
from __future__ import annotations

import numpy as np
import pytest

from planning.occupancy_queries import _clearance_brute, occupied_cells, point_states
from semantic_map.occupancy import make_occupancy

VOX = 0.3


def _grid(backend: str, rng) -> object:
    g = make_occupancy(VOX, -5, 30, backend=backend)
    ijk = rng.integers(-15, 15, (3000, 3))
    g.update(ijk, rng.choice([-3, 2], len(ijk)))
    return g


def _independent(g, pts: np.ndarray, radius: float) -> np.ndarray:
    ijk, val = g.active()
    lo = ijk.numpy()[val.numpy() > 0] * VOX
    out = np.full(len(pts), np.inf)
    for n, p in enumerate(pts):
        if len(lo):
            d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - (lo + VOX)), 0), axis=1).min()
            out[n] = d if d <= radius else np.inf
    return out


@pytest.mark.parametrize("backend", ["vdb", "torch"])
def test_clearance_equals_the_window_read_across_updates(backend):
    rng = np.random.default_rng(5)
    g = _grid(backend, rng)
    radius = 1.0
    r = int(np.ceil(radius / VOX))
    for step in range(4):
        pts = rng.uniform(-5, 5, (300, 3))
        pts[:20] = (rng.integers(-15, 15, (20, 3)) + rng.choice([0.0, 0.5, 1.0], (20, 3))) * VOX  # on faces
        st, dist = point_states(g, VOX, pts, radius)
        idx = occupied_cells(g, rebuild=False)
        assert idx is not None and idx.revision == g.revision and len(idx.ijk) > 0   # the index path ran
        assert np.isfinite(dist).sum() > 50
        full = g.occupied()                                     # the kept cells are the grid's
        assert np.array_equal(idx.ijk, full[np.lexsort(full.T[::-1])])
        brute = _clearance_brute(g, VOX, pts, np.floor(pts / VOX).astype(np.int64), r, radius)
        assert np.array_equal(dist, brute)                     # bit for bit, inf where none
        assert np.allclose(np.where(np.isfinite(dist), dist, -1),
                           np.where(np.isfinite(ind := _independent(g, pts, radius)), ind, -1))
        assert (dist[st == 1] == 0).all()
        # the map changes: the cached cells must follow
        ijk = rng.integers(-15, 15, (400, 3))
        g.update(ijk, rng.choice([-20, 20], len(ijk)))
        if step == 2:
            g.prune(2)


def test_clearance_of_a_changed_cell_is_seen_at_once():
    g = make_occupancy(VOX, -5, 30, backend="vdb")
    g.update(np.array([[0, 0, 0]]), 5)
    p = np.array([[0.15 + 0.6, 0.15, 0.15]])
    assert point_states(g, VOX, p, 1.0)[1][0] == pytest.approx(0.45)
    g.update(np.array([[1, 0, 0]]), 5)                          # nearer occupied cube
    assert point_states(g, VOX, p, 1.0)[1][0] == pytest.approx(0.15)
    g.update(np.array([[0, 0, 0], [1, 0, 0]]), -30)             # both freed
    assert point_states(g, VOX, p, 1.0)[1][0] == np.inf


def test_a_large_stale_index_waits_until_window_reads_cost_as_much():
    """Many active voxels (free space) and an index that needs a full rebuild: window reads
    answer first (the same answer), the rebuild comes once they have read a share of the
    grid's active voxels, and later writes are followed from the change log."""
    from planning import occupancy_queries as oq

    g = make_occupancy(VOX, -5, 30, backend="vdb")
    ax = np.arange(-40, 40)
    g.update(np.stack(np.meshgrid(ax, ax, ax[:20], indexing="ij"), -1).reshape(-1, 3), -2)   # 128k free
    g.update(np.array([[0, 0, 0], [5, 5, 5]]), 9)
    pts = np.array([[0.75, 0.1, 0.1], [1.4, 1.4, 1.4]])          # windows of 2 * 9^3 cells
    rounds = 0
    while oq.occupied_cells(g, rebuild=False) is None:
        assert not oq.index_current(g)
        st, d = point_states(g, VOX, pts, 1.0)
        assert d[0] == pytest.approx(0.45) and d[1] == pytest.approx(np.sqrt(3) * 0.1)
        rounds += 1
    assert 15 < rounds < 30                               # 0.25 * 128k / 1458 cells per request: 22
    assert oq.index_current(g)
    g.update(np.array([[1, 0, 0]]), 9)                    # written: followed without a rebuild
    assert not oq.index_current(g)
    assert point_states(g, VOX, pts, 1.0)[1][0] == pytest.approx(0.15) and oq.index_current(g)
    assert oq._OCCUPIED[g].based and len(oq._OCCUPIED[g].ijk) == 3
