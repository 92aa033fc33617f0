"""Per-robot ROS 2 search, Nav2 goals and costmaps (``ros.robots``), decoded by the real rclpy.

In one process, fast: a map of the synthetic world (one-hot class features, so a search
needs no text model: the test's text encoder gives each class name its one-hot vector), the
mapper's real state, search service and ROS 2 output on a real Zenoh router session; the
test listens from a second (client) session on the rmw_zenoh keys and decodes every message
with ``rclpy.serialization.deserialize_message``. Checked against the search service's own
answers from the robot's position, ``costmap_slice`` of the same band, and rmw_zenoh's token
format written out by hand.
"""
from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import pytest
import torch
import zenoh

from common.feature_space import FeatureSpace
from common.ros2 import cdr
from common.search_messages import SearchRequest
from common.zenoh_session import free_tcp_port
from tests.support.ports import open_loopback_router
from tests.support.processes import wait_for
from tests.support.roles import zenoh_client_config

HW = (48, 64)
TEXT = "onehot-test"


class OneHotText:
    """Test text model: a class name → its one-hot vector over the world's classes."""

    name = TEXT

    def __init__(self, classes):
        self.classes = list(classes)

    def encode_labels(self, texts, templates="none"):
        out = torch.zeros((len(texts), len(self.classes)))
        for i, t in enumerate(texts):
            out[i, self.classes.index(t)] = 1.0
        return out


class Recorder:
    """Every sample under ``0/**`` (key, payload) in arrival order."""

    def __init__(self, s):
        self.lock = threading.Lock()
        self.samples: list = []
        self.sub = s.declare_subscriber("0/**", self._cb)

    def _cb(self, sample):
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def of(self, topic: str) -> list[bytes]:
        with self.lock:
            return [p for k, p in self.samples if k.startswith(f"0/{topic.strip('/')}/") and k.count("/") ==
                    topic.strip("/").count("/") + 3]


@pytest.fixture(scope="module")
def world_map():
    """The synthetic world, its classes' text model registered, and a map of 20 ground frames."""
    from mapper import query_answer
    from mapper.service_config import load_mapper_config
    from mapper.service_map import create_map
    from synthetic_world import World

    w = World.generate(3)
    query_answer._TEXT_ENCODERS[(TEXT, "cpu", "")] = OneHotText(w.classes)
    fs = FeatureSpace("label", "onehot", len(w.classes), text_model=TEXT)
    bg = [c for c in ("building", "road", "ground", "tree", "sky") if c in w.classes]
    cfg = load_mapper_config(None, ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=15",
                                    f"search.background={json.dumps(bg)}", "ros.enabled=true", "ros.rate_hz=0",
                                    "ros.costmap_z_band=[]"])
    poses = w.trajectory("ground", 240, seed=3)
    K = w.camera(HW, 90.0)
    frames = []
    for p in poses[:60:3]:
        r = w.render(p, K, HW)
        oh = torch.nn.functional.one_hot(torch.as_tensor(r.labels.astype(np.int64)), len(w.classes))
        frames.append((p, r.depth.astype(np.float32), r.rgb, oh.permute(2, 0, 1).float()))
    return dict(world=w, fs=fs, cfg=cfg, K=K, frames=frames, make=lambda: create_map(cfg, fs))


