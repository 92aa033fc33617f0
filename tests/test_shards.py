"""Mapper shards: the client-side merge of several shards' answers (query_client.merge), the
shard region filter (mapper.shards) and, with real processes on loopback, two shards that
answer like one mapper holding the whole map."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from common.cones import cone_union_volume
from common.messages import QueryResult
from common.robot_messages import decode_shard_info, encode_shard_info
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
# the README's first shard example: regions only, no tile flags anywhere (routing by the shards'
# announcements, docs/key_space.md#shards); the lap spans x in +-41 m, y in +-24 m
WEST = ["shard.region=[-1000, -1000, 0, 1000]"]
EAST = ["shard.region=[0, -1000, 1000, 1000]"]
TARGETS = ["car", "tree", "building", "street lamp"]
#: occupancy box across the border where the lap crosses it (y = -23.6 m, driving +x): west's
#: frames at x = -17 and -2 see up to x ~ 18, east's first frame (x = 13.5) sees beyond
OCC_BOX = ([-6.0, -27.0, 0.0], [20.0, -20.0, 3.0])


def _by_shard(oks, decode):
    """{shard name ('' for the unsharded mapper): (answer, shard info)} of a fan-out get."""
    out = {}
    for d, att in oks:
        info = decode_shard_info(att)
        out[str(info.get("shard", ""))] = (decode(d), info)
    return out


def _check_search(s, ref, world):
    """The merged search of the two shards against the whole-map mapper's answer ``ref``."""
    ids = [f["id"] for f in s.found]
    assert len(ids) >= 4 and len(set(ids)) == len(ids), ids
    assert all(isinstance(i, str) and i.split(":")[0] == f["shard"] for i, f in zip(ids, s.found, strict=True))
    assert {f["shard"] for f in s.found} == {"west", "east"}, ids
    xs = [f["centroid"][0] for f in s.found]
    assert min(xs) < -5 and max(xs) > 5, xs                             # instances from both halves
    # every object of the whole map (>= 8 voxels) is found, its box overlapping (within 1 m)
    big = [i for i in ref.found if i["voxels"] >= 8]
    assert len(big) >= 3, ref.found
    for r in big:
        near = [f for f in s.found if f["target"] == r["target"]
                and np.all(np.array(f["box_min"]) <= np.array(r["box_max"]) + 1.0)
                and np.all(np.array(r["box_min"]) <= np.array(f["box_max"]) + 1.0)]
        assert near, (r, [(f["id"], f["target"], f["box_min"], f["box_max"]) for f in s.found])
    # de-duplicated: no two instances of one target from different shards touch
    for a in s.found:
        for b in s.found:
            if a is not b and a["target"] == b["target"] and a["shard"] != b["shard"]:
                gap = np.maximum(np.array(a["box_min"]) - b["box_max"], np.array(b["box_min"]) - a["box_max"])
                assert gap.max() > 0.25, (a, b)
    # look-next goals ranked over both shards, best first, in free space of the true world
    assert s.look_next and [g["score"] for g in s.look_next] == sorted((g["score"] for g in s.look_next),
                                                                       reverse=True)
    assert {g["shard"] for g in s.look_next} <= {"west", "east"}
    assert np.all(world.labels_at(np.array([g["position"] for g in s.look_next])) == 0), s.look_next


