"""Mapper shards: the client-side merge of several shards' answers (query_client.merge), the
shard region filter (mapper.shards) and, with real processes on loopback, two shards that
answer like one mapper holding the whole map."""
from __future__ import annotations

import numpy as np
import pytest

from common.cones import cone_union_volume
from common.fleet import decode_shard_info, encode_shard_info
from common.messages import QueryResult
from query_client.merge import merge_results


def _res(clusters, voxels, rays, frames=1, vol=0.0):
    r = QueryResult(id="q", query="x", frames_mapped=frames, search_volume_m3=vol)
    if clusters:
        r.cluster_xyz = np.array([c[0] for c in clusters], np.float32)
        r.cluster_size = np.array([c[1] for c in clusters], np.int32)
        r.cluster_extent = np.array([c[2] for c in clusters], np.float32)
        r.cluster_score = np.array([c[3] for c in clusters], np.float32)
    if voxels:
        r.voxel_xyz = np.array([v[0] for v in voxels], np.float32)
        r.voxel_score = np.array([v[1] for v in voxels], np.float32)
    if rays:
        r.ray_origin = np.array([x[0] for x in rays], np.float32)
        r.ray_direction = np.array([x[1] for x in rays], np.float32)
        r.ray_score = np.array([x[2] for x in rays], np.float32)
    return r.validate()


INFO = {"half_angle_deg": 10.0, "search_range_m": 50.0, "search_cell_m": 1.0, "search_samples": 50_000,
        "search_rays": 3, "cluster_rel_score": 0.9, "vox_size": 1.0}


def test_merge_ranks_thresholds_unions_and_recomputes_volume():
    a = _res([((0, 0, 0), 4, (2, 2, 2), 0.9), ((10, 0, 0), 1, (1, 1, 1), 0.6)],
             [((0, 0, 0), 0.9), ((10, 0, 0), 0.6)],
             [((0, 0, 0), (1, 0, 0), 0.8), ((0, 0, 0), (0, 1, 0), 0.3)], frames=3, vol=100.0)
    # shard b: the same object across the border (box touches a's first cluster), and a weak one
    b = _res([((1.5, 0, 0), 2, (1, 1, 1), 0.95), ((30, 0, 0), 1, (1, 1, 1), 0.2)],
             [((1.5, 0, 0), 0.95)],
             [((5, 5, 0), (0, 0, 1), 0.85)], frames=2, vol=200.0)
    ia = dict(INFO, shard="a", score_min=0.1)
    ib = dict(INFO, shard="b", score_min=0.0)
    m = merge_results([(a, ia), (b, ib)], top_k=5)
    assert m.frames_mapped == 5
    np.testing.assert_allclose(m.voxel_score, [0.95, 0.9, 0.6])
    # threshold over both shards: 0 + 0.9 * (0.95 - 0) = 0.855 -> the two touching clusters, merged
    assert len(m.cluster_score) == 1 and m.cluster_score[0] == pytest.approx(0.95)
    assert m.cluster_size[0] == 6
    np.testing.assert_allclose(m.cluster_xyz[0], [(0 * 4 + 1.5 * 2) / 6, 0, 0], atol=1e-6)
    np.testing.assert_allclose(m.cluster_extent[0], [3.0, 2, 2])      # box union -1..2
    np.testing.assert_allclose(m.ray_score, [0.85, 0.8, 0.3])
    want = cone_union_volume(m.ray_origin[:3], m.ray_direction[:3], 10.0, 50.0, 1.0, max_cells=50_000)
    assert m.search_volume_m3 == pytest.approx(want) and want > 200.0
    # one reply: returned as it is
    assert merge_results([(a, ia)], 5) is a


def test_merge_without_info_and_empty_shards():
    a = _res([((0, 0, 0), 1, (1, 1, 1), 0.5)], [((0, 0, 0), 0.5)], [], vol=7.0)
    empty = QueryResult(id="q", query="x")
    m = merge_results([(a, {}), (empty, {})], top_k=3)
    assert len(m.cluster_score) == 1 and m.search_volume_m3 == 7.0 and len(m.ray_score) == 0
    with pytest.raises(ValueError):
        merge_results([], 3)


def test_shard_info_roundtrip_tolerant():
    info = dict(INFO, shard="s1", score_min=0.25, junk=1)
    got = decode_shard_info(encode_shard_info(info))
    assert got["shard"] == "s1" and got["score_min"] == 0.25 and "junk" not in got
    assert decode_shard_info(None) == {} and decode_shard_info(b"\xff") == {} and decode_shard_info(b"[1]") == {}