class Rig:
    """MapperState + SearchServer + RosOutput on a router session; a client session recording."""

    def __init__(self, wm, robots: dict, n_frames: int = 14, msg_serv: bool = False, record: bool = True):
        from dataclasses import replace

        from common.keys import KeySpace
        from mapper.outputs.ros import RosOutput
        from mapper.search_server import SearchServer
        from mapper.state import MapperState, RobotState

        ros = wm["cfg"].ros
        cfg = replace(wm["cfg"], ros=replace(ros, robots=robots, msg_serv=replace(ros.msg_serv, enabled=msg_serv)))
        cfg.ros.validate()
        self.wm = wm
        self.state = st = MapperState(cfg, threading.Event())
        st.map, st.space, st.keys = wm["make"](), wm["fs"], KeySpace(cfg.zenoh.prefix)
        self.frames_done = 0
        self.integrate(n_frames)
        port = free_tcp_port()
        st.session = open_loopback_router(port)
        self.client = zenoh.open(zenoh_client_config(f"tcp/127.0.0.1:{port}"))
        self.rec = Recorder(self.client) if record else None

        class QueryCopies:      # the query server's part a search reads: the map's query copy
            def query_copy(_, timings, flush=False):
                from semantic_map.query_copy import QueryCopy

                return QueryCopy().take(st.map, st.map_gen)

        self.search = SearchServer(st, QueryCopies())
        for rid in robots:
            st.robots[rid] = RobotState(rid, queue=__import__("collections").deque())
        self.out = RosOutput(st, search=self.search).start()
        time.sleep(0.5)

    def integrate(self, n: int) -> None:
        st, K = self.state, self.wm["K"]
        for p, d, rgb, f in self.wm["frames"][self.frames_done:self.frames_done + n]:
            st.map.integrate(p, K, d, rgb, f)
            st.map_gen += 1
            st.version += 1
            st.mapped += 1
        self.frames_done += n
        st.map.flush()

    def place(self, rid: str, xyz, yaw: float = 0.0, stamp: float = 1000.0) -> None:
        """The robot's last mapped frame at ``xyz`` looking along ``yaw`` (what the map worker records)."""
        P = np.eye(4)
        fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        P[:3, 0], P[:3, 1], P[:3, 2] = np.cross(fwd, [0, 0, 1.0]), [0, 0, -1.0], fwd   # RDF camera axes
        P[:3, 3] = xyz
        with self.state.robots_lock:
            self.state.robots[rid].pose, self.state.robots[rid].pose_stamp = P, stamp

    def close(self):
        self.out.close()
        self.client.close()
        self.state.session.close()


def _pose_array(raw):
    from geometry_msgs.msg import PoseArray
    from rclpy.serialization import deserialize_message

    pa = deserialize_message(raw, PoseArray)
    return pa, np.array([[p.position.x, p.position.y, p.position.z] for p in pa.poses]).reshape(-1, 3)


def _stamped(raw):
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message

    return deserialize_message(raw, PoseStamped)


def _yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y ** 2 + q.z ** 2))


def _wait_count(rec, topic, n, what):
    return wait_for(lambda: len(rec.of(topic)) >= n or None, 20, what=what)


@pytest.mark.timeout(120)
def test_two_robots_get_goals_ranked_from_their_own_positions(world_map):
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import Float32, Float32MultiArray, String, UInt32

    rig = Rig(world_map, {"r1": {"targets": ["car"], "approach": False},
                          "r2": {"targets": ["car"], "namespace": "/bot2", "approach": False, "frame_id": "odom"}})
    try:
        a, b = np.array([2.0, 2.0, 1.2]), np.array([30.0, 25.0, 1.2])
        rig.place("r1", a, stamp=1234.5)
        rig.place("r2", b, stamp=77.25)
        rig.out.robots.update_all()
        for ns, xyz, fid, stamp in (("/r1", a, "map", 1234.5), ("/bot2", b, "odom", 77.25)):
            base = f"{ns}/rayfronts/search"
            _wait_count(rig.rec, f"{base}/status", 1, f"{ns} answered")
            ref = rig.search.run_search(SearchRequest(targets=["car"], z_band=[-0.5, 3.0], threshold=0.5,
                                                      max_goals=5, max_instances=10, from_xyz=list(xyz)))
            assert len(ref.look_next) >= 2, "there is something to rank"
            pa, gxyz = _pose_array(rig.rec.of(f"{base}/goals")[-1])
            assert pa.header.frame_id == fid and pa.header.stamp.sec + pa.header.stamp.nanosec * 1e-9 == \
                pytest.approx(stamp)
            np.testing.assert_allclose(gxyz, [g["position"] for g in ref.look_next], atol=1e-9)
            # each goal's distance is from this robot's position
            np.testing.assert_allclose([g["distance_m"] for g in ref.look_next],
                                       np.linalg.norm(gxyz - xyz, axis=1), atol=1e-6)
            sc = deserialize_message(rig.rec.of(f"{base}/goal_scores")[-1], Float32MultiArray)
            np.testing.assert_allclose(sc.data, [g["score"] for g in ref.look_next], rtol=1e-6)
            # the Nav2 goal: the best look-next goal (nothing is confident enough to approach)
            gs = _stamped(rig.rec.of(f"{ns}/goal_pose")[-1])
            assert gs.header.frame_id == fid
            np.testing.assert_allclose([gs.pose.position.x, gs.pose.position.y, gs.pose.position.z],
                                       ref.look_next[0]["position"], atol=1e-9)
            assert _yaw(gs.pose.orientation) == pytest.approx(ref.look_next[0]["heading_rad"], abs=1e-6)
            # feedback: best confidence and objects found so far, found poses
            _, fxyz = _pose_array(rig.rec.of(f"{base}/result_poses")[-1])
            cen = np.array([f["centroid"] for f in ref.found]).reshape(-1, 3)
            assert len(cen) > 0
            np.testing.assert_allclose(fxyz[np.lexsort(fxyz.T)], cen[np.lexsort(cen.T)], atol=1e-9)
            best = deserialize_message(rig.rec.of(f"{base}/best_confidence")[-1], Float32).data
            assert best == pytest.approx(max(f["confidence"] for f in ref.found), abs=1e-6)
            assert deserialize_message(rig.rec.of(f"{base}/objects_found")[-1], UInt32).data == len(cen)
            status = json.loads(deserialize_message(rig.rec.of(f"{base}/status")[-1], String).data)
            assert status["goal"]["kind"] == "look" and status["targets"] == ["car"]
        # the two robots' rankings differ: each nearest-first among equals from its own place
        _, g1 = _pose_array(rig.rec.of("/r1/rayfronts/search/goals")[-1])
        _, g2 = _pose_array(rig.rec.of("/bot2/rayfronts/search/goals")[-1])
        assert not np.array_equal(g1, g2)
        # a robot that moves gets its list re-ranked from where it is now
        rig.place("r1", b, stamp=1240.0)
        n = len(rig.rec.of("/r1/rayfronts/search/goals"))
        rig.out.robots.update("r1")
        _wait_count(rig.rec, "/r1/rayfronts/search/goals", n + 1, "r1 re-ranked")
        _, g1b = _pose_array(rig.rec.of("/r1/rayfronts/search/goals")[-1])
        np.testing.assert_allclose(g1b, g2, atol=1e-9)      # same map, same place: the same list as r2's
    finally:
        rig.close()


