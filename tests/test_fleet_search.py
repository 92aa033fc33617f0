"""Fleet search (issue 44, docs/fleet.md "Fleet search"): the schemas, then real processes over
loopback Zenoh — one mapper (router mode, ROS 2 output on) and two edges on the synthetic world
(robots r1 and r2 on different laps of one town) — answering ``rayfronts search --fleet``,
``Client.fleet_search`` / ``watch_fleet_search`` / ``report_unreachable`` and each robot's ROS 2
goal topic (decoded by the real rclpy).

Checked against independent computations: each robot's position is the last camera position of
its synthetic lap (``World.trajectory``), the goals are those
:func:`planning.fleet_allocation.allocate_goals` gives on the reply's own candidates, and every
pair of goals lies at least the footprint apart."""
from __future__ import annotations

import json
import subprocess
import threading

import numpy as np
import pytest

from common.fleet_messages import (
    FLEET_JSON_FIELDS,
    MAX_FLEET_ROBOTS,
    SCHEMA_FLEET_SEARCH_REQUEST,
    FleetSearchReply,
    FleetSearchRequest,
    UnreachableReport,
    decode_fleet_search_reply,
    decode_fleet_search_request,
    decode_unreachable,
    encode_fleet_search_reply,
    encode_fleet_search_request,
    encode_unreachable,
)
from common.messages import VERSION, MessageError
from common.wire import encode_message
from common.zenoh_session import free_tcp_port
from tests.support.browser import module_browser
from tests.support.console import EventStream, click, http, matches_openapi, post_json, wait_page
from tests.support.ports import free_port
from tests.support.processes import ROOT, Proc, cli_cmd, stop_all, wait_for, zenoh_env
from tests.support.roles import client, edge_args, mapper_args, zenoh_client_config

FRAMES = 12
LAPS = {"r1": 1, "r2": 2}            # robot -> trajectory_seed (town seed 0)
FOOTPRINT = 4.0
browser = module_browser()


# ----------------------------------------------------------------------------- schemas
def test_fleet_request_round_trip_and_reply():
    req = FleetSearchRequest(targets=["car"], robots=["r1", "r2"], box=[0, 0, 30, 30], target_count=2,
                             footprint_m=5.0, standing=True, id="f1", max_goals=12)
    assert decode_fleet_search_request(encode_fleet_search_request(req)) == req.validate()
    rep = FleetSearchReply(id="f1", goals={"r1": {"position": [1.0, 2.0, 0.5]}, "r2": None},
                           robots={"r1": {"state": "assigned"}, "r2": {"state": "waiting"}}, waiting=["r2"],
                           utility=1.5, method="greedy", footprint_m=5.0)
    back = decode_fleet_search_reply(encode_fleet_search_reply(rep))
    assert back.to_dict() == rep.to_dict() and tuple(back.to_dict()) == FLEET_JSON_FIELDS
    u = decode_unreachable(encode_unreachable(UnreachableReport([1, 2, 3], "f1")))
    assert u.position == [1.0, 2.0, 3.0] and u.id == "f1"


@pytest.mark.parametrize("kw,match", [
    (dict(targets=["car"], robots=["r1", "r1"]), "robots named twice in the fleet: r1"),
    (dict(targets=["car"], robots=["r/1"]), r"robot id 'r/1' in the fleet must match"),
    (dict(targets=["car"], robots=[f"r{i}" for i in range(MAX_FLEET_ROBOTS + 1)]), "at most 32 robot ids"),
    (dict(targets=["car"], target_count=0), r"target_count must be an integer in \[1, 100\]"),
    (dict(targets=["car"], footprint_m=-1.0), r"footprint_m must be metres in \[0, 100\]"),
    (dict(targets=["car"], from_xyz=[0, 0, 0]), "from_xyz has no meaning in a fleet search"),
    (dict(targets=["car"], max_goals=0), "max_goals"),
    (dict(targets=[]), "targets must be a list of 1..16"),
])
def test_bad_fleet_requests_one_line(kw, match):
    with pytest.raises(MessageError, match=match) as e:
        FleetSearchRequest(**kw).validate()
    assert "\n" not in str(e.value)


def test_unknown_fleet_field_and_bad_unreachable():
    raw = encode_message(SCHEMA_FLEET_SEARCH_REQUEST, VERSION, {"targets": ["car"], "from_xyz": [0, 0, 0]})
    with pytest.raises(MessageError, match=r"unknown fields \['from_xyz'\]"):
        decode_fleet_search_request(raw)
    with pytest.raises(MessageError, match=r"unreachable position \[x, y, z\] must have 3 numbers"):
        UnreachableReport([1, 2]).validate()


