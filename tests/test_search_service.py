"""Search for planners over Zenoh: the schemas (common.search_messages), and real processes
(mapper in router mode + an edge on the synthetic world, seed 0) answering
``rayfronts search`` and ``Client.search`` / ``Client.occupancy_*`` against the world's
ground truth."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from common.messages import MessageError
from common.search_messages import (
    MAX_INSTANCES,
    SCHEMA_SEARCH_REQUEST,
    VERSION,
    OccupancyRequest,
    SearchReply,
    SearchRequest,
    decode_occupancy_request,
    decode_search_reply,
    decode_search_request,
    encode_occupancy_request,
    encode_search_reply,
    encode_search_request,
)
from common.wire import encode_message
from common.zenoh_session import free_tcp_port
from tests.support.instances import describe, match_by_position
from tests.support.processes import ROOT, Proc, cli_cmd, stop_all, wait_for, zenoh_env
from tests.support.roles import client, edge_args, mapped, mapper_args

VOX = 0.5     # tests.support.roles.FAST_MAP
#: an instance found again when a later answer has one whose centroid is this near (m): 3
#: voxels, what more views of the same car move its centroid by (a car is ~4.5 m long)
MATCH_M = 3 * VOX


# ----------------------------------------------------------------------------- schemas
def test_search_request_round_trip():
    req = SearchRequest(targets=["car", "bench"], background=["road"], area=[[0, 0], [10, 0], [10, 10]],
                        z_band=[0, 3], threshold=0.6, max_instances=4, from_xyz=[1, 2, 3], standing=True, id="s1")
    got = decode_search_request(encode_search_request(req))
    assert got == req.validate()
    box = decode_search_request(encode_search_request(SearchRequest(targets=["car"], box=[0, 0, 5, 5])))
    assert box.polygon() == [[0, 0], [5, 0], [5, 5], [0, 5]] and box.background is None
    emb = SearchRequest(targets=["x"], embeddings=np.ones((1, 8), np.float32))
    assert np.array_equal(decode_search_request(encode_search_request(emb)).embeddings, np.ones((1, 8)))
    rep = SearchReply(id="a", found=[{"id": 1, "centroid": [1.0, 2.0, 3.0]}], frames_mapped=3, map_version=4,
                      timings_ms={"total": 1.5})
    back = decode_search_reply(encode_search_reply(rep))
    assert back.to_dict() == rep.to_dict()
    occ = OccupancyRequest("points", points=np.zeros((3, 3)), radius=2.0)
    assert decode_occupancy_request(encode_occupancy_request(occ)).points.shape == (3, 3)


@pytest.mark.parametrize("kw,match", [
    (dict(targets=[]), "targets must be a list of 1..16"),
    (dict(targets=["car"], area=[]), "area must be a polygon of 3"),
    (dict(targets=["car"], area=[[0, 0], [1, 1], [2, 2]]), "degenerate"),
    (dict(targets=["car"], threshold=1.0), r"threshold must be a probability in \(0, 1\)"),
    (dict(targets=["car"], threshold=0.0), r"threshold must be a probability in \(0, 1\)"),
    (dict(targets=["car"], box=[0, 0, 5000, 5000]), "exceeds the limit of 4,000,000 m²"),
    (dict(targets=["car"], z_band=[3, 1]), "z0 <= z1"),
    (dict(targets=["car"], from_xyz=[1, 2]), "from_xyz"),
    (dict(targets=["car"], standing=True), "needs an id"),
])
def test_bad_search_requests_one_line(kw, match):
    with pytest.raises(MessageError, match=match) as e:
        SearchRequest(**kw).validate()
    assert "\n" not in str(e.value)


def test_unknown_field_rejected():
    raw = encode_message(SCHEMA_SEARCH_REQUEST, VERSION, {"targets": ["car"], "colour": "red"})
    with pytest.raises(MessageError, match=r"unknown fields \['colour'\]"):
        decode_search_request(raw)
    with pytest.raises(MessageError, match="occupancy kind"):
        OccupancyRequest("cube").validate()


# ----------------------------------------------------------------------------- processes
def _search_cli(ep: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(cli_cmd("search", *args, "--connect", ep, "--timeout", "60"), env=zenoh_env(),
                          cwd=str(ROOT), capture_output=True, text=True, timeout=120)


def _box_distance(p, lo, hi) -> float:
    p = np.asarray(p, np.float64)
    return float(np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0)))


@pytest.mark.timeout(300)
def test_search_service_with_real_processes(tmp_path, procs, pca_file):
    from synthetic_world import World

    world = World.generate(0)
    cars = world.instances_of(world.class_id("car"))
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs.append(Proc("mapper", mapper_args(ep, ["queues.idle_flush_s=0.5"]), tmp_path))
    procs.append(Proc("edge", edge_args(ep, pca_file, frames=40, rate=4.0), tmp_path))
    with client(ep) as c:
        wait_for(lambda: mapped(c) >= 20, 180, what="20 frames mapped")
        # no cold start: the text model was loaded before anyone asked
        warm_s = wait_for(lambda: c.stats()["text_warm_up_s"], 120, what="text model warm-up")
        q = _search_cli(ep, "car", "--json")
        assert q.returncode == 0, q.stderr[-2000:]
        first = json.loads(q.stdout)            # exactly one JSON object
        assert set(first) == {"found", "look_next", "beyond", "events", "frames_mapped", "map_version",
                              "timings_ms", "missing_shards"}
        assert warm_s > 0
        # the first search found the text model loaded: the warm-up thread loaded it, not the search
        loads = c.stats()["text_models"]
        assert [v["thread"] for v in loads.values()] == ["text-warm-up"], loads
        # object-sized instances (>= 20 voxels at 0.5 m) are true cars: centroid within 2 voxels
        # of a car's box; small fragments can come from labels bleeding onto the ground at car
        # edges (the edge's feature sampling), they rank after the objects
        big = [i for i in first["found"] if i["voxels"] >= 20]
        assert len(big) >= 2, first["found"]
        assert first["found"][:len(big)] == big
        for inst in first["found"]:
            assert inst["target"] == "car" and 0.5 < inst["confidence"] <= 1.0
        for inst in big:
            assert min(_box_distance(inst["centroid"], t.aabb_min, t.aabb_max) for t in cars) <= 2 * VOX, inst
        for g in first["look_next"]:
            assert world.labels_at(np.array([g["position"]]))[0] == 0       # free in the true world
        # the goals are free in the map too (occupancy points)
        if first["look_next"]:
            occ = c.occupancy_points([g["position"] for g in first["look_next"]], radius=1.0)
            assert np.all(occ.states == 0)
        # more frames: the same objects keep their ids
        assert procs[1].p.wait(timeout=180) == 0              # the edge sent its 40 frames
        c.wait_settled(mapped=first["frames_mapped"] + 1, timeout=60)    # more frames mapped, all flushed
        later = c.search("car", max_instances=MAX_INSTANCES)      # all of them: none pushed out of the top 10
        assert later.frames_mapped > first["frames_mapped"]
        # every object-sized instance of the first answer is found again at its place (its
        # centroid within MATCH_M of a later instance's) under the same id
        pairs, lost = match_by_position(big, later.found, MATCH_M)
        assert not lost, f"not found again near their place: {[describe(i) for i in lost]}"
        renamed = [f"{describe(a)} is now #{b['id']}" for a, b in pairs if a["id"] != b["id"]]
        assert not renamed, f"{len(renamed)} of {len(big)} instances changed id: {renamed}"
        ids_then = {i["id"]: i for i in first["found"]}
        kept = [i for i in later.found if i["id"] in ids_then]
        for i in kept:
            a = ids_then[i["id"]]
            assert i["first_seen"] == a["first_seen"] and i["observations"] >= a["observations"] + 1
            # the same object: nearest true car unchanged
            near = [int(np.argmin([_box_distance(x["centroid"], t.aabb_min, t.aabb_max) for t in cars]))
                    for x in (a, i)]
            assert near[0] == near[1]
        # asking again without new frames: same ids, same instances
        again = c.search("car", max_instances=MAX_INSTANCES)
        assert [i["id"] for i in again.found] == [i["id"] for i in later.found]
        # an area that excludes every found instance finds none of them
        far = c.search("car", area=[1000, 1000, 1010, 1010])
        assert far.found == [] and far.look_next == []
        # occupancy: a slice and a box around the robot, consistent with each other
        cen = np.asarray(later.found[0]["centroid"])
        box = c.occupancy_box(cen - 3, cen + 3)
        assert box.states.ndim == 3 and set(np.unique(box.states)) <= {-1, 0, 1} and box.cell_m == VOX
        assert (box.states == 1).any()
        sl = c.occupancy_slice(cen[:2] - 3, cen[:2] + 3, (cen[2] - 3, cen[2] + 3))
        assert sl.states.shape == box.states.shape[:2]
        assert np.array_equal(sl.states == 1, (box.states == 1).any(2))
        # bad requests: one-line errors from the client and the CLI
        from query_client.client import QueryError

        with pytest.raises(QueryError, match="threshold"):
            c.search("car", threshold=1.5)
        with pytest.raises(QueryError, match="limit of"):
            c.occupancy_box([-2000, -2000, 0], [2000, 2000, 10])
        bad = _search_cli(ep, "car", "--threshold", "0")
        assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "threshold" in bad.stderr
    stop_all(reversed(procs))