@pytest.mark.timeout(120)
def test_goal_topic_quiet_while_the_goal_holds_and_approach_when_confident(world_map):
    rig = Rig(world_map, {"r1": {"targets": ["car"], "approach": False, "goal_min_move_m": 0.5,
                                 "goal_min_turn_deg": 20}})
    try:
        a = np.array([2.0, 2.0, 1.2])
        rig.place("r1", a)
        for _ in range(4):                          # the same map and place: the same goal
            rig.out.robots.update("r1")
        wait_for(lambda: len(rig.rec.of("/r1/rayfronts/search/status")) >= 4 or None, 20, what="4 answers")
        time.sleep(0.3)
        assert len(rig.rec.of("/r1/goal_pose")) == 1
        # a small move of the robot (the ranked list may change, the goal moves < 0.5 m): still quiet
        rig.place("r1", a + [0.05, 0.0, 0.0])
        rig.out.robots.update("r1")
        time.sleep(0.3)
        assert len(rig.rec.of("/r1/goal_pose")) == 1
        # a confident found object becomes the goal: its approach pose, facing it
        rig.out.robots.robots["r1"].cfg.approach = True
        rig.out.robots.update("r1")
        wait_for(lambda: len(rig.rec.of("/r1/goal_pose")) == 2 or None, 20, what="the approach goal")
        gs = _stamped(rig.rec.of("/r1/goal_pose")[-1])
        rep = rig.out.robots.robots["r1"].last_reply
        f = rep.found[0]
        assert f["confidence"] >= 0.9
        p = np.array([gs.pose.position.x, gs.pose.position.y, gs.pose.position.z])
        c = np.asarray(f["centroid"])
        half = np.linalg.norm(np.subtract(f["box_max"], f["box_min"])[:2]) / 2
        assert np.linalg.norm(p[:2] - c[:2]) == pytest.approx(half + 1.0, abs=1e-6)
        assert p[2] == pytest.approx(a[2] + 0.0, abs=0.06)
        to_c = c[:2] - p[:2]
        assert _yaw(gs.pose.orientation) == pytest.approx(math.atan2(to_c[1], to_c[0]), abs=1e-6)
    finally:
        rig.close()