@pytest.mark.timeout(300)
def test_two_shards_answer_like_one_mapper(tmp_path):
    """A router, two shard mappers (west / east of x = 0, the README's first example: regions
    only) and a third, unsharded mapper holding every frame, fed by one robot driving a lap
    across both halves. The edge learns the shards' regions and sends each frame to its owner
    (about one delivery per frame); queries, searches and occupancy merged over the two shards
    match the whole-map mapper's; a SIGKILLed shard is named in every reply."""
    from apps.bench.fleet import render_recordings
    from common.messages import QueryRequest, decode_query_result, encode_query_request
    from common.search_messages import (
        OccupancyRequest,
        SearchRequest,
        decode_occupancy_reply,
        decode_search_reply,
        encode_occupancy_request,
        encode_search_request,
    )
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client import Client
    from query_client.client import QueryError
    from synthetic_world.scene import World
    from tests.support.processes import cli_cmd, proc_env

    rec = render_recordings(tmp_path / "recs", 1, 16, "48x64")[0]
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    common_map = ["--mode", "client", "--connect", ep, "preset=throughput", "map.vox_size=0.5",
                  "map.depth_limit=20", "layers.rate_hz=0", "snapshots.on_exit=false", "queues.per_robot=1000",
                  "queues.idle_flush_s=0.5"]
    procs = [Proc("router", ["router", "--listen", ep], tmp_path)]
    try:
        east_snap = ["shard.name=east", *EAST, f"snapshots.dir={tmp_path / 'east-snaps'}", "snapshots.period_s=1"]
        for name, extra in (("west", ["shard.name=west", *WEST]), ("east", east_snap), ("all", [])):
            procs.append(Proc(name, ["mapper", *common_map, *extra], tmp_path))
        ref_proc = procs[-1]
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=30.0) as c:
            def mapped():
                oks, _ = c._get_all(c.keys.stats, None, 5.0)
                return len(oks) == 3 and c.shards()[0] == ["east", "west"]
            wait_for(mapped, 120, what="three mappers up")
            edge = Proc("edge", ["edge", "--connect", ep, "robot=r1", "source.kind=recording",
                                 f"source.path={rec}", "publish.rate_hz=10", "pca.out_dim=16",
                                 "pca.fit_frames=3", "publish.linger_s=3"], tmp_path)
            procs.append(edge)

            def done():
                from common.messages import decode_stats
                from query_client.vocabulary import settled

                if edge.p.poll() is None:
                    return None
                oks, _ = c._get_all(c.keys.stats, None, 5.0)
                sts = {s.get("fleet", {}).get("shard") or "all": s for s in (decode_stats(d) for d, _ in oks)}
                if set(sts) != {"west", "east", "all"}:
                    return None
                ok = all("r1" in s["robots"] and settled(s, mapped=0) for s in sts.values())
                return sts if ok else None
            parts = wait_for(done, 180, every=0.5, what="every frame mapped")
            n = parts["all"]["robots"]["r1"]["mapped"]
            assert n >= 12 and parts["all"]["robots"]["r1"]["outside_shard"] == 0
            assert parts["west"]["frames"]["mapped"] > 0 and parts["east"]["frames"]["mapped"] > 0
            assert parts["west"]["frames"]["mapped"] + parts["east"]["frames"]["mapped"] == n, {
                k: (v["frames"], v["robots"]["r1"]) for k, v in parts.items()}
            # routing by default: each frame reaches the shard owning its camera centre (and a
            # neighbour within shard.halo_m); without routing every shard receives every frame (2.0)
            sent = parts["all"]["frames"]["received"]
            got = parts["west"]["frames"]["received"] + parts["east"]["frames"]["received"]
            assert sent == parts["all"]["robots"]["r1"]["received"] >= 12
            print(f"deliveries per frame: {got / sent:.3f} ({got} deliveries of {sent} frames)")
            assert n <= got <= 1.3 * sent, (got, sent)
            for q in ("car", "tree", "building", "water tower"):
                oks, errs = c._get_all(c.keys.mapper_query, encode_query_request(QueryRequest(text=q, top_k=20)),
                                       60.0)
                assert len(oks) == 3, errs
                got = _by_shard(oks, decode_query_result)
                ref = got[""][0]
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
            # the Client does the same fan-out and merge (all three replies here: the whole map's too)
            r = c.query("car", top_k=5)
            assert r.timings.get("shards") == 3.0 and r.missing_shards == []

            # the whole-map mapper's search and occupancy (the reference), then it leaves
            sreq = SearchRequest(targets=TARGETS, max_instances=60, max_goals=10, from_xyz=[0, -23.6, 1.5])
            oks, _ = c._get_all(c.keys.mapper_search, encode_search_request(sreq.validate()), 60.0)
            ref_search = _by_shard(oks, decode_search_reply)[""][0]
            box_req = OccupancyRequest("box", *OCC_BOX).validate()
            oks, _ = c._get_all(c.keys.mapper_occupancy, encode_occupancy_request(box_req), 30.0)
            occ = _by_shard(oks, decode_occupancy_reply)
            assert set(occ) == {"", "west", "east"}
            ref_box = occ[""][0].states

            ref_proc.stop()
            wait_for(lambda: len(c._get_all(c.keys.stats, None, 5.0)[0]) == 2, 30, what="the reference gone")

            # search: instances from both halves, site-wide unique ids, like the whole map's
            s = c.search(TARGETS, max_instances=60, max_goals=10, from_xyz=[0, -23.6, 1.5])
            assert s.missing_shards == [] and s.timings_ms["shards"] == 2.0
            _check_search(s, ref_search, World.generate(0, "default"))
            # occupancy: a box across the border is whole (known on both sides, like the whole map)
            box = c.occupancy_box(*OCC_BOX)
            assert box.missing_shards == [] and box.states.shape == ref_box.shape
            cx = box.origin[0] + (np.arange(box.states.shape[0]) + 0.5) * box.cell_m
            known, ref_known = box.states != -1, ref_box != -1
            assert known[cx < 0].sum() >= 100 and known[cx >= 0].sum() >= 100, (known[cx < 0].sum(),
                                                                                 known[cx >= 0].sum())
            alone = [(occ[k][0].states != -1).sum() for k in ("west", "east")]
            assert known.sum() > max(alone) and known.sum() >= 0.9 * ref_known.sum(), (known.sum(), alone,
                                                                                       ref_known.sum())
            both = known & ref_known
            assert np.mean(box.states[both] == ref_box[both]) >= 0.9
            sl = c.occupancy_slice(OCC_BOX[0][:2], OCC_BOX[1][:2], (OCC_BOX[0][2], OCC_BOX[1][2]))
            # the costmap agrees with the box (a column can differ where the owner knows only part
            # of it: the slice falls back to the other shard's column, the box per voxel)
            assert sl.missing_shards == [] and sl.states.shape == box.states.shape[:2]
            agree = np.mean((sl.states == 1) == (box.states == 1).any(2))
            print(f"costmap slice agrees with the box's columns in {agree:.3f} of the cells")
            assert agree >= 0.95 and (sl.states == 1).any()
            # a region no shard owns: one line naming the shards' regions
            for call in (lambda: c.occupancy_box([2000, 0, 0], [2002, 2, 2]),
                         lambda: c.search("car", area=[2000, 0, 2010, 10])):
                with pytest.raises(QueryError, match="no shard's region") as ei:
                    call()
                assert "\n" not in str(ei.value) and "west" in str(ei.value) and "east" in str(ei.value)

            # a shard dies (SIGKILL: no goodbye): the next merged answers name it (liveliness)
            east_mapped = parts["east"]["frames"]["mapped"]
            wait_for(lambda: c.stats_all(5.0)["east"]["snapshot"].get("frames_mapped") == east_mapped, 30,
                     what="east's periodic snapshot")
            seen, found = [], []
            watch = c.watch("car", seen.append, top_k=5)
            wsearch = c.watch_search(TARGETS, found.append, max_instances=60)
            assert seen and seen[0].missing_shards == [] and seen[0].timings.get("shards") == 2.0
            assert found and found[0].missing_shards == [] and {f["shard"] for f in found[0].found} == {"west", "east"}
            assert sorted(f["id"] for f in found[0].found) == sorted(f["id"] for f in s.found)
            procs[2].p.kill()
            procs[2].p.wait()
            # --watch: the dead shard's last result is dropped and it is reported missing
            wait_for(lambda: any(x.missing_shards == ["east"] for x in seen), 10, what="watch: east missing")
            west_mapped = parts["west"]["frames"]["mapped"]
            last = next(x for x in seen if x.missing_shards == ["east"])
            assert last.frames_mapped == west_mapped
            wait_for(lambda: any(x.missing_shards == ["east"] for x in found), 10, what="search: east missing")
            last = next(x for x in found if x.missing_shards == ["east"])
            assert last.found and {f["shard"] for f in last.found} == {"west"}
            watch.cancel()
            wsearch.cancel()
            r = wait_for(lambda: (lambda x: x if x.missing_shards else None)(c.query("car", top_k=5)), 10,
                         every=0.3, what="east reported missing")
            assert r.missing_shards == ["east"] and r.frames_mapped == west_mapped
            s2 = c.search(TARGETS, max_instances=60)
            assert s2.missing_shards == ["east"] and {f["shard"] for f in s2.found} == {"west"}
            b2 = c.occupancy_box(*OCC_BOX)
            assert b2.missing_shards == ["east"] and (b2.states != -1).sum() == alone[0]
            # restarted with the same name and snapshot store: it answers again with its region
            procs.append(Proc("east-again", ["mapper", *common_map, *east_snap], tmp_path))

            def east_back():
                oks, _ = c._get_all(c.keys.mapper_query, encode_query_request(QueryRequest(text="car", top_k=5)),
                                    30.0)
                return _by_shard(oks, decode_query_result).get("east")
            e, info = wait_for(east_back, 120, every=0.5, what="east answering again")
            assert e.frames_mapped == east_mapped and info["region"][0] == 0 and info["region"][3] == 1000
            assert c.query("car", top_k=5).missing_shards == []
            # a shard that answers with an error (a third one, its map empty): a fresh CLI client
            # names it missing and warns as it does for queries; --json carries the field
            procs.append(Proc("north", ["mapper", *common_map, "shard.name=north",
                                        "shard.region=[-1000, 1000, 1000, 2000]"], tmp_path))
            wait_for(lambda: "north" in c.shards()[0], 120, what="north up")
            out = subprocess.run(cli_cmd("search", *TARGETS[:1], "--json", "--connect", ep, "--timeout", "20"),
                                 capture_output=True, text=True, env=proc_env(), timeout=120)
            assert out.returncode == 0, out.stderr[-2000:]
            assert json.loads(out.stdout)["missing_shards"] == ["north"]
            assert "rayfronts search: warning: shards that did not answer: north" in out.stderr
    finally:
        stop_all(reversed(procs))