def _goal(x: float, y: float) -> dict:
    return {"position": [x, y, 1.0], "heading_rad": 0.0, "score": 0.0, "gain_m3": 10.0, "distance_m": 1.0,
            "target": None, "frontier": [x, y, 1.0], "rays": [], "ray_z": 0.0}


def test_shard_merge_keeps_goals_apart_and_names_their_shard():
    from query_client.fleet_search import merge_fleet_replies

    req = FleetSearchRequest(targets=["car"]).validate()
    assigned = {"state": "assigned", "position": [0.0, 0.0, 1.0], "unreachable": 0}
    east = FleetSearchReply(goals={"r1": _goal(10, 0), "r2": _goal(11, 0)}, footprint_m=4.0, method="greedy",
                            robots={"r1": dict(assigned), "r2": dict(assigned)})
    west = FleetSearchReply(goals={"r1": _goal(-10, 0), "r2": _goal(-20, 0), "r3": None}, footprint_m=4.0,
                            robots={"r1": dict(assigned), "r2": dict(assigned),
                                    "r3": {"state": "waiting", "position": None, "unreachable": 0}})
    m = merge_fleet_replies([(west, {"shard": "west"}), (east, {"shard": "east"})], req)
    # shard-name order, east first: r1 keeps east's goal; east's r2 goal lies 1 m from it (closer
    # than the footprint) and is dropped, so r2 takes west's; west's r1 goal is not used; r3 waits
    assert m.goals["r1"]["shard"] == "east" and m.goals["r1"]["position"] == [10, 0, 1.0]
    assert m.goals["r2"]["shard"] == "west" and m.goals["r2"]["position"] == [-20, 0, 1.0]
    assert m.goals["r3"] is None and m.waiting == ["r3"] and m.robots["r2"]["state"] == "assigned"
    lone = FleetSearchReply(goals={"r1": _goal(1, 1)})
    assert merge_fleet_replies([(lone, {})], req) is lone


def test_unreachable_store_is_bounded_and_forgets():
    from mapper.fleet_search import Unreachable

    now = [0.0]
    u = Unreachable(3, 10.0, clock=lambda: now[0])
    for i in range(5):
        u.add("r1", [i, 0, 0])
    assert u.of("r1") == ((2.0, 0.0, 0.0), (3.0, 0.0, 0.0), (4.0, 0.0, 0.0))      # the oldest forgotten
    u.add("r2", [9, 9, 9])
    now[0] = 10.5
    assert u.of("r1") == () and u.of("r2") == ()                                   # past the TTL
    u.add("r3", [1, 1, 1])
    u.keep_only({"r1"})
    assert u.of("r3") == ()


