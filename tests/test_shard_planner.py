"""The planners' API over mapper shards, without processes: what a shard owns and where an edge
sends a frame (common.shard_routing, the routed frame keys), and the client-side merge of
several shards' search and occupancy answers (query_client.search_merge), each checked against
an independent brute-force computation. The real processes are in tests/test_shards.py."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from common.cones import cone_union_volume
from common.search_messages import OccupancyReply, OccupancyRequest, SearchReply, SearchRequest
from common.shard_routing import (
    ShardRegion,
    ShardRoutingError,
    decode_shard_routing,
    encode_shard_routing,
    route_targets,
)
from query_client.search_merge import NoShardOwns, check_owned, merge_occupancy, merge_search_replies

WEST = ShardRegion.make("west", [-1000, -1000, 0, 1000], halo_m=2.0)
EAST = ShardRegion.make("east", [0, -1000, 1000, 1000], halo_m=2.0)


def test_region_ownership_margin_tiles_and_unbounded():
    pts = np.array([[-0.5, 0, 0], [0.0, 0, 0], [1.5, 3, 9], [-1000, 999.9, 0], [5000, 0, 0]])
    assert WEST.owns_xyz(pts).tolist() == [True, False, False, True, False]
    assert EAST.owns_xyz(pts).tolist() == [False, True, True, False, False]
    assert WEST.owns_xyz(pts, margin=2.0).tolist() == [True, True, True, True, False]   # 1.5 m across: halo
    tiles = ShardRegion.make("t", tile_m=10, tiles=["0,0", "-1,2"])
    brute = [(np.floor(x / 10), np.floor(y / 10)) in {(0, 0), (-1, 2)} for x, y, _ in pts]
    assert tiles.owns_xyz(pts).tolist() == brute
    # 6-value region with +-1e9 (how announcements and shard info write "unbounded")
    half = ShardRegion.make("h", [-1e9, -1e9, -1e9, 0, 1e9, 1e9])
    assert np.isinf(half.lo).all() and half.owns_xyz([[-1e12, 5e11, 0]]).tolist() == [True]
    assert half.region_list() == [-1e9, -1e9, -1e9, 0.0, 1e9, 1e9]
    assert ShardRegion.make("all").owns_xyz(pts).all() and not ShardRegion.make("all").bounded
    assert WEST.intersects_box([-5, -5], [-1, 5]) and not WEST.intersects_box([0, 0], [3, 3])
    assert tiles.intersects_box([5, 5], [6, 6]) and not tiles.intersects_box([15, 5], [16, 6])
    for bad, what in (([0, 0, 0, 1], "min < max"), (["a"] * 4, "numbers")):
        with pytest.raises(ShardRoutingError, match=what):
            ShardRegion.make("x", bad)
    with pytest.raises(ShardRoutingError, match="tile_m"):
        ShardRegion.make("x", tiles=["1,2"])


def test_announcement_roundtrip_and_routing_in_the_world_frame():
    east = ShardRegion.make("east", [0, -1000, 1000, 1000], robots=["r1", "r2"], halo_m=1.0)
    T = np.eye(4)
    T[0, 3] = 50.0                                  # r2's frames are 50 m east in the map's world
    east.transforms["r2"] = T
    back = decode_shard_routing(encode_shard_routing(east))
    assert back.name == "east" and back.robots == {"r1", "r2"} and back.halo_m == 1.0
    np.testing.assert_allclose(back.transforms["r2"], T)
    np.testing.assert_allclose(back.lo[:2], [0, -1000]) and np.testing.assert_allclose(back.hi[:2], [1000, 1000])
    west = ShardRegion.make("west", [-1000, -1000, 0, 1000], halo_m=1.0)
    west.transforms["r2"] = T                       # every shard applies the robot's transform
    west = decode_shard_routing(encode_shard_routing(west))
    regions = [west, back]
    # brute force over a line of camera centres: the shards whose region (grown by the halo)
    # holds the world-frame centre
    for x in np.arange(-80.0, 20.0, 0.25):
        for robot, shift in (("r1", 0.0), ("r2", 50.0), ("r3", 0.0)):
            xw = x + shift
            want = sorted(n for n, lo, hi, rb in (("west", -1001, 1.0, None), ("east", -1.0, 1001, {"r1", "r2"}))
                          if lo <= xw < hi and (rb is None or robot in rb))
            pose = np.eye(4)
            pose[:3, 3] = [x, 3.0, 1.5]
            assert route_targets(regions, robot, pose[:3, 3]) == want, (robot, x)
    bad = encode_shard_routing(ShardRegion.make("east"))
    from common.wire import decode_message, encode_message

    _, _, body = decode_message(bad)
    body["world_from_robot"] = {"r1": [1.0] * 15}
    with pytest.raises(ShardRoutingError, match="16 finite numbers"):
        decode_shard_routing(encode_message("rayfronts.shard_routing", 1, body))


def test_routed_frame_keys_reach_only_their_shards():
    import zenoh

    from common.keys import KeySpace

    k = KeySpace("site")
    key = k.frames_routed("r1", ["east", "west"])
    assert key == "site/robots/r1/frames/s.east.west." and k.robot_from_key(key) == "r1"
    subs = {n: zenoh.KeyExpr(k.frames_routed_all(n)) for n in ("east", "west", "eas", "st", "all")}
    for shards in (["east"], ["west"], ["east", "west"], ["all", "east"], ["beast"]):
        got = {n for n, ke in subs.items() if ke.intersects(zenoh.KeyExpr(k.frames_routed("r1", shards)))}
        assert got == set(shards) & set(subs), shards
    # an unsharded mapper's subscriptions take routed frames too; a tile subscription does not
    assert zenoh.KeyExpr(k.frames_tiled_all).intersects(zenoh.KeyExpr(key))
    assert not zenoh.KeyExpr(k.frames_tile_all((0, 0))).intersects(zenoh.KeyExpr(key))
    assert k.mapper_shard_routing("east") == "site/mapper/shards/east/routing"
    assert zenoh.KeyExpr(k.mapper_shard_routing_all).intersects(zenoh.KeyExpr(k.mapper_shard_routing("east")))
    assert not zenoh.KeyExpr(k.mapper_shards_all).intersects(zenoh.KeyExpr(k.mapper_shard_routing("east")))


INFO = {"half_angle_deg": 10.0, "search_range_m": 50.0, "search_cell_m": 1.0, "search_samples": 50_000,
        "search_rays": 3, "vox_size": 0.5}


def _inst(i, target, lo, hi, conf, vox):
    lo, hi = np.array(lo, float), np.array(hi, float)
    return dict(id=i, target=target, centroid=((lo + hi) / 2).tolist(), box_min=lo.tolist(), box_max=hi.tolist(),
                confidence=conf, voxels=vox, observations=3, first_seen=1, last_seen=5)


def _goal(p, score, target="car"):
    return dict(position=list(p), heading_rad=0.0, score=score, ray_z=1.0, gain_m3=5.0, distance_m=1.0,
                target=target, frontier=list(p), rays=1)


def _ray(o, d, s, target="car"):
    return dict(origin=list(o), direction=list(d), score=s, target=target)


def test_search_merge_ids_border_instances_goals_and_beyond():
    w = SearchReply(id="s", found=[_inst(1, "car", [-3, 0, 0], [-0.25, 2, 1.5], 0.9, 40),      # straddles x = 0
                                   _inst(2, "car", [-30, 0, 0], [-28, 2, 1.5], 0.8, 30),
                                   _inst(3, "tree", [-1, 0, 0], [0.5, 1, 5], 0.7, 20)],
                    look_next=[_goal([-5, 0, 1], 0.6), _goal([0.1, 0.1, 1], 0.4)],
                    beyond={"rays": [_ray([-1, 0, 1], [1, 0, 0], 0.5), _ray([-9, 0, 1], [0, 1, 0], 0.2)],
                            "estimates": [{"position": [40, 0, 0], "radius_m": 2, "score": 0.3, "target": "car"}],
                            "search_volume_m3": 10.0},
                    events=[{"kind": "split", "id": 2, "parent": 1, "target": "car", "frame": 4},
                            {"kind": "merge", "id": 1, "merged": [5, 6], "target": "car", "frame": 4}],
                    frames_mapped=10, map_version=3)
    e = SearchReply(id="s", found=[_inst(1, "car", [0.0, 0.5, 0], [2, 2, 1.5], 0.95, 25),        # the same car
                                   _inst(4, "tree", [0.25, 0, 0], [1, 1, 5], 0.7, 10)],          # same tree
                    look_next=[_goal([0.15, 0.1, 1], 0.7), _goal([9, 9, 1], 0.1)],
                    beyond={"rays": [_ray([-1, 0, 1], [0.999, 0.01, 0], 0.55), _ray([5, 5, 1], [0, 0, 1], 0.1)],
                            "estimates": [], "search_volume_m3": 20.0},
                    events=[{"kind": "new", "id": 4, "target": "tree", "frame": 2}], frames_mapped=7, map_version=2)
    req = SearchRequest(targets=["car", "tree"], max_instances=10, max_goals=5).validate()
    m = merge_search_replies([(w, dict(INFO, shard="west", region=[-1000, -1000, -1e9, 0, 1000, 1e9])),
                              (e, dict(INFO, shard="east", region=[0, -1000, -1e9, 1000, 1000, 1e9]))], req)
    assert len(m.found) == 3                    # 5 parts, two objects seen from both sides
    ids = [f["id"] for f in m.found]
    assert len(set(ids)) == len(ids) and all(isinstance(i, str) and i.split(":")[0] in ("west", "east") for i in ids)
    car = next(f for f in m.found if f["target"] == "car" and "parts" in f)
    # the west part's centroid (-1.6) is in west's region, the east part's (1.0) in east's: the
    # larger owner keeps its id; union box, best confidence, voxels summed, weighted centroid
    assert car["id"] == "west:1" and car["parts"] == ["west:1", "east:1"] and car["shard"] == "west"
    assert car["box_min"] == [-3, 0, 0] and car["box_max"] == [2, 2, 1.5] and car["confidence"] == 0.95
    assert car["voxels"] == 65
    np.testing.assert_allclose(car["centroid"][0], (-1.625 * 40 + 1.0 * 25) / 65)
    tree = next(f for f in m.found if f["target"] == "tree")
    assert tree["parts"] == ["west:3", "east:4"] and tree["voxels"] == 30
    assert [f["id"] for f in m.found] == ["west:1", "west:2", "west:3"]      # ranked by confidence
    # goals: ranked over both shards; (0.1, 0.1) and (0.15, 0.1) are one voxel apart -> the better one
    assert [(g["shard"], g["score"]) for g in m.look_next] == [("east", 0.7), ("west", 0.6), ("east", 0.1)]
    # rays: (1,0,0) ~ (0.999, 0.01, 0) from the same voxel: once, the best
    assert [r["score"] for r in m.beyond["rays"]] == [0.55, 0.2, 0.1]
    rays = m.beyond["rays"]
    want = cone_union_volume(np.array([r["origin"] for r in rays]), np.array([r["direction"] for r in rays]),
                             10.0, 50.0, 1.0, max_cells=50_000)
    assert m.beyond["search_volume_m3"] == pytest.approx(want) and want > 20.0
    assert [ev["id"] for ev in m.events] == ["west:2", "west:1", "east:4"]
    assert m.events[0]["parent"] == "west:1" and m.events[1]["merged"] == ["west:5", "west:6"]
    assert m.frames_mapped == 17 and m.timings_ms["shards"] == 2.0
    assert len(merge_search_replies([(w, dict(INFO, shard="west")), (e, dict(INFO, shard="east"))],
                                    SearchRequest(targets=["car"], max_instances=1, max_goals=1).validate()).found) == 1
    # one mapper without a shard name: its own reply, integer ids
    assert merge_search_replies([(w, {})], req) is w
    one = merge_search_replies([(e, dict(INFO, shard="east"))], req)
    assert [f["id"] for f in one.found] == ["east:1", "east:4"]



def test_search_merge_ranks_equal_goals_the_same_whatever_the_reply_order():
    # equal scores on both shards (the site rehearsal's look-next goals all scored 1.0): every
    # planner must get the same goals in the same order, whichever shard answered first
    w = SearchReply(id="s", look_next=[_goal([-5, 0, 1], 1.0), _goal([-9, 0, 1], 1.0)], frames_mapped=1)
    e = SearchReply(id="s", look_next=[_goal([5, 0, 1], 1.0), _goal([9, 0, 1], 0.5)], frames_mapped=1)
    req = SearchRequest(targets=["car"], max_goals=3).validate()
    iw, ie = dict(INFO, shard="west"), dict(INFO, shard="east")
    a = merge_search_replies([(w, iw), (e, ie)], req).look_next
    b = merge_search_replies([(e, ie), (w, iw)], req).look_next
    assert a == b and [(g["shard"], g["position"][0]) for g in a] == [("east", 5), ("west", -5), ("west", -9)]

def _grid(lo, shape, cell, fill):
    return OccupancyReply(kind="box", states=fill.astype(np.int8).reshape(shape), origin=list(lo), cell_m=cell)


def test_occupancy_merge_takes_each_cell_from_its_owner():
    rng = np.random.default_rng(3)
    lo, shape, cell = [-2.0, -1.0, 0.0], (8, 4, 2), 0.5
    req = OccupancyRequest("box", lo, [2.0, 1.0, 1.0]).validate()
    sw = rng.integers(-1, 2, size=shape)
    se = rng.integers(-1, 2, size=shape)
    iw = dict(shard="west", region=[-1000, -1000, -1e9, 0, 1000, 1e9])
    ie = dict(shard="east", region=[0, -1000, -1e9, 1000, 1000, 1e9])
    m = merge_occupancy([(_grid(lo, shape, cell, sw), iw), (_grid(lo, shape, cell, se), ie)], req)
    # brute force: cell x centre < 0 -> west's, else east's; unknown there -> the other's
    assert set(np.unique(sw)) == {-1, 0, 1} and set(np.unique(se)) == {-1, 0, 1}
    for i, j, k in itertools.product(*map(range, shape)):
        x = lo[0] + (i + 0.5) * cell
        own, other = (sw, se) if x < 0 else (se, sw)
        want = own[i, j, k] if own[i, j, k] != -1 else other[i, j, k]
        assert m.states[i, j, k] == want, (i, j, k)
    assert m.origin == lo and m.cell_m == cell
    # points: states per owner, dist = the nearest over all shards
    pts = np.array([[-1.0, 0, 0], [1.0, 0, 0], [3000.0, 0, 0]])
    preq = OccupancyRequest("points", points=pts).validate()
    pw = OccupancyReply("points", np.array([1, 0, -1], np.int8), [], 0.5, dist=np.array([0.0, 2.0, np.inf]))
    pe = OccupancyReply("points", np.array([0, -1, -1], np.int8), [], 0.5, dist=np.array([1.0, 0.5, np.inf]))
    mp = merge_occupancy([(pw, iw), (pe, ie)], preq)
    assert mp.states.tolist() == [1, 0, -1] and mp.dist.tolist() == [0.0, 0.5, np.inf]
    # a box no shard owns: one line naming the regions; a missing shard's remembered region counts
    far = OccupancyRequest("box", [3000, 0, 0], [3001, 1, 1]).validate()
    g = _grid([3000, 0, 0], (2, 2, 2), 0.5, np.full(8, -1))
    with pytest.raises(NoShardOwns, match=r"no shard's region .*west .*east") as ei:
        merge_occupancy([(g, iw), (g, ie)], far)
    assert "\n" not in str(ei.value) and "shard.region" in str(ei.value)
    got = merge_occupancy([(g, iw)], far, others=[dict(shard="far", region=[2000, -10, 4000, 10])])
    assert got.states.shape == (2, 2, 2)
    with pytest.raises(ValueError, match="different box grids"):
        merge_occupancy([(_grid(lo, shape, cell, sw), iw), (_grid(lo, shape, 0.25, se), ie)], req)
    with pytest.raises(NoShardOwns, match="search area"):
        check_owned("search area", [2000, 0], [2100, 10], [WEST, EAST])
    check_owned("search area", [-5, 0], [5, 10], [WEST, EAST])


def test_edge_routes_only_when_every_live_shard_has_announced():
    """Real Zenoh sessions in one process: a router, two 'shards' (a liveliness token and the
    routing queryable each, declared one after the other) and the edge's ShardRoutes. A frame
    goes to the shards owning it only while every live shard has been heard; otherwise (or
    when none owns it) on the plain key."""
    import threading

    from common.keys import KeySpace
    from common.zenoh_session import ZenohConfig, open_session
    from edge.shard_routes import ShardRoutes
    from tests.support.ports import free_port, open_loopback_router
    from tests.support.processes import wait_for

    port = free_port()
    router = open_loopback_router(port)
    keys = KeySpace("t")
    cfg = ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=10_000)
    edge_s, east_s, west_s = (open_session(cfg) for _ in range(3))
    stop = threading.Event()
    ents = []
    try:
        routes = ShardRoutes(edge_s, keys, "r1", stop, period_s=0.2).start()

        def at(x):
            pose = np.eye(4)
            pose[:3, 3] = [x, 0.0, 1.5]
            return routes.targets(pose)

        def announce(s, reg):
            body = encode_shard_routing(reg)
            return s.declare_queryable(keys.mapper_shard_routing(reg.name), lambda q: q.reply(q.key_expr, body))
        assert at(5.0) == [] and routes.shards() == []                        # no shard: plain key
        ents.append(east_s.liveliness().declare_token(keys.mapper_shard_alive("east")))
        wait_for(lambda: "east" in routes._alive, 5, what="east's token")
        assert at(5.0) == []                                                  # live but unheard
        ents.append(announce(east_s, EAST))
        assert wait_for(lambda: at(5.0) == ["east"], 5, what="east announced")
        assert at(-5.0) == [] and at(-1.5) == ["east"]                        # not east's / its halo
        ents.append(west_s.liveliness().declare_token(keys.mapper_shard_alive("west")))
        wait_for(lambda: "west" in routes._alive, 5, what="west's token")
        assert at(5.0) == [] and at(-1.5) == []                               # west unheard: plain
        ents.append(announce(west_s, WEST))
        wait_for(lambda: at(-1.5) == ["east", "west"], 5, what="west announced")
        assert at(-5.0) == ["west"] and at(5.0) == ["east"] and at(0.5) == ["east", "west"]
        east_s.close()                                                         # token and queryable gone
        wait_for(lambda: routes.shards() == ["west"], 5, what="east forgotten")
        assert at(5.0) == [] and at(-5.0) == ["west"]                          # nobody owns x = 5 now
    finally:
        stop.set()
        for s in (edge_s, west_s, east_s, router):
            try:
                s.close()
            except Exception:
                pass
