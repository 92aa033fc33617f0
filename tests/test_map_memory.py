"""The map's memory: what its estimate counts, and how little spare room its tables hold.

* ``SemanticVoxels.memory_bytes`` equals the bytes of its row tensors at capacity plus the key
  index, computed here from the field sizes; capacity never exceeds the growth policy
  (``need + max(need / 32, 1024)``), checked after every insert of a growing map.
* The ray store keeps at most a ninth of its rows dead and a fifth of its index entries
  tombstones (above the compaction floor), and its
  field reads are copies: writing into them changes nothing stored.
* ``RayFrontsMap.memory_bytes`` is the semantic layers' sum; the occupancy grid is reported apart.
"""
from __future__ import annotations

import numpy as np
import torch

from common.geometry import intrinsics_from_fov
from semantic_map.config import map_config
from semantic_map.map import RayFrontsMap
from semantic_map.ray_frontiers import RayStore
from semantic_map.row_storage import grown_capacity
from semantic_map.semantic_voxels import SemanticVoxels
from synthetic_world.mission import MissionCity


def test_semantic_voxels_memory_is_rows_at_capacity_plus_index():
    c = 24
    sv = SemanticVoxels(0.5, c, torch.float16)
    g = torch.Generator().manual_seed(0)
    n_prev = 0
    for step in range(40):
        xyz = torch.rand((700, 3), generator=g) * 40.0 + step * 7.0   # mostly new voxels, some refused
        sv.fuse(xyz, torch.rand((700, 3), generator=g), torch.randn((700, c), generator=g))
        n, cap = len(sv), sv._count.numel()
        assert n >= n_prev and n <= cap
        assert cap <= max(1024, n + max(n // 32, 1024)), (n, cap)
        n_prev = n
        per_row = 8 + 3 * 2 + c * 2 + 4                  # key, rgb and feature float16, count
        idx = len(sv.index)
        assert idx == n
        index_bytes = 8 * idx + 4 * idx                   # int64 key, int32 row
        assert sv.memory_bytes() == cap * per_row + index_bytes
    assert n_prev > 10 * 1024


def test_grown_capacity_policy():
    assert grown_capacity(100, 50) == 100
    assert grown_capacity(1024, 1025) == 1025 + 1024
    assert grown_capacity(10**6, 10**6 + 1) == 10**6 + 1 + (10**6 + 1) // 32


def test_ray_store_dead_rows_bounded_and_fields_are_copies():
    rs = RayStore(1.0, 30.0, 4)
    g = torch.Generator().manual_seed(1)
    live_keys = torch.empty(0, dtype=torch.int64)
    most_rows = 0
    for step in range(60):
        keys = torch.arange(step * 500, step * 500 + 2000, dtype=torch.int64)   # frontiers move along
        gone = live_keys[live_keys < step * 500]
        if gone.numel():
            rs.prune_keys(gone, requeue=False)
        live_keys = keys
        fk = keys[torch.randint(0, keys.numel(), (3000,), generator=g)]
        d = torch.nn.functional.normalize(torch.randn((3000, 3), generator=g), dim=1)
        rs.merge(fk, keys, d, torch.randn((3000, 4), generator=g), torch.rand(3000, generator=g) + 0.1)
        live = len(rs)
        assert rs._n_dead <= max(RayStore._MIN_COMPACT, live // 8), (rs._n_dead, live)
        assert rs._n_tomb <= max(RayStore._MIN_COMPACT, live // 4), (rs._n_tomb, live)
        most_rows = max(most_rows, rs._n)
        assert rs._rk.shape[0] <= grown_capacity(0, most_rows), (rs._rk.shape[0], most_rows)
    assert live > 0 and most_rows > 2 * RayStore._MIN_COMPACT   # compactions happened
    entries = sum(len(r) for r in rs._runs)
    row_bytes = 8 + 4 + 4 * 4 + 4 + 12 + 1   # key, bin, float32 feature (dim 4), weight, dsum, live
    assert rs.memory_bytes() == rs._rk.shape[0] * row_bytes + entries * (8 + 4 + 4)
    before = rs.state()
    f = rs.feat
    f += 1.0
    rs.weight.zero_()
    after = rs.state()
    for k, v in before.items():
        assert torch.equal(v, after[k]), k


def test_map_memory_is_semantic_layers_occupancy_apart():
    city, hw = MissionCity(0), (48, 64)
    m = RayFrontsMap(map_config("throughput", {"depth_limit": 20.0}), 16, "test")
    K = intrinsics_from_fov(90.0, *hw)
    g = torch.Generator().manual_seed(0)
    for p in city.poses(0, 6, 0.5):
        r = city.render(p, K, hw)
        m.integrate(p, K, r.depth.astype(np.float32), r.rgb, torch.randn(16, 3, 4, generator=g).to(torch.float16))
    m.flush()
    st = m.stats()
    assert st["n_voxels"] > 0 and st["n_rays"] > 0
    parts = m.memory_parts()
    assert parts["frontiers"] == 16 * m.n_frontiers()          # int64 key + int64 count per frontier
    assert parts["voxels"] >= st["n_voxels"] * (8 + 4 + 2 * (3 + 16))  # key, count, float16 rgb + features
    assert parts["rays"] >= st["n_rays"] * (8 + 4 + 4 + 4 * 3 + 2 * 16)  # key, bin, weight, dsum, features
    assert st["memory_bytes"] == sum(parts.values())
    assert st["occupancy_memory_bytes"] == m.occupancy_view().memory_bytes() > 0
