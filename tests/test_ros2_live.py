"""Live ROS 2 source (``source.kind=ros2``) against an independent publisher process.

``tests/ros2_replay.py`` (imports nothing of ours) replays a bag's raw CDR messages,
serialised by rosbags, on real Zenoh with rmw_zenoh keys (Humble and Jazzy type hashes)
or zenoh-bridge-ros2dds keys; the live source must build exactly the frames the bag
source builds from the same bag (poses, intrinsics, depth, RGB, stamps, indices), and the
faults of a live stream must be counted, never crash.
"""
from __future__ import annotations

import logging
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer

from apps.demo import zenoh_env
from common.zenoh_session import free_tcp_port
from edge.sources import SourceConfig, SourceError, open_source
from tests.support import rosbag_data as bagdata
from tests.support.processes import ROOT, cli_cmd, stop_process
from tests.support.rosbag_data import T0, TS, H, T, W


class Replay:
    """The publisher process (router mode on a free loopback port)."""

    def __init__(self, bag: Path, tmp: Path, layout="rmw_zenoh", distro="humble", wait_subs=4, speed=2.0,
                 linger=1.0, latch=()):
        self.ep = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.log = open(tmp / f"replay-{layout}-{distro}.log", "wb")
        self.p = subprocess.Popen([sys.executable, str(ROOT / "tests" / "ros2_replay.py"), str(bag), "--listen",
                                   self.ep, "--layout", layout, "--distro", distro, "--wait-subs", str(wait_subs),
                                   "--speed", str(speed), "--linger", str(linger),
                                   *[x for t in latch for x in ("--latch", t)]],
                                  stdout=subprocess.PIPE, stderr=self.log, env=zenoh_env(), cwd=str(ROOT))
        line = self.p.stdout.readline().decode()
        assert line.startswith("READY"), line

    def finish(self) -> int:
        out = self.p.stdout.read().decode()
        self.p.wait(30)
        self.log.close()
        assert self.p.returncode == 0
        return int(out.split("DONE")[1].split()[0])

    def kill(self):
        stop_process(self.p, signal.SIGKILL)


@pytest.fixture
def replays():
    started = []
    yield started
    for r in started:
        r.kill()


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    return bagdata.write_bag(tmp_path_factory.mktemp("bags") / "odom_bag")


BASE = dict(rgb_topic="/cam/color", depth_topic="/cam/depth", camera_info_topic="/cam/depth/info")


def live_frames(ep, layout="rmw_zenoh", **kw):
    cfg = SourceConfig(kind="ros2", ros_connect=[ep], ros_keys=layout, ros_idle_timeout=1.5,
                       ros_startup_timeout=30, ros_max_delay=0.3, **{**BASE, **kw})
    src = open_source(cfg)
    frames = list(src)
    return src, frames


def assert_same_frames(live, ref):
    assert [f.meta["index"] for f in live] == [f.meta["index"] for f in ref]
    for a, b in zip(live, ref, strict=True):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        assert a.meta["rgb_index"] == b.meta["rgb_index"]
        assert a.seq == b.seq and a.robot == b.robot


@pytest.mark.parametrize("layout,distro,pose", [
    ("rmw_zenoh", "humble", dict(pose_topic="/odom")),
    ("rmw_zenoh", "jazzy", dict(world_frame="map", camera_frame="camera_optical_frame")),
    ("bridge", "humble", dict(pose_topic="/odom", camera_frame="camera_optical_frame")),
])
def test_live_frames_equal_bag_frames(bag, tmp_path, replays, layout, distro, pose):
    n_subs = 3 + (2 if "world_frame" in pose or "camera_frame" in pose else 0) + ("pose_topic" in pose)
    ref_src = open_source(SourceConfig(kind="rosbag", path=str(bag), **BASE, **pose))
    ref = list(ref_src)
    assert len(ref) == 4  # the bag test's frames 0, 1, 2, 5
    r = Replay(bag, tmp_path, layout, distro, wait_subs=n_subs)
    replays.append(r)
    src, frames = live_frames(r.ep, layout, **pose)
    r.finish()
    assert_same_frames(frames, ref)
    # the same three frames are skipped for the same reasons as in the bag
    assert dict(src.skipped) == dict(ref_src.skipped), src.stats()
    st = src.stats()
    assert st["frames"] == 4
    assert st["topics"]["/cam/depth"]["received"] == 7 and st["topics"]["/cam/depth"]["type"] == "sensor_msgs/msg/Image"
    assert all(t.get("bad", 0) == 0 and t.get("out_of_order", 0) == 0 for t in st["topics"].values())
    # and the hand-written poses of the bag test hold for the live frames too
    off = np.array([0.0, -0.1, 0.2]) if "camera_frame" in pose else np.zeros(3)
    for f in frames:
        np.testing.assert_allclose(f.pose, bagdata.expected_rdf(f.stamp, off), atol=1e-6)