@pytest.mark.timeout(120)
def test_costmap_fixed_origin_transient_local_equals_slice(world_map):
    from nav_msgs.msg import OccupancyGrid
    from rclpy.serialization import deserialize_message

    from common.ros2.keys import parse_liveliness, parse_qos
    from planning.occupancy_queries import costmap_slice

    rig = Rig(world_map, {"r1": {"costmap_window_m": 24.0, "costmap_resolution_m": 1.0},
                          "r2": {"costmap_window_m": 24.0, "costmap_resolution_m": 1.0,
                                 "unknown_near_obstacle": "occupied", "unknown_near_obstacle_m": 1.5}}, n_frames=4)
    try:
        # a robot moving a little at each of ten map updates: origin and size stay
        grids, refs = [], []
        for i in range(10):
            rig.integrate(1)
            rig.place("r1", np.array([0.2 * i, 23.4 - 0.1 * i, 1.5]))     # on the road the frames drove
            rig.out.robots.update("r1")
            wait_for(lambda i=i: len(rig.rec.of("/r1/rayfronts/costmap")) == i + 1 or None, 20, what=f"costmap {i}")
            og = deserialize_message(rig.rec.of("/r1/rayfronts/costmap")[-1], OccupancyGrid)
            o = np.array([og.info.origin.position.x, og.info.origin.position.y])
            states, origin, cell = costmap_slice(rig.state.map.occupancy_view(), 0.5, o + 0.25,
                                                 o + np.array([og.info.width, og.info.height]) * 1.0 - 0.25,
                                                 [0.5, 1.5], 2)
            grids.append(og)
            refs.append(states)
            np.testing.assert_allclose(origin, o)
            assert cell == og.info.resolution == 1.0 and og.info.origin.position.z == 0.5
        assert {(g.info.width, g.info.height) for g in grids} == {(24, 24)}
        assert len({(g.info.origin.position.x, g.info.origin.position.y) for g in grids}) == 1
        o = grids[0].info.origin.position
        # the window was centred on the robot's first position (to a whole cell)
        assert abs(o.x + 12 - 0.0) <= 1.0 and abs(o.y + 12 - 23.4) <= 1.0 and o.x % 1.0 == o.y % 1.0 == 0.0
        for og, ref in zip(grids, refs, strict=True):
            grid = np.asarray(og.data, np.int8).reshape(og.info.height, og.info.width).T
            np.testing.assert_array_equal(grid, np.where(ref == 1, 100, np.where(ref == 0, 0, -1)))
        assert {-1, 0, 100} <= set(np.unique(np.asarray(grids[-1].data)).tolist())
        assert len({bytes(np.asarray(g.data, np.int8)) for g in grids}) > 1, "the map changed under it"
        # r2 where r1 began (the same window) on the same map: unknown cells within 1.5 m (centre
        # to centre) of an occupied one are occupied
        rig.place("r2", np.array([0.0, 23.4, 1.5]))
        rig.out.robots.update("r2")
        wait_for(lambda: rig.rec.of("/r2/rayfronts/costmap") or None, 20, what="r2's costmap")
        og2 = deserialize_message(rig.rec.of("/r2/rayfronts/costmap")[-1], OccupancyGrid)
        g1 = np.asarray(grids[-1].data, np.int8).reshape(24, 24).T
        g2 = np.asarray(og2.data, np.int8).reshape(24, 24).T
        assert og2.info.origin.position.x == grids[-1].info.origin.position.x
        occ = np.argwhere(g1 == 100)
        near = np.array([[(g1[i, j] == -1) and ((occ - [i, j]) ** 2).sum(1).min() <= 1.5 ** 2 for j in range(24)]
                         for i in range(24)])
        assert near.sum() > 5
        np.testing.assert_array_equal(g2, np.where(near, 100, g1))

        # transient-local + reliable, depth 1, in the publisher's liveliness token (rmw_zenoh's
        # format: <reliability>:<durability>:<history>,<depth>:... each only where not default;
        # TRANSIENT_LOCAL = 1, depth 1); the other topics keep the defaults
        toks = [parse_liveliness(str(r.ok.key_expr)) for r in
                rig.client.liveliness().get("@ros2_lv/0/**", timeout=3.0) if r.ok is not None]
        pubs = {t["topic"]: t for t in toks if t and t["kind"] == "publisher"}
        assert pubs["/r1/rayfronts/costmap"]["qos"] == ":1:,1:,:,:,,"
        assert pubs["/r1/rayfronts/costmap"]["type"] == "nav_msgs/msg/OccupancyGrid"
        assert parse_qos(pubs["/r1/rayfronts/costmap"]["qos"]) == {"reliability": 1, "durability": 1, "history": 1,
                                                                   "depth": 1}
        assert pubs["/r1/goal_pose"]["qos"] == "::,:,:,:,,"
        subs = {t["topic"] for t in toks if t and t["kind"] == "subscription"}
        assert "/r1/rayfronts/search" in subs

        # a late subscriber (rmw_zenoh's transient-local subscription: an advanced subscriber
        # detecting late publishers) gets the last grid, once
        late: list = []
        key = f"0/r1/rayfronts/costmap/nav_msgs::msg::dds_::OccupancyGrid_/{cdr.type_hash(OCC, 'jazzy')}"
        sub = zenoh.ext.declare_advanced_subscriber(rig.client, "0/r1/rayfronts/costmap/*/*",
                                                    lambda s: late.append((str(s.key_expr), s.payload.to_bytes())),
                                                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
        wait_for(lambda: late or None, 20, what="the late subscriber's grid")
        time.sleep(0.5)
        assert len(late) == 1 and late[0][0] == key
        assert late[0][1] == rig.rec.of("/r1/rayfronts/costmap")[-1]
        sub.undeclare()
    finally:
        rig.close()


OCC = "nav_msgs/msg/OccupancyGrid"


@pytest.mark.timeout(120)
def test_bad_search_input_one_line_counted_and_serving_goes_on(world_map, caplog):
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    rig = Rig(world_map, {"r1": {}}, n_frames=6)
    h = cdr.type_hash("std_msgs/msg/String", "jazzy")

    def put(ns, text):
        rig.client.put(f"0/{ns}/rayfronts/search/std_msgs::msg::dds_::String_/{h}",
                       serialize_message(String(data=text)))

    try:
        robots = rig.out.robots
        rig.place("r1", np.array([2.0, 2.0, 1.2]))
        caplog.set_level("WARNING", logger="rayfronts.mapper")
        cases = [("nobody", "car", "unknown_namespace", ("unknown robot namespace '/nobody'",
                                                         "ros.robots.<id>.namespace=/nobody")),
                 ("r1", "{targets: [car", "bad_search", ("not YAML",)),
                 ("r1", '{"targets": ["car"], "treshold": 0.4}', "bad_search", ("treshold", "allowed: targets")),
                 ("r1", '{"targets": ["car"], "threshold": 1.5}', "bad_search", ("threshold must be a probability",)),
                 ("r1", "[1, 2]", "bad_search", ("expected an object",))]
        for ns, text, reason, words in cases:
            n = robots.rejected[reason]
            put(ns, text)
            wait_for(lambda r=reason, k=n + 1: robots.rejected[r] == k or None, 20, what=f"{text!r} counted")
            line = robots.last_error
            assert "\n" not in line and line.startswith(f"ROS 2 search on /{ns}/rayfronts/search rejected: ")
            assert all(w in line for w in words), line
        logged = [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]
        assert any("unknown robot namespace" in m for m in logged) and any("not YAML" in m for m in logged)
        assert rig.out.errors >= 4 and robots.robots["r1"].search is None
        # still serving: a good request on the same topic is answered
        put("r1", '{"targets": ["car"], "threshold": 0.5, "max_goals": 3}')
        wait_for(lambda: rig.rec.of("/r1/rayfronts/search/goals") or None, 30, what="the good search answered")
        pa, g = _pose_array(rig.rec.of("/r1/rayfronts/search/goals")[-1])
        assert 0 < len(g) <= 3 and robots.robots["r1"].search.targets == ["car"]
        # a robot of the mapper's table that is not configured may ask on its own namespace
        from mapper.state import RobotState

        with rig.state.robots_lock:
            rig.state.robots["r9"] = RobotState("r9", queue=__import__("collections").deque())
        rig.place("r9", np.array([5.0, 5.0, 1.2]))
        put("r9", "car")
        wait_for(lambda: rig.rec.of("/r9/rayfronts/search/goals") or None, 30, what="r9 answered")
        assert robots.rejected["unknown_namespace"] == 1
    finally:
        rig.close()


def _cloud(raw) -> tuple[list[str], dict[str, np.ndarray], str]:
    """rclpy PointCloud2 → (field names, {field: (N,) float32} through its field table, frame_id)."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    msg = deserialize_message(raw, PointCloud2)
    assert msg.height == 1 and msg.row_step == msg.point_step * msg.width and not msg.is_bigendian
    a = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.width, msg.point_step)
    assert all(f.datatype == 7 and f.count == 1 for f in msg.fields)
    return ([f.name for f in msg.fields], {f.name: a[:, f.offset:f.offset + 4].copy().view("<f4").reshape(-1)
                                           for f in msg.fields}, msg.header.frame_id)


@pytest.mark.timeout(120)
def test_upstream_messaging_service_drop_in(world_map):
    """Upstream RayFronts' interface: text queries as std_msgs/String on
    rayfronts/msg_serv/new_text_query; per query x, y, z, sim clouds of the voxels and
    x, y, z, theta, phi, sim of the rays, only on topics someone subscribes to; sim the softmax
    across the queries (checked against the map's own features)."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    rig = Rig(world_map, {}, n_frames=10, msg_serv=True, record=False)
    got: dict = {}
    lock = threading.Lock()

    def keep(sample):
        with lock:
            got.setdefault("/".join(str(sample.key_expr).split("/")[1:-2]), []).append(sample.payload.to_bytes())

    try:
        subs = [rig.client.declare_subscriber(f"0/rayfronts/msg_serv/{t}/*/*", keep)
                for t in ("voxels_sim/q0_car", "voxels_sim/q1_building", "rays_sim/q1_building",
                          "voxel_similarity/q0_car")]
        time.sleep(0.5)
        h = cdr.type_hash("std_msgs/msg/String", "jazzy")
        for text in ("car", "building", "car", ""):
            rig.client.put(f"0/rayfronts/msg_serv/new_text_query/std_msgs::msg::dds_::String_/{h}",
                           serialize_message(String(data=text)))
            time.sleep(0.3)
        ms = rig.out.msg_serv
        wait_for(lambda: ms.rejected == 1 or None, 20, what="the empty query refused")
        assert ms.queries == ["car", "building"] and "empty query text" in ms.last_error
        ms.publish()                    # (also after each query) now with both queries
        wait_for(lambda: all(f"rayfronts/msg_serv/{t}" in got for t in
                             ("voxels_sim/q0_car", "voxels_sim/q1_building", "rays_sim/q1_building",
                              "voxel_similarity/q0_car")) or None,
                 30, what="the four subscribed clouds")
        with lock:
            car, bld, rays = (got[f"rayfronts/msg_serv/{t}"][-1] for t in
                              ("voxels_sim/q0_car", "voxels_sim/q1_building", "rays_sim/q1_building"))
        names, c0, fid = _cloud(car)
        _, c1, _ = _cloud(bld)
        with lock:      # the name for the same cloud (ros.msg_serv.voxel_alias)
            alias = _cloud(got["rayfronts/msg_serv/voxel_similarity/q0_car"][-1])
        assert alias[0] == names and all(np.array_equal(alias[1][k], c0[k]) for k in names)
        assert names == ["x", "y", "z", "sim"] and fid == "map"
        # the map's voxels, all of them (threshold 0), the same order in both clouds
        m = rig.state.map
        vox = float(m.cfg.vox_size)
        ijk = m.voxel_ijk().numpy()
        xyz = np.stack([c0["x"], c0["y"], c0["z"]], 1)
        ref = (ijk + 0.5) * vox
        assert len(xyz) == len(ref) > 100
        np.testing.assert_allclose(xyz[np.lexsort(xyz.T)], ref[np.lexsort(ref.T)], atol=1e-5)
        np.testing.assert_array_equal(xyz, np.stack([c1["x"], c1["y"], c1["z"]], 1))
        # sim: softmax over the two queries of 100 * cosine with each class's one-hot vector
        w = world_map["world"]
        f = m.voxels().features.float().numpy()
        cos = f[:, [w.classes.index("car"), w.classes.index("building")]] / np.linalg.norm(f, axis=1)[:, None]
        p = np.exp(100 * (cos - cos.max(1, keepdims=True)))
        p /= p.sum(1, keepdims=True)
        order = {tuple(np.round(v, 4)): i for i, v in enumerate(ref)}
        idx = np.array([order[tuple(np.round(v, 4))] for v in xyz])
        np.testing.assert_allclose(c0["sim"] + c1["sim"], 1.0, atol=1e-5)
        sure = np.abs(cos[idx, 0] - cos[idx, 1]) > 0.05          # beyond the float16 copy's rounding
        assert sure.sum() > 50 and (p[idx, 0] > 0.99).sum() > 5 and (p[idx, 1] > 0.99).sum() > 5
        np.testing.assert_allclose(c0["sim"][sure], p[idx[sure], 0], atol=0.02)
        # rays: each ray's frontier, its direction's angles, its share of "building"
        rn, r1, _ = _cloud(rays)
        assert rn == ["x", "y", "z", "theta", "phi", "sim"]
        o = m.ray_geometry()[0].numpy()
        d = m.ray_geometry()[1].numpy()
        assert len(r1["x"]) == len(o) > 10
        np.testing.assert_allclose(np.stack([r1["x"], r1["y"], r1["z"]], 1), o, atol=1e-5)
        np.testing.assert_allclose(r1["theta"], np.degrees(np.arctan2(d[:, 1], d[:, 0])), atol=1e-3)
        np.testing.assert_allclose(r1["phi"], np.degrees(np.arccos(np.clip(d[:, 2], -1, 1))), atol=1e-3)
        assert ((r1["sim"] >= 0) & (r1["sim"] <= 1)).all()
        # nobody subscribes to the 'all' clouds, the car's rays or the frontiers: never published
        pub = rig.out.published
        assert pub.get("/rayfronts/msg_serv/voxels_sim/q0_car", 0) >= 1
        for t in ("voxels_sim/all", "rays_sim/all", "rays_sim/q0_car", "frontiers", "ray_similarity/q1_building"):
            assert pub.get(f"/rayfronts/msg_serv/{t}", 0) == 0, t
        for sub in subs:
            sub.undeclare()
    finally:
        rig.close()


def test_costmap_window_unknown_near_obstacles_and_goal_gate_pure():
    """The pure parts against brute force: the window's origin, unknown cells near obstacles,
    the goal gate's thresholds, the platforms' costmap bands."""
    from mapper.outputs.ros_robots import (
        GoalGate,
        RobotSearch,
        RosRobots,
        robot_section,
        unknown_near_obstacles,
        window_origin,
    )

    # window: re-centred (whole cells) only when the robot leaves the middle half
    o = window_origin(None, np.array([3.3, -2.1]), 20, 0.5)
    np.testing.assert_allclose(o, [-2.0, -7.5])      # floor((3.3 - 5) / 0.5) * 0.5, floor((-2.1 - 5) / 0.5) * 0.5
    for xy in ([5.4, -2.1], [0.6, -4.9], [5.5, 0.0]):        # in the middle half [0.5, 5.5] x [-5, 0]
        assert window_origin(o, np.array(xy), 20, 0.5) is o
    moved = window_origin(o, np.array([6.2, -2.1]), 20, 0.5)
    np.testing.assert_allclose(moved, [1.0, -7.5])
    # unknown near obstacles: brute force over cell centres
    rng = np.random.default_rng(4)
    st = rng.choice([-1, 0, 1], size=(30, 25), p=[0.5, 0.4, 0.1]).astype(np.int8)
    for r in (0.5, 1.0, 1.5, 2.9):
        got = unknown_near_obstacles(st, r)
        occ = np.argwhere(st == 1)
        ref = np.zeros(st.shape, bool)
        for i, j in np.argwhere(st == -1):
            ref[i, j] = bool(((occ - [i, j]) ** 2).sum(1).min() <= r * r)
        np.testing.assert_array_equal(got, ref)
        assert r < 1 and not got.any() or got.any()
    # the gate: distance and heading (wrapped), and a change of kind
    g = GoalGate(0.5, 20)
    assert g.due(np.zeros(3), 0.0, "look") and not g.due(np.array([0.4, 0.2, 0]), 0.0, "look")
    assert not g.due(np.zeros(3), math.radians(19), "look") and g.due(np.zeros(3), math.radians(21), "look")
    assert not g.due(np.zeros(3), math.radians(21) - 2 * math.pi, "look")     # the same heading
    assert g.due(np.zeros(3), math.radians(21), "approach")
    # costmap bands: ground fixed (world z), aerial around the robot, or as given
    rr = RosRobots.__new__(RosRobots)
    pose = np.eye(4)
    pose[2, 3] = 12.0
    assert rr.costmap_band(RobotSearch("a", robot_section("a", {})), pose) == [0.5, 1.5]
    assert rr.costmap_band(RobotSearch("b", robot_section("b", {"platform": "aerial"})), pose) == [11.0, 13.0]
    assert rr.costmap_band(RobotSearch("b", robot_section("b", {"platform": "aerial"})), None) is None
    assert rr.costmap_band(RobotSearch("c", robot_section("c", {"costmap_z_band": [1, 2]})), pose) == [1.0, 2.0]


@pytest.mark.timeout(120)
def test_path_to_the_goal_over_free_cells_is_shortest(world_map):
    """nav_msgs/Path (``path``): from the robot over its costmap to the goal, never through an
    occupied cell, as cheap as scipy's Dijkstra finds over the same 8-connected graph (a step:
    its length times 1 into a free cell, 3 into an unknown one)."""
    from nav_msgs.msg import OccupancyGrid, Path
    from rclpy.serialization import deserialize_message
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    rig = Rig(world_map, {"r1": {"targets": ["car"], "approach": False, "path": True, "costmap_window_m": 60.0}})
    try:
        xyz = np.array([0.0, 23.4, 1.5])
        rig.place("r1", xyz)
        rig.out.robots.update("r1")
        wait_for(lambda: all(rig.rec.of(t) for t in ("/r1/rayfronts/search/path", "/r1/rayfronts/costmap",
                                                     "/r1/goal_pose")) or None, 30,
                 what="the path, the costmap and the goal")
        path = deserialize_message(rig.rec.of("/r1/rayfronts/search/path")[-1], Path)
        og = deserialize_message(rig.rec.of("/r1/rayfronts/costmap")[-1], OccupancyGrid)
        goal = _stamped(rig.rec.of("/r1/goal_pose")[-1])
        pts = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses])
        assert len(pts) > 5 and path.header.frame_id == "map"
        np.testing.assert_allclose(pts[0], xyz[:2], atol=1e-9)
        np.testing.assert_allclose(pts[-1], [goal.pose.position.x, goal.pose.position.y], atol=1e-9)
        nx, ny, cell = og.info.width, og.info.height, og.info.resolution
        o = np.array([og.info.origin.position.x, og.info.origin.position.y])
        grid = np.asarray(og.data, np.int8).reshape(ny, nx).T
        ij = np.floor((pts - o) / cell).astype(int)
        assert (grid[ij[1:-1, 0], ij[1:-1, 1]] != 100).all()               # never through an obstacle
        assert (grid[ij[1:-1, 0], ij[1:-1, 1]] == 0).sum() > 5               # and over known free cells
        step = np.abs(np.diff(ij, axis=0))
        assert (step.max(1) == 1).all()                                    # 8-neighbours, one at a time
        # as short as the shortest way over the same graph (scipy's Dijkstra)
        ok = grid != 100
        ok[tuple(ij[-1])] = True
        cost = np.where(grid == 0, 1.0, 3.0)
        cost[tuple(ij[-1])] = 1.0
        idx = np.arange(nx * ny).reshape(nx, ny)
        rows, cols, w = [], [], []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == dj == 0:
                    continue
                a = ok[max(0, -di):nx - max(0, di), max(0, -dj):ny - max(0, dj)]
                b = ok[max(0, di):nx - max(0, -di), max(0, dj):ny - max(0, -dj)]
                sa = idx[max(0, -di):nx - max(0, di), max(0, -dj):ny - max(0, dj)][a & b]
                sb = idx[max(0, di):nx - max(0, -di), max(0, dj):ny - max(0, -dj)][a & b]
                rows += [sa]
                cols += [sb]
                w += [math.hypot(di, dj) * cost[max(0, di):nx - max(0, -di), max(0, dj):ny - max(0, -dj)][a & b]]
        g = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(nx * ny,) * 2)
        best = dijkstra(g.tocsr(), indices=idx[tuple(ij[0])])[idx[tuple(ij[-1])]]
        entered = cost[ij[1:, 0], ij[1:, 1]]
        assert (np.hypot(*step.T) * entered).sum() == pytest.approx(best, abs=1e-9)
        assert best < 3.0 * np.hypot(*(ij[-1] - ij[0]))      # cheaper than straight through the unknown
    finally:
        rig.close()
