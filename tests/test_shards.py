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
from tests.support.processes import Proc, stop_all, wait_for


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


def test_merge_dedups_border_voxels_and_keeps_every_shards_rays():
    # the same voxel centre (float32 noise) from both shards: once, with the best score
    a = _res([], [((0.25, 0.25, 0.25), 0.7), ((3.25, 0.25, 0.25), 0.5)],
             [((0.25, 0.25, 0.25), (1, 0, 0), 0.6), ((0.25, 0.25, 0.25), (0, 1, 0), 0.4)])
    b = _res([], [((0.2500001, 0.25, 0.25), 0.8), ((-0.25, 0.25, 0.25), 0.3)],
             [((0.25, 0.25, 0.25), (0.999, 0.01, 0), 0.65), ((-9.75, 0.25, 0.25), (-1, 0, 0), 0.2)])
    # regions say a frontier at x = -9.75 is a's, yet b's ray from there is kept (none is lost)
    ia = dict(INFO, shard="a", vox_size=0.5, region=[-100, -100, -1e9, 0, 100, 1e9])
    ib = dict(INFO, shard="b", vox_size=0.5, region=[0, -100, -1e9, 100, 100, 1e9])
    m = merge_results([(a, ia), (b, ib)], top_k=10)
    np.testing.assert_allclose(m.voxel_score, [0.8, 0.5, 0.3])
    np.testing.assert_allclose(m.voxel_xyz[:, 0], [0.25, 3.25, -0.25], atol=1e-5)
    np.testing.assert_allclose(m.ray_score, [0.65, 0.4, 0.2])       # (1,0,0) ~ (0.999,0.01,0): one bin
    np.testing.assert_allclose(m.ray_origin[2], [-9.75, 0.25, 0.25])
    assert len(merge_results([(a, ia), (b, ib)], top_k=2).voxel_score) == 2


def test_shard_subscription_tiles():
    from mapper.shards import ShardFilter, ShardSection

    def tiles(**kw):
        cfg = ShardSection(**kw)
        return ShardFilter(cfg).subscription_tiles(cfg)
    assert tiles(region=[0, -10, 20, 10]) is None                               # no tile_m: every frame
    assert tiles(region=[0, -10, 20, 10], tile_m=10, halo_tiles=0) == {(0, -1), (0, 0), (1, -1), (1, 0)}
    got = tiles(region=[0, -10, 20, 10], tile_m=10)                              # halo of one tile
    assert got == {(i, j) for i in range(-1, 3) for j in range(-2, 2)}
    assert tiles(tile_m=5, tiles=["2,3"], halo_tiles=0) == {(2, 3)}
    assert len(tiles(tile_m=5, tiles=["2,3"])) == 9
    assert tiles(region=[-1e6, -1e6, 0, 1e6], tile_m=1) is None                 # too many: every frame


def test_tile_and_shard_keys():
    import zenoh

    from common.keys import KeySpace

    k = KeySpace("site/x")
    assert k.frames_tile("r1", (-3, 4)) == "site/x/robots/r1/frames/-3_4"
    assert k.robot_from_key("site/x/robots/r1/frames/-3_4") == "r1"
    assert k.robot_from_key("site/x/robots/r1/frames") == "r1"
    for bad in ("site/x/robots/r1/alive/1_2", "site/x/robots/r1/frames/1_x", "site/x/robots/r1/frames/1_2/3"):
        assert k.robot_from_key(bad) is None, bad
    tile_sub = zenoh.KeyExpr(k.frames_tile_all((-3, 4)))
    assert tile_sub.intersects(zenoh.KeyExpr(k.frames_tile("r2", (-3, 4))))
    assert not tile_sub.intersects(zenoh.KeyExpr(k.frames_tile("r2", (-3, 5))))
    assert not tile_sub.intersects(zenoh.KeyExpr(k.frames("r2")))
    assert zenoh.KeyExpr(k.frames_tiled_all).intersects(zenoh.KeyExpr(k.frames_tile("r2", (0, 0))))
    assert k.shard_from_key(k.mapper_shard_alive("east")) == "east" and k.shard_from_key(k.mapper_alive) is None