def test_latched_tf_static_and_camera_info_reach_a_late_edge(bag, tmp_path, replays):
    """/tf_static and CameraInfo published once from a cache before the edge subscribes (as
    robot_state_publisher does, transient local): the edge still gets them and builds the bag's frames."""
    pose = dict(world_frame="map", camera_frame="camera_optical_frame")
    ref = list(open_source(SourceConfig(kind="rosbag", path=str(bag), **BASE, **pose)))
    r = Replay(bag, tmp_path, "rmw_zenoh", "jazzy", wait_subs=3, latch=("/tf_static", "/cam/depth/info"))
    replays.append(r)
    time.sleep(1.0)  # the latched messages are out before anyone listens
    src, frames = live_frames(r.ep, "rmw_zenoh", **pose)
    r.finish()
    assert_same_frames(frames, ref)
    assert src.stats()["topics"]["/tf_static"]["decoded"] >= 1


def test_list_topics_from_graph_tokens_and_keys(bag, tmp_path, replays):
    from edge.sources.ros2 import format_topics, list_topics

    r = Replay(bag, tmp_path, "rmw_zenoh", "jazzy", wait_subs=1, speed=1.0)
    replays.append(r)
    rows = list_topics(SourceConfig(kind="ros2", ros_connect=[r.ep]), seconds=2.0)
    by = {row["topic"]: row for row in rows}
    assert set(by) == {"/cam/color", "/cam/depth", "/cam/depth/info", "/odom", "/tf", "/tf_static"}
    assert by["/cam/color"]["type"] == "sensor_msgs/msg/Image"
    assert by["/odom"]["type"] == "nav_msgs/msg/Odometry"
    assert all("graph" in row["via"] and row["publishers"] == 1 for row in rows)
    assert any("data" in row["via"] for row in rows)  # the subscriber matched: samples flowed
    table = format_topics(rows)
    assert "/cam/depth" in table and "nav_msgs/msg/Odometry" in table
    r.finish()


# ---------------------------------------------------------------------- faults


def _img(t, arr, enc):
    return bagdata.image(t, "camera_optical_frame", arr, enc)


def write_fault_bag(path: Path) -> Path:
    """Depth/colour/pose at 10 Hz for 4 s with, by design:
    * depth 5 has encoding 'yuv422' (unsupported) → counted, the stream goes on;
    * colour 12 has a stamp 0.5 s in the past (out of order) → dropped and counted;
    * frames 20..29 are a burst: 10 depth messages at the same bag time;
    * the colour topic stops after 3.0 s (depth 30.. have no colour);
    * the pose stops at 2.6 s → depth 27.. cannot have a pose: counted."""
    with Writer(path, version=9) as w:
        c_rgb = w.add_connection("/cam/color", "sensor_msgs/msg/Image", typestore=TS)
        c_d = w.add_connection("/cam/depth", "sensor_msgs/msg/Image", typestore=TS)
        c_pose = w.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=TS)
        msgs = []
        for k in range(40):
            t = T0 + 0.1 * k
            bag_t = T0 + 2.0 if 20 <= k < 30 else t
            d = bagdata.depth_values(k % 5)
            if k == 5:
                msgs.append((bag_t, c_d, "sensor_msgs/msg/Image", _img(t, np.zeros((H, W, 2), np.uint8), "yuv422")))
            else:
                msgs.append((bag_t, c_d, "sensor_msgs/msg/Image", _img(t, d, "32FC1")))
            if t < T0 + 3.0:
                tr = t - 0.5 if k == 12 else t + 0.01
                msgs.append((bag_t + 0.001, c_rgb, "sensor_msgs/msg/Image",
                             _img(tr, bagdata.rgb_values(k % 5), "rgb8")))
            if t <= T0 + 2.6:
                msgs.append((bag_t + 0.002, c_pose, "geometry_msgs/msg/PoseStamped", T["geometry_msgs/msg/PoseStamped"](
                    header=bagdata.header(t, "map"), pose=bagdata.pose((0.1 * k, 0, 1), (0, 0, 0, 1)))))
        msgs.sort(key=lambda m: m[0])
        for t, conn, typ, msg in msgs:
            w.write(conn, int(t * 1e9), TS.serialize_cdr(msg, typ))
    return path


