"""The ROS 2 wire format checked with the real ROS 2 client library (``rclpy`` wheels from
the package index): its ``serialize_message`` / ``deserialize_message`` are the authority.

* a real mapper process (``ros.enabled``) maps a synthetic-world edge; every message type it
  publishes (PointCloud2, MarkerArray, PoseArray, Float32MultiArray, OccupancyGrid) decodes
  with rclpy and equals the mapper's own answers (layers, ``Client.search``,
  ``Client.occupancy_slice``); a search starts from a std_msgs/String serialised by rclpy;
* each publisher numbers its samples 1, 2, 3, ... and carries its own gid, the XXH3-128 of
  its liveliness token key (as rmw_zenoh does, docs/key_space.md);
* the edge's live ``ros2`` source turns rclpy-serialised Image / CameraInfo / Odometry
  messages into exactly the frames they describe.
"""
from __future__ import annotations

import json
import math
import signal
import threading
import time

import numpy as np
import pytest
import xxhash
import zenoh

from common.ros2 import cdr
from common.zenoh_session import free_tcp_port
from tests.support.ports import open_loopback_router
from tests.support.processes import Proc, stop_all, wait_for
from tests.support.roles import SampleLog, client, edge_args, mapper_args, zenoh_client_config

STRING_KEY = "std_msgs::msg::dds_::String_"


def _dds(t: str) -> str:
    pkg, sub, name = t.split("/")
    return f"{pkg}::{sub}::dds_::{name}_"


def _cloud(msg) -> dict[str, np.ndarray]:
    """An rclpy PointCloud2 → {field: (N,) float32} read through its own field table."""
    raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.width, msg.point_step)
    return {f.name: raw[:, f.offset:f.offset + 4].copy().view("<f4").reshape(-1) for f in msg.fields}


class Recorder(SampleLog):
    """Every sample under ``0/rayfronts/**``: (key, payload, attachment) in arrival order."""

    def __init__(self, s, key: str = "0/rayfronts/**"):
        super().__init__(s, key)

    def of(self, topic: str) -> list:
        with self.lock:
            return [x for x in self.samples if x[0].startswith(f"0/{topic}/")]

    def last(self, topic: str, depth: int | None = None):
        """The last sample of ``topic`` (``depth``: of exactly that topic, not its sub-topics)."""
        got = [x for x in self.of(topic) if depth is None or x[0].count("/") == topic.count("/") + 3]
        return got[-1] if got else None