def test_shard_info_roundtrip_tolerant():
    info = dict(INFO, shard="s1", score_min=0.25, junk=1)
    got = decode_shard_info(encode_shard_info(info))
    assert got["shard"] == "s1" and got["score_min"] == 0.25 and "junk" not in got
    assert decode_shard_info(None) == {} and decode_shard_info(b"\xff") == {} and decode_shard_info(b"[1]") == {}


# ------------------------------------------------------------------ real processes
# tile-routed (docs/key_space.md#shards): 10 m tiles, one tile of halo; the lap spans x in +-41 m
WEST = ["shard.region=[-60, -60, 0, 60]", "shard.tile_m=10"]
EAST = ["shard.region=[0, -60, 60, 60]", "shard.tile_m=10"]


@pytest.mark.timeout(300)
def test_two_shards_answer_like_one_mapper(tmp_path):
    """A router, two shard mappers (west / east of x = 0) and a third mapper holding every
    frame, fed by one robot driving a lap across both halves. One ``get`` reaches all three
    queryables; the two shards' merged answer matches the whole-map mapper's."""
    from apps.bench.fleet import render_recordings
    from common.fleet import decode_shard_info
    from common.messages import QueryRequest, decode_query_result, encode_query_request
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client import Client

    rec = render_recordings(tmp_path / "recs", 1, 16, "48x64")[0]
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    common_map = ["--mode", "client", "--connect", ep, "preset=throughput", "map.vox_size=0.5",
                  "map.depth_limit=20", "layers.rate_hz=0", "snapshots.on_exit=false", "queues.per_robot=1000",
                  "queues.idle_flush_s=0.5"]
    procs = [Proc("router", ["router", "--listen", ep], tmp_path)]
    try:
        east_snap = ["shard.name=east", *EAST, f"snapshots.dir={tmp_path / 'east-snaps'}", "snapshots.period_s=1"]
        for name, extra in (("west", ["shard.name=west", *WEST]), ("east", east_snap), ("all", ["shard.name=all"])):
            procs.append(Proc(name, ["mapper", *common_map, *extra], tmp_path))
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=30.0) as c:
            def mapped():
                oks, _ = c._get_all(c.keys.stats, None, 5.0)
                return len(oks) == 3
            wait_for(mapped, 120, what="three mappers up")
            edge = Proc("edge", ["edge", "--connect", ep, "robot=r1", "source.kind=recording",
                                 f"source.path={rec}", "publish.rate_hz=10", "pca.out_dim=16",
                                 "pca.fit_frames=3", "publish.linger_s=3", "publish.tile_m=10"], tmp_path)
            procs.append(edge)

            def done():
                from common.messages import decode_stats

                if edge.p.poll() is None:
                    return None
                oks, _ = c._get_all(c.keys.stats, None, 5.0)
                sts = {s.get("fleet", {}).get("shard"): s for s in (decode_stats(d) for d, _ in oks)}
                if set(sts) != {"west", "east", "all"}:
                    return None
                for s in sts.values():
                    r = s["robots"].get("r1", {})
                    if not r or r["queue"] or r["mapped"] + r["outside_shard"] < r["received"] \
                            or s["flushed_version"] != s["map_version"]:
                        return None
                return sts
            parts = wait_for(done, 180, every=0.5, what="every frame mapped")
            n = parts["all"]["robots"]["r1"]["mapped"]
            assert n >= 12 and parts["all"]["robots"]["r1"]["outside_shard"] == 0
            assert parts["west"]["frames"]["mapped"] > 0 and parts["east"]["frames"]["mapped"] > 0
            assert parts["west"]["frames"]["mapped"] + parts["east"]["frames"]["mapped"] == n
            # Zenoh routes each frame to the shards subscribed to its tile: a shard receives its own
            # frames plus those of the halo, not every frame ('all' subscribes to every key)
            sent = parts["all"]["frames"]["received"]
            got = parts["west"]["frames"]["received"] + parts["east"]["frames"]["received"]
            assert sent == parts["all"]["robots"]["r1"]["received"] >= 12
            assert n <= got <= 1.3 * sent, (got, sent)
            for q in ("car", "tree", "building", "water tower"):
                oks, errs = c._get_all(c.keys.mapper_query, encode_query_request(QueryRequest(text=q, top_k=20)),
                                       60.0)
                assert len(oks) == 3, errs
                got = {decode_shard_info(att)["shard"]: (decode_query_result(d), decode_shard_info(att))
                       for d, att in oks}
                ref = got["all"][0]
                m = merge_results([got["west"], got["east"]], 20)
                # a voxel near the border seen by both shards is in the merge once (0.5 m voxels)
                keys = np.round(m.voxel_xyz / 0.25).astype(np.int64)
                assert len(np.unique(keys, axis=0)) == len(keys), q
                # top voxels: the same best score, the best voxel of the merge among the whole map's top
                assert abs(float(m.voxel_score[0]) - float(ref.voxel_score[0])) < 0.02, q
                assert np.min(np.linalg.norm(ref.voxel_xyz - m.voxel_xyz[0], axis=1)) < 1.0, q
                # best cluster within a voxel or two of the whole map's best cluster
                if len(ref.cluster_xyz):
                    d = np.linalg.norm(m.cluster_xyz[:3][:, None] - ref.cluster_xyz[None, :1], axis=2).min()
                    assert d < 2.0, (q, m.cluster_xyz[:3], ref.cluster_xyz[:1])
                # rays: frontiers near the border collect rays from the frames of both sides in the
                # whole map but of one side in a shard, so ray scores of in-range classes differ
                # there; for a class beyond range the best rays score alike (their directions are
                # near-ties at this tiny resolution) and the search volume is alike
                if q in ("water tower",):
                    k = min(10, len(m.ray_score), len(ref.ray_score))
                    assert abs(float(m.ray_score[0]) - float(ref.ray_score[0])) < 0.05, q
                    assert abs(float(m.ray_score[:k].mean()) - float(ref.ray_score[:k].mean())) < 0.05, q
                    assert m.search_volume_m3 == pytest.approx(ref.search_volume_m3, rel=0.35), q
            # the Client does the same fan-out and merge (all three replies here: 'all' included)
            r = c.query("car", top_k=5)
            assert r.timings.get("shards") == 3.0 and r.missing_shards == []
            assert c.shards()[0] == ["all", "east", "west"]

            # a shard dies (SIGKILL: no goodbye): the next merged answer names it (liveliness)
            east_mapped = parts["east"]["frames"]["mapped"]
            wait_for(lambda: c.stats_all(5.0)["east"]["snapshot"].get("frames_mapped") == east_mapped, 30,
                     what="east's periodic snapshot")
            seen = []
            watch = c.watch("car", seen.append, top_k=5)
            assert seen and seen[0].missing_shards == [] and seen[0].timings.get("shards") == 3.0
            procs[2].p.kill()
            procs[2].p.wait()
            # --watch: the dead shard's last result is dropped and it is reported missing
            wait_for(lambda: any(x.missing_shards == ["east"] for x in seen), 10, what="watch: east missing")
            last = next(x for x in seen if x.missing_shards == ["east"])
            assert last.timings.get("shards") == 2.0
            watch.cancel()
            r = wait_for(lambda: (lambda x: x if x.missing_shards else None)(c.query("car", top_k=5)), 10,
                         every=0.3, what="east reported missing")
            assert r.missing_shards == ["east"] and r.timings.get("shards") == 2.0
            # restarted with the same name and snapshot store: it answers again with its region
            procs.append(Proc("east-again", ["mapper", *common_map, *east_snap], tmp_path))

            def east_back():
                oks, _ = c._get_all(c.keys.mapper_query, encode_query_request(QueryRequest(text="car", top_k=5)),
                                    30.0)
                got = {decode_shard_info(att).get("shard"): (decode_query_result(d), decode_shard_info(att))
                       for d, att in oks}
                return got.get("east")
            e, info = wait_for(east_back, 120, every=0.5, what="east answering again")
            assert e.frames_mapped == east_mapped and info["region"][0] == 0 and info["region"][3] == 60
            assert c.query("car", top_k=5).missing_shards == []
    finally:
        stop_all(reversed(procs))