def test_live_faults_counted_nothing_crashes(tmp_path, replays, caplog):
    bag = write_fault_bag(tmp_path / "faults")
    r = Replay(bag, tmp_path, "rmw_zenoh", "humble", wait_subs=3, speed=1.0)
    replays.append(r)
    caplog.set_level(logging.WARNING, logger="edge.sources.ros2")
    cfg = SourceConfig(kind="ros2", ros_connect=[r.ep], rgb_topic="/cam/color", depth_topic="/cam/depth",
                       pose_topic="/pose", body_axes="RDF", intrinsics=[10.0, 10.0, 4.0, 3.0], ros_queue=4,
                       ros_idle_timeout=2.5, ros_startup_timeout=30, ros_max_delay=0.3, ros_log_every=60)
    src = open_source(cfg)
    frames = list(src)
    assert r.finish() > 0
    st = src.stats()
    depth, rgb = st["topics"]["/cam/depth"], st["topics"]["/cam/color"]
    assert depth["bad"] == 1                                     # the yuv422 image
    assert rgb["out_of_order"] == 1                               # colour 12
    assert depth["dropped_full"] > 0                              # the burst overflowed the 4-slot buffer
    assert rgb["stalls"] == 1                                     # colour stopped at 3 s while depth went on
    assert st["skipped"].get("no colour image within sync_tolerance", 0) > 0
    assert st["skipped"].get("no pose at the depth stamp", 0) > 0
    kept = [f.meta["index"] for f in frames]
    assert 5 not in kept and kept == sorted(kept) and len(kept) >= 15
    assert all(i < 27 for i in kept)                              # no pose after 2.6 s
    for f in frames:                                              # what was kept is right
        np.testing.assert_allclose(f.pose[:3, 3], [0.1 * f.meta["index"], 0, 1], atol=1e-6)
    text = caplog.text
    assert "/cam/depth" in text and "yuv422" in text             # one line naming the topic
    assert "/cam/color" in text and "older than the newest" in text
    assert "no message for" in text
    assert text.count("unsupported depth encoding") == 1         # rate-limited


def test_missing_tf_counted_and_startup_lists_topics(bag, tmp_path, replays, caplog):
    """camera_frame that no tf reaches: every frame skipped as 'no tf chain', the start-up
    timeout's error lists what was seen; nothing crashes."""
    r = Replay(bag, tmp_path, "rmw_zenoh", "humble", wait_subs=5, speed=2.0)
    replays.append(r)
    caplog.set_level(logging.WARNING, logger="edge.sources.ros2")
    cfg = SourceConfig(kind="ros2", ros_connect=[r.ep], world_frame="map", camera_frame="lidar_link",
                       ros_startup_timeout=4.0, ros_max_delay=0.2, ros_log_every=1.0, **BASE)
    src = open_source(cfg)
    with pytest.raises(SourceError, match=r"(?s)no frame matched.*seen: .*/cam/depth \[sensor_msgs/msg/Image\]"):
        list(src)
    r.finish()
    assert src.skipped["no tf chain to camera_frame"] >= 4
    assert "lidar_link" in caplog.text and "waiting for the first matched frame" in caplog.text


def test_stop_event_ends_a_silent_stream(tmp_path):
    """Nobody publishes: the iterator waits (start-up) and returns promptly once stop is set."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["{ep}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(conf)
    try:
        stop = threading.Event()
        src = open_source(SourceConfig(kind="ros2", ros_connect=[ep], pose_topic="/odom", **BASE), stop=stop)
        threading.Timer(1.0, stop.set).start()
        assert list(src) == []
        assert src.stats()["frames"] == 0
    finally:
        s.close()


def test_config_errors():
    with pytest.raises(SourceError, match="rgb_topic"):
        open_source(SourceConfig(kind="ros2", pose_topic="/odom"))
    with pytest.raises(SourceError, match="no pose source"):
        open_source(SourceConfig(kind="ros2", **BASE))
    with pytest.raises(SourceError, match="not a usable ROS topic"):
        open_source(SourceConfig(kind="ros2", rgb_topic="/a/*", depth_topic="/d", pose_topic="/p"))
    with pytest.raises(SourceError, match="domain"):
        open_source(SourceConfig(kind="ros2", ros_domain=999, pose_topic="/p", **BASE))


def test_cli_list_topics_bridge_and_config_error(bag, tmp_path, replays):
    """`rayfronts edge --list-topics` on bridge keys (no graph tokens: the data keys seen), and a
    ros2 edge without topics fails with one error line."""
    r = Replay(bag, tmp_path, "bridge", "humble", wait_subs=1, speed=1.0)
    replays.append(r)
    out = subprocess.run(cli_cmd("edge", "--list-topics", f"source.ros_connect=[{r.ep}]",
                          "source.ros_keys=bridge", "--list-seconds", "3"), capture_output=True, text=True,
                         env=zenoh_env(), cwd=str(ROOT), timeout=90)
    assert out.returncode == 0, out.stderr[-2000:]
    for topic in ("/cam/color", "/cam/depth", "/odom", "/tf_static"):
        assert topic in out.stdout
    assert "data" in out.stdout and "Hz" in out.stdout
    r.finish()
    bad = subprocess.run(cli_cmd("edge", "source.kind=ros2", "source.pose_topic=/odom",
                          "--connect", "tcp/127.0.0.1:1"), capture_output=True, text=True, env=zenoh_env(),
                         cwd=str(ROOT), timeout=90)
    assert bad.returncode != 0
    assert "rgb_topic" in bad.stderr and "Traceback" not in bad.stderr