def _gid(token: str) -> bytes:
    """rmw_zenoh's gid of an entity, computed here: XXH3-128 of its token key, low then high
    64 bits, little endian."""
    v = xxhash.xxh3_128(token.encode()).intdigest()
    return v.to_bytes(16, "little")


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_mapper_ros_outputs_decode_with_rclpy(tmp_path, procs, pca_file):
    from geometry_msgs.msg import PoseArray
    from nav_msgs.msg import OccupancyGrid
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float32MultiArray, String
    from visualization_msgs.msg import MarkerArray

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs.append(Proc("mapper", mapper_args(ep, ["queues.idle_flush_s=0.5", "ros.enabled=true", "ros.rate_hz=2",
                                                 "ros.frame_id=odom", "ros.costmap_z_band=[0.0,2.0]",
                                                 "ros.robots.r1.approach=false",
                                                 "layers.max_voxels=100000000", "ros.max_rays=100000000"]),
                      tmp_path))
    s = None
    try:
        with client(ep) as c:
            wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
            s = zenoh.open(zenoh_client_config(ep))
            rec = Recorder(s)
            r1 = Recorder(s, "0/r1/**")
            time.sleep(0.5)
            procs.append(Proc("edge", edge_args(ep, pca_file, frames=24, rate=6.0), tmp_path))
            assert procs[1].p.wait(timeout=150) == 0
            assert c.wait_settled(mapped=24, timeout=60)["frames"]["mapped"] == 24
            vox_l, _ = c.layer("voxels")
            rays_l, _ = c.layer("rays")

            def final_cloud():
                last = rec.last("rayfronts/voxels")
                return last if last and deserialize_message(last[1], PointCloud2).width == len(vox_l["xyz"]) \
                    else None

            _, raw, _ = wait_for(final_cloud, 60, what="the final voxel cloud")
            pc = deserialize_message(raw, PointCloud2)
            assert pc.header.frame_id == "odom" and [f.name for f in pc.fields] == ["x", "y", "z", "rgb"]
            cl = _cloud(pc)
            xyz = np.stack([cl["x"], cl["y"], cl["z"]], 1)
            np.testing.assert_array_equal(xyz[np.lexsort(xyz.T)], vox_l["xyz"][np.lexsort(vox_l["xyz"].T)])
            def final_rays():
                # the rays go out in their own message, which can trail the cloud by a tick
                last = rec.last("rayfronts/rays")
                ma = deserialize_message(last[1], MarkerArray) if last else None
                return ma if ma and len(ma.markers) - 1 == len(rays_l["origin"]) else None

            ma = wait_for(final_rays, 60, what="the final ray markers")
            assert ma.markers[0].action == 3
            o = np.array([[m.points[0].x, m.points[0].y, m.points[0].z] for m in ma.markers[1:]])
            np.testing.assert_allclose(o, rays_l["origin"], atol=1e-6)

            # the costmap equals the planners' slice over the same cells
            og = deserialize_message(wait_for(lambda: rec.last("rayfronts/costmap"), 30, what="costmap")[1],
                                     OccupancyGrid)
            cell, nx, ny = og.info.resolution, og.info.width, og.info.height
            lo = np.array([og.info.origin.position.x, og.info.origin.position.y])
            assert og.info.origin.position.z == 0.0 and nx * ny == len(og.data) > 0
            ref = c.occupancy_slice(lo + cell / 2, lo + (np.array([nx, ny]) - 0.5) * cell, (0.0, 2.0))
            assert ref.states.shape == (nx, ny) and ref.cell_m == pytest.approx(cell)
            np.testing.assert_allclose(ref.origin, lo)
            grid = np.asarray(og.data, np.int8).reshape(ny, nx).T
            expect = np.where(ref.states == 1, 100, np.where(ref.states == 0, 0, -1))
            np.testing.assert_array_equal(grid, expect)
            assert {0, 100} <= set(np.unique(grid).tolist())

            # a standing search from ROS: a String serialised by rclpy (after a payload that is not one)
            h = cdr.type_hash("std_msgs/msg/String", "jazzy")
            s.put(f"0/rayfronts/search_text/{STRING_KEY}/{h}", b"\x00\x01\x00\x00\xff")
            s.put(f"0/rayfronts/search_text/{STRING_KEY}/{h}", serialize_message(String(data=" car , ")))
            wait_for(lambda: rec.last("rayfronts/search/goal_scores"), 120, what="the ROS search answer")
            rep = c.search("car", threshold=0.5, max_instances=10, max_goals=5)
            assert rep.found, "the synthetic world's cars are found"
            fm = deserialize_message(rec.last("rayfronts/search/found")[1], MarkerArray)
            assert fm.markers[0].action == 3
            cubes = [m for m in fm.markers[1:] if m.ns == "found"]
            labels = [m for m in fm.markers[1:] if m.ns == "found_label"]
            assert [m.id for m in cubes] == [m.id for m in labels] == [f["id"] for f in rep.found]
            for m, f in zip(cubes, rep.found, strict=True):
                assert m.type == 1 and m.header.frame_id == "odom"
                np.testing.assert_allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z],
                                           (np.asarray(f["box_min"]) + f["box_max"]) / 2, atol=1e-9)
                np.testing.assert_allclose([m.scale.x, m.scale.y, m.scale.z],
                                           np.asarray(f["box_max"]) - f["box_min"], atol=1e-9)
            assert all(m.type == 9 and f"#{f['id']}" in m.text and "car" in m.text
                       for m, f in zip(labels, rep.found, strict=True))
            fp = deserialize_message(rec.last("rayfronts/search/found_poses")[1], PoseArray)
            np.testing.assert_allclose([[p.position.x, p.position.y, p.position.z] for p in fp.poses],
                                       [f["centroid"] for f in rep.found], atol=1e-9)
            gp = deserialize_message(rec.last("rayfronts/search/goals")[1], PoseArray)
            gs = deserialize_message(rec.last("rayfronts/search/goal_scores")[1], Float32MultiArray)
            assert len(gp.poses) == len(gs.data) == len(rep.look_next) > 0
            np.testing.assert_allclose([[p.position.x, p.position.y, p.position.z] for p in gp.poses],
                                       np.array([g["position"] for g in rep.look_next]).reshape(-1, 3), atol=1e-9)
            np.testing.assert_allclose([math.atan2(2 * p.orientation.z * p.orientation.w,
                                                   1 - 2 * p.orientation.z ** 2) for p in gp.poses],
                                       [g["heading_rad"] for g in rep.look_next], atol=1e-6)
            np.testing.assert_allclose(np.asarray(gs.data), [g["score"] for g in rep.look_next], rtol=1e-6)
            assert gs.layout.dim[0].label == "goals" and gs.layout.dim[0].size == len(rep.look_next)
            # the answer's events as JSON (what this map version changed: the same for every search of it)
            ev = json.loads(deserialize_message(rec.last("rayfronts/search/events")[1], String).data)
            assert ev == rep.events

            # per publisher: increasing sequence numbers from 1 and the gid of its own liveliness token
            toks = [str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/0/**", timeout=3.0) if r.ok is not None]
            pub_tok = {"/".join(t.split("/")[9].split("%")[1:]): t for t in toks if t.split("/")[5] == "MP"}
            by_topic: dict[str, list] = {}
            for key, _, att in rec.samples:
                if key.startswith("0/rayfronts/search_text/"):
                    continue  # the test's own puts
                by_topic.setdefault("/".join(key.split("/")[1:-2]), []).append(cdr.parse_attachment(att))
            assert {"rayfronts/voxels", "rayfronts/rays", "rayfronts/costmap", "rayfronts/search/goals"} \
                <= set(by_topic)
            gids = {}
            for topic, atts in by_topic.items():
                # strictly increasing from 1 per publisher; a sample this recorder missed on a
                # loaded machine (Zenoh's default congestion control drops) leaves a gap
                seq = [a[0] for a in atts]
                assert seq[0] >= 1 and all(np.diff(seq) > 0), (topic, seq)
                assert len(seq) >= 0.5 * seq[-1], (topic, seq)
                assert {a[2] for a in atts} == {_gid(pub_tok[topic])}, topic
                gids[topic] = atts[0][2]
            assert len(set(gids.values())) == len(gids)

            # robot r1's own search, asked on its namespace: ranked from the position of its last
            # mapped frame, its goal as a PoseStamped on /r1/goal_pose stamped with that frame's stamp
            from geometry_msgs.msg import PoseStamped
            from std_msgs.msg import String as Str

            from edge.sources import SourceConfig
            from synthetic_world import World

            sc = SourceConfig()
            last = World.generate(sc.seed, sc.preset).trajectory(sc.trajectory, 24, seed=sc.trajectory_seed)[-1]
            version = c.stats()["map_version"]
            s.put(f"0/r1/rayfronts/search/{STRING_KEY}/{h}", serialize_message(String(data="{targets: [car]}")))

            def final_status():
                got = r1.last("r1/rayfronts/search/status", 0)
                st = got and json.loads(deserialize_message(got[1], Str).data)
                return st if st and st["map_version"] == version else None

            st = wait_for(final_status, 60, what="r1's search of the final map")
            np.testing.assert_allclose(st["robot_xyz"], last[:3, 3], atol=1e-9)
            ref = c.search("car", threshold=0.5, max_instances=10, max_goals=5, z_band=(-0.5, 3.0),
                           from_xyz=st["robot_xyz"])
            g1 = deserialize_message(r1.last("r1/rayfronts/search/goals", 0)[1], PoseArray)
            assert len(g1.poses) == len(ref.look_next) > 0
            np.testing.assert_allclose([[p.position.x, p.position.y, p.position.z] for p in g1.poses],
                                       [g["position"] for g in ref.look_next], atol=1e-9)
            # the goal last sent (quiet since while the goal held): the first goal of the search
            # it came with (same stamp), within the gate's 0.5 m / 20 deg of the final first goal
            gp = deserialize_message(r1.last("r1/goal_pose", 0)[1], PoseStamped)
            assert gp.header.frame_id == "map"
            gxyz = np.array([gp.pose.position.x, gp.pose.position.y, gp.pose.position.z])
            gyaw = math.atan2(2 * gp.pose.orientation.z * gp.pose.orientation.w, 1 - 2 * gp.pose.orientation.z ** 2)
            stamp = gp.header.stamp.sec + gp.header.stamp.nanosec * 1e-9
            sts = [json.loads(deserialize_message(x[1], Str).data) for x in r1.of("r1/rayfronts/search/status")
                   if x[0].count("/") == 6]
            assert sts and len(r1.of("r1/goal_pose")) >= 1
            same = [x for x in sts if abs(x["stamp"] - stamp) < 1e-6 and x["goal"]["kind"] == "look"
                    and np.allclose(x["goal"]["position"], gxyz, atol=1e-9)]
            assert same and same[-1]["goal"]["yaw_rad"] == pytest.approx(gyaw, abs=1e-6)
            assert np.linalg.norm(gxyz - ref.look_next[0]["position"]) <= 0.5 + 1e-9
            turn = abs((gyaw - ref.look_next[0]["heading_rad"] + math.pi) % (2 * math.pi) - math.pi)
            assert turn <= math.radians(20) + 1e-9
            assert c.mapper_alive()
    finally:
        if s is not None:
            s.close()
        stop_all(procs, signal.SIGTERM, 30)
    assert procs[0].p.returncode == 0


def test_edge_ros2_source_reads_rclpy_messages():
    """Image (rgb8, 32FC1), CameraInfo and Odometry serialised by rclpy, on rmw_zenoh keys →
    frames with exactly those pixels, intrinsics and poses."""
    from builtin_interfaces.msg import Time
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CameraInfo, Image

    from edge.sources import SourceConfig, open_source

    port = free_tcp_port()
    pub_s = open_loopback_router(port)
    rng = np.random.default_rng(3)
    H, W, N, T0 = 6, 8, 3, 1000.0
    K = [5.0, 0.0, 4.0, 0.0, 6.0, 3.0, 0.0, 0.0, 1.0]
    truth = []
    for i in range(N):
        yaw = 0.3 * i
        q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        P = np.eye(4)
        P[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
        P[:3, 3] = [1.0 + i, 2.0, 0.5]
        truth.append(dict(t=T0 + 0.2 * i, rgb=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                          depth=rng.uniform(0.5, 5.0, (H, W)).astype(np.float32), q=q, pose=P))
    src = open_source(SourceConfig(kind="ros2", ros_connect=[f"tcp/127.0.0.1:{port}"], rgb_topic="/cam/color",
                                   depth_topic="/cam/depth", camera_info_topic="/cam/info", pose_topic="/odom",
                                   body_axes="RDF", ros_idle_timeout=2.0, ros_startup_timeout=30, ros_max_delay=0.3))
    frames: list = []
    th = threading.Thread(target=lambda: frames.extend(src), daemon=True)
    th.start()
    hashes = {t: cdr.type_hash(t, "jazzy") for t in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo",
                                                    "nav_msgs/msg/Odometry")}

    def put(topic, msgtype, msg):
        pub_s.put(f"0/{topic}/{_dds(msgtype)}/{hashes[msgtype]}", serialize_message(msg))

    def stamp(t):
        return Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))

    try:
        time.sleep(2.0)  # the source's subscriptions reach the router
        for f in truth:
            hdr = dict(stamp=stamp(f["t"]), frame_id="cam_optical_frame")
            info = CameraInfo(height=H, width=W, k=K, distortion_model="plumb_bob")
            info.header.stamp, info.header.frame_id = hdr["stamp"], hdr["frame_id"]
            put("cam/info", "sensor_msgs/msg/CameraInfo", info)
            for dt in (-0.01, 0.0, 0.01):
                od = Odometry(child_frame_id="cam_optical_frame")
                od.header.stamp, od.header.frame_id = stamp(f["t"] + dt), "map"
                p = od.pose.pose
                p.position.x, p.position.y, p.position.z = (float(v) for v in f["pose"][:3, 3])
                p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = f["q"]
                put("odom", "nav_msgs/msg/Odometry", od)
            d = Image(height=H, width=W, encoding="32FC1", is_bigendian=0, step=4 * W,
                      data=f["depth"].tobytes())
            d.header.stamp, d.header.frame_id = hdr["stamp"], hdr["frame_id"]
            put("cam/depth", "sensor_msgs/msg/Image", d)
            c = Image(height=H, width=W, encoding="rgb8", is_bigendian=0, step=3 * W, data=f["rgb"].tobytes())
            c.header.stamp, c.header.frame_id = hdr["stamp"], hdr["frame_id"]
            put("cam/color", "sensor_msgs/msg/Image", c)
            time.sleep(0.1)
        th.join(60)
        assert not th.is_alive()
    finally:
        pub_s.close()
    assert len(frames) == N, (len(frames), src.stats())
    for fr, f in zip(frames, truth, strict=True):
        assert fr.stamp == pytest.approx(f["t"], abs=1e-9)
        np.testing.assert_array_equal(fr.rgb, f["rgb"])
        np.testing.assert_array_equal(fr.depth, f["depth"])
        np.testing.assert_allclose(fr.intrinsics, np.reshape(K, (3, 3)))
        np.testing.assert_allclose(fr.pose, f["pose"], atol=1e-9)


def test_entity_gid_is_xxh3_128_of_the_token_key():
    """The published XXH3-128 test vector of the empty input (0x99aa06d3014798d8_6001c324468d497f),
    low half first, each half little endian; different token keys → different gids."""
    from common.ros2.keys import entity_gid, liveliness_token

    assert entity_gid("") == bytes.fromhex("7f498d4624c30160") + bytes.fromhex("d8984701d306aa99")
    toks = [liveliness_token(0, "abc", 0, i, "MP", "n", topic=f"/t{i}", msgtype="std_msgs/msg/String")
            for i in range(1, 4)]
    assert len({entity_gid(t) for t in toks}) == 3
    assert all(entity_gid(t) == _gid(t) for t in toks)