# ----------------------------------------------------------------------------- processes
class Site:
    """The mapper, the edges and a client; ``positions``: each robot's last camera position."""

    def __init__(self, tmp, pca):
        from synthetic_world import World

        self.ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.procs: list[Proc] = []
        self.procs.append(Proc("mapper", mapper_args(self.ep, [
            "queues.idle_flush_s=0.5", f"search.fleet_footprint_m={FOOTPRINT}", "ros.enabled=true",
            "ros.keys=rmw_zenoh", "ros.rate_hz=0"]), tmp))
        self.edges = {}
        for r, lap in LAPS.items():
            self.edges[r] = Proc(f"edge-{r}", edge_args(self.ep, pca, robot=r, frames=FRAMES, rate=4.0, extra=[
                f"source.trajectory_seed={lap}", "publish.linger_s=600"]), tmp)
            self.procs.append(self.edges[r])
        self.port = free_port()
        self.procs.append(Proc("console", ["console", "--connect", self.ep, "--http", f"127.0.0.1:{self.port}",
                                           "--timeout", "60"], tmp))
        world = World.generate(0)
        self.positions = {r: np.asarray(world.trajectory("ground", FRAMES, seed=lap))[-1][:3, 3]
                          for r, lap in LAPS.items()}
        try:
            self.client = c = client(self.ep)
            # each robot's last frame mapped (an edge's first frame may go before the mapper subscribed)
            wait_for(lambda: all(c.stats()["robots"][r]["last_seq"] == FRAMES - 1 for r in LAPS), 240,
                     what="the last frame of both robots mapped")
            wait_for(lambda: c.stats()["text_warm_up_s"], 120, what="text model warm-up")
            c.fleet_search("car", timeout=60)            # the first search embeds the text: not timed
            wait_for(lambda: http(self.url("/api/config"), timeout=5)[0] == 200, 60, what="console serving")
        except BaseException:
            stop_all(reversed(self.procs))
            raise

    def cli(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run(cli_cmd("search", *args, "--connect", self.ep, "--timeout", "60"), env=zenoh_env(),
                              cwd=str(ROOT), capture_output=True, text=True, timeout=120)

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def close(self):
        self.client.close()
        stop_all(reversed(self.procs))


@pytest.fixture(scope="module")
def site(tmp_path_factory, pca_file):
    s = Site(tmp_path_factory.mktemp("fleet"), pca_file)
    yield s
    s.close()


def _allocation(rep: FleetSearchReply, unreachable: dict | None = None) -> dict:
    """What ``allocate_goals`` gives on the reply's own candidates, positions and found list."""
    from planning.fleet_allocation import FoundInstance, RobotSlot, allocate_goals
    from planning.look_next import Goal

    slots = [RobotSlot(r, tuple(i["position"]), tuple(map(tuple, (unreachable or {}).get(r, []))))
             for r, i in rep.robots.items() if i["state"] in ("assigned", "idle")]      # the fleet's order
    found = [FoundInstance(f["target"], tuple(f["centroid"])) for f in rep.found]
    a = allocate_goals(slots, [Goal.from_dict(d) for d in rep.candidates], footprint_m=rep.footprint_m,
                       unreachable_tol_m=1.0, found=found, target_count=1)
    return {r: None if g is None else [float(v) for v in g.position] for r, g in a.goals.items()}


def _check_distinct(rep: FleetSearchReply) -> list[np.ndarray]:
    goals = [np.asarray(g["position"]) for g in rep.goals.values() if g is not None]
    for i in range(len(goals)):
        for j in range(i + 1, len(goals)):
            assert np.linalg.norm(goals[i] - goals[j]) >= rep.footprint_m - 1e-9, rep.goals
    return goals


@pytest.mark.timeout(400)
def test_cli_fleet_gives_distinct_goals_per_robot(site):
    q = site.cli("car", "--fleet", "r1,r2", "--json")
    assert q.returncode == 0, q.stderr[-2000:]
    d = json.loads(q.stdout)                       # exactly one JSON object
    assert tuple(d) == FLEET_JSON_FIELDS
    rep = decode_fleet_search_reply(encode_fleet_search_reply(FleetSearchReply(**d)))
    assert rep.footprint_m == FOOTPRINT and rep.method == "greedy"
    assert len(rep.candidates) >= 4, rep.candidates           # something to share out
    assert set(rep.goals) == set(LAPS) and rep.waiting == [] and rep.gone == []
    for r in LAPS:                                  # each robot where its lap ended
        assert np.allclose(rep.robots[r]["position"], site.positions[r], atol=1e-4), (r, rep.robots[r])
        g = rep.goals[r]
        assert g is not None and rep.robots[r]["state"] == "assigned"
        assert any(np.allclose(g["position"], c["position"]) for c in rep.candidates)
        assert g["distance_m"] == pytest.approx(np.linalg.norm(np.asarray(g["position"]) - site.positions[r]),
                                                abs=1e-3)
    assert len(_check_distinct(rep)) == 2
    assert {r: g["position"] for r, g in rep.goals.items()} == _allocation(rep)
    # "all": the same robots (both present)
    q2 = site.cli("car", "--fleet", "all", "--json")
    assert q2.returncode == 0, q2.stderr[-2000:]
    assert sorted(json.loads(q2.stdout)["goals"]) == sorted(LAPS)


@pytest.mark.timeout(300)
def test_bad_fleet_input_one_line_nothing_else_changes(site):
    import zenoh

    c = site.client
    before = c.stats()
    for args, match in ((("--fleet", "r1,r9"), "unknown robot r9 in the fleet (robots this mapper knows: r1, r2)"),
                        (("--fleet", ""), "--fleet is empty"),
                        (("--fleet", " , "), "--fleet is empty"),
                        (("--fleet", "r1", "--from", "1,2,3"), "--from has no meaning with --fleet"),
                        (("--fleet", "r1,r1"), "robots named twice in the fleet: r1")):
        q = site.cli("car", *args, "--json")
        assert q.returncode != 0 and q.stdout == "", (args, q.stdout)
        lines = q.stderr.strip().splitlines()
        assert len(lines) == 1 and match in lines[0], (args, q.stderr)
    after = c.stats()
    assert after["request_errors"].get("fleet search", 0) == before["request_errors"].get("fleet search", 0) + 1
    assert set(after["robots"]) == set(LAPS)           # r9 was not added
    # a robot without a pose yet (its liveliness only): documented waiting, the others unchanged
    s = zenoh.open(zenoh_client_config(site.ep))
    try:
        tok = s.liveliness().declare_token("rayfronts/robots/r3/alive")
        wait_for(lambda: "r3" in c.stats()["robots"], 30, what="r3 known to the mapper")
        rep = c.fleet_search("car", ["r1", "r2", "r3"])
        assert rep.waiting == ["r3"] and rep.goals["r3"] is None and rep.robots["r3"]["state"] == "waiting"
        assert rep.robots["r3"]["position"] is None
        assert all(rep.goals[r] is not None for r in LAPS)
        assert {r: g["position"] for r, g in rep.goals.items() if r != "r3"} == _allocation(rep)
        every = c.fleet_search("car")                 # all present robots: r3 waits there too
        assert sorted(every.goals) == ["r1", "r2", "r3"] and every.waiting == ["r3"]
        tok.undeclare()
    finally:
        s.close()
    with pytest.raises(Exception, match="the fleet is empty|unknown robot"):
        c.fleet_search("car", ["nobody"])


@pytest.mark.timeout(300)
def test_console_fleet_search_http_api_matches_client_and_openapi(site):
    from openapi_spec_validator import validate

    c = site.client
    c.wait_settled(timeout=60)                       # a frozen map: the same answer twice
    direct = c.fleet_search("car", ["r1", "r2"])
    st, spec = http(site.url("/openapi.json"))
    assert st == 200
    validate(spec)
    st, got = http(site.url("/api/fleet_search?q=car&fleet=r1,r2"))
    assert st == 200, got
    matches_openapi(spec, "/api/fleet_search", "get", got)
    assert tuple(got) == FLEET_JSON_FIELDS and got["goals"] == direct.goals and got["found"] == direct.found
    assert all(got["goals"][r] is not None for r in LAPS)
    st, posted = post_json(site.url("/api/fleet_search"), {"q": ["car"], "fleet": ["r1", "r2"]})
    assert st == 200, posted
    matches_openapi(spec, "/api/fleet_search", "post", posted)
    assert posted["goals"] == direct.goals
    for url, match in (("/api/fleet_search?q=car&fleet=r1,r9", "unknown robot r9 in the fleet"),
                       ("/api/fleet_search?q=car&fleet=", "--fleet is empty"),
                       ("/api/fleet_search?q=car&fleet=r1&target_count=0", "target_count must be an integer")):
        st, err = http(site.url(url))
        assert st == 400 and set(err) == {"error"} and match in err["error"] and "\n" not in err["error"], (url, err)
        matches_openapi(spec, "/api/fleet_search", "get", err, st)
    s = EventStream("127.0.0.1", site.port, "/api/fleet_search/stream?q=car&fleet=r1,r2")
    try:
        ev = s.next()
        matches_openapi(spec, "/api/fleet_search/stream", "get", ev)
        assert ev["goals"] == direct.goals
    finally:
        s.close()


@pytest.mark.timeout(300)
def test_console_page_shows_each_robots_goal(site, browser):
    """The page in real headless chromium: targets and a fleet typed, Search clicked; its fleet
    rows are the API's answer (robots, states, goals to 2 decimals, paths to 1)."""
    site.client.wait_settled(timeout=60)
    st, api = http(site.url("/api/fleet_search?q=car&fleet=r1,r2"))
    assert st == 200 and all(api["goals"][r] for r in LAPS), api
    browser.navigate(site.url("/"))
    wait_page(browser, "document.readyState === 'complete' && !!document.getElementById('fleet')", 30, "the page")
    for field, text in (("q", "car"), ("fleet", "r1,r2")):
        browser.evaluate(f"document.getElementById('{field}').value = ''; document.getElementById('{field}').focus()")
        browser.call("Input.insertText", text=text)
    click(browser, "search")
    rows_js = "[...document.querySelectorAll('#fleet_goals tr')].map(r => [...r.cells].map(c => c.textContent))"
    rows = wait_page(browser, rows_js + ".length && " + rows_js, 60, "fleet goals")
    want = [[r, api["robots"][r]["state"], ", ".join(f"{v:.2f}" for v in api["goals"][r]["position"]),
             f"{api['goals'][r]['distance_m']:.1f}"] for r in sorted(api["goals"])]
    assert rows == want
    n_found = browser.evaluate("document.querySelectorAll('#instances tr').length")
    assert n_found == len(api["found"]) and "2 robots assigned" in browser.evaluate(
        "document.getElementById('status').textContent")


@pytest.mark.timeout(400)
def test_standing_unreachable_and_a_robot_leaving_gives_its_goal_to_another(site):
    import zenoh
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message

    c = site.client
    got: list[FleetSearchReply] = []
    cv = threading.Condition()

    def on_reply(r):
        with cv:
            got.append(r)
            cv.notify_all()

    def wait_reply(pred, what, timeout=60.0):
        with cv:
            assert cv.wait_for(lambda: any(pred(r) for r in got), timeout), (what, got[-1:] and got[-1].to_dict())
            return [r for r in got if pred(r)][-1]

    goal_keys = {r: [] for r in LAPS}                 # each robot's ROS 2 goal topic (rmw_zenoh layout)
    s = zenoh.open(zenoh_client_config(site.ep))

    def on_ros(sample):
        k = str(sample.key_expr)
        for r in LAPS:
            if k.startswith(f"0/{r}/goal_pose/"):
                goal_keys[r].append(sample.payload.to_bytes())

    sub = s.declare_subscriber("0/*/goal_pose/**", on_ros)
    own: list[FleetSearchReply] = []                   # r1's own key: its part of each answer
    own_sub = c.watch_fleet_goal(own.append, robot="r1")
    h = c.watch_fleet_search("car", on_reply, robots=["r1", "r2"])
    try:
        first = wait_reply(lambda r: all(r.goals.get(x) for x in LAPS), "both robots assigned")
        _check_distinct(first)
        assert {r: g["position"] for r, g in first.goals.items()} == _allocation(first)
        # each robot's goal reaches its own namespace as a Nav2 PoseStamped
        wait_for(lambda: all(goal_keys[r] for r in LAPS), 30, what="a ROS 2 goal per robot")
        for r in LAPS:
            ps = deserialize_message(goal_keys[r][-1], PoseStamped)
            assert ps.header.frame_id == "map"
            pos = [ps.pose.position.x, ps.pose.position.y, ps.pose.position.z]
            assert any(np.allclose(pos, x.goals[r]["position"], atol=1e-5) for x in got if x.goals.get(r)), r
        wait_for(lambda: own, 30, what="r1's fleet_goal")
        assert set(own[-1].goals) == {"r1"} and own[-1].id == h.id
        assert any(own[-1].goals["r1"] == x.goals["r1"] for x in got)
        # r1 cannot reach its goal: it gets another, at once, away from that position
        bad = first.goals["r1"]["position"]
        ack = c.report_unreachable("r1", bad, sid=h.id)
        assert ack["held"] == 1 and h.id in ack["goals"]
        new = ack["goals"][h.id]
        assert new is not None and np.linalg.norm(np.asarray(new["position"]) - bad) > 1.0
        after = wait_reply(lambda r: r.robots.get("r1", {}).get("unreachable") == 1, "the reassignment published")
        assert after.goals["r1"]["position"] == new["position"]
        assert {r: g["position"] for r, g in after.goals.items()} == _allocation(after, {"r1": [bad]})
        # r2 leaves (its edge stops: its liveliness token goes): r1 is assigned as if alone, every
        # candidate open to it again (r2's goal among them)
        site.edges["r2"].stop()
        gone = wait_reply(lambda r: r.gone == ["r2"], "r2 gone")
        assert gone.goals["r2"] is None and gone.robots["r2"]["state"] == "gone"
        alone = _allocation(gone, {"r1": [bad]})
        assert list(alone) == ["r1"] and gone.goals["r1"]["position"] == alone["r1"]
        # r2 joins again (its liveliness; its last pose is still known): both are assigned at once
        tok = s.liveliness().declare_token("rayfronts/robots/r2/alive")
        back = wait_reply(lambda r: r.gone == [] and r.goals.get("r2") is not None, "r2 back")
        _check_distinct(back)
        assert {r: g["position"] for r, g in back.goals.items()} == _allocation(back, {"r1": [bad]})
        tok.undeclare()
        fs = c.stats()["fleet_search"]
        assert fs["standing"] == 1 and fs["unreachable"] == {"r1": 1} and h.id in fs["leases_s"]
    finally:
        h.cancel()
        sub.undeclare()
        own_sub.undeclare()
        s.close()
