"""`rayfronts edge source.kind=ros2` end to end: a robot's ROS 2 topics (rendered from the
synthetic world, serialised by rosbags, replayed by the independent ``tests/ros2_replay.py``
process on rmw_zenoh and on bridge keys) → the edge process (tiny random-weight NARADIO, no labels
needed) → the mapper process. The frames the edge sent and the mapper's map must equal
those built in-process from the bag source reading the same bag."""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer

from apps.demo import zenoh_env
from common.zenoh_session import ZenohConfig, free_tcp_port
from edge.sources import SourceConfig, open_source
from edge.sources.transforms import matrix_to_quat
from tests.support import rosbag_data as bagdata
from tests.support.processes import start_cli, stop_all, wait_for

ROOT = Path(__file__).resolve().parents[1]
TS, T = bagdata.TS, bagdata.T
T0 = 1_750_000_000.0
N = 10
FAST_MAP = ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0", "rerun.file=",
            "snapshots.on_exit=false", "queues.idle_flush_s=30", "layers.max_voxels=100000000"]
TOPICS = ["source.rgb_topic=/camera/color/image_raw", "source.depth_topic=/camera/depth/image_rect_raw",
          "source.camera_info_topic=/camera/depth/camera_info", "source.pose_topic=/camera/pose",
          "source.body_axes=RDF"]


def _image(t, arr, enc):
    return bagdata.image(t, "camera_color_optical_frame", arr, enc)


@pytest.fixture(scope="module")
def world_bag(tmp_path_factory) -> Path:
    """Ten 48×64 frames of the synthetic world as ROS 2 messages (RDF optical-frame poses)."""
    src = open_source(SourceConfig(kind="synthetic", resolution="48x64", n_frames=N, depth_limit=15.0))
    path = tmp_path_factory.mktemp("ros") / "world_bag"
    with Writer(path, version=9) as w:
        c_rgb = w.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=TS)
        c_d = w.add_connection("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", typestore=TS)
        c_i = w.add_connection("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=TS)
        c_p = w.add_connection("/camera/pose", "geometry_msgs/msg/PoseStamped", typestore=TS)
        for k, f in enumerate(src):
            t = T0 + 0.1 * k
            q = matrix_to_quat(f.pose[:3, :3])
            p = f.pose[:3, 3]
            pose = T["geometry_msgs/msg/PoseStamped"](header=bagdata.header(t, "map"), pose=bagdata.pose(p, q))
            if k == 0:
                info = bagdata.camera_info(t, "camera_depth_optical_frame", f.intrinsics, 48, 64)
                w.write(c_i, int((t - 0.05) * 1e9), TS.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            ns = int(t * 1e9)
            w.write(c_p, ns, TS.serialize_cdr(pose, "geometry_msgs/msg/PoseStamped"))
            w.write(c_d, ns + 1000, TS.serialize_cdr(_image(t, f.depth.astype(np.float32), "32FC1"),
                                                     "sensor_msgs/msg/Image"))
            w.write(c_rgb, ns + 2000, TS.serialize_cdr(_image(t + 0.004, f.rgb[..., ::-1], "bgr8"),
                                                       "sensor_msgs/msg/Image"))
    return path


@pytest.fixture(scope="module")
def radio(tmp_path_factory):
    from encoders.radio import RadioConfig, save_flat
    from encoders.random_init import random_checkpoint

    rc = RadioConfig(embed_dim=32, depth=1, num_heads=2, pos_grid=8, mlp_hidden=64)
    return str(save_flat(random_checkpoint(rc, head_hidden=32, head_out=16),
                         tmp_path_factory.mktemp("radio") / "radio.safetensors"))


def _run(args, log):
    return start_cli(args, log, env=zenoh_env())


@pytest.mark.slow
@pytest.mark.timeout(240)
@pytest.mark.parametrize("layout", ["rmw_zenoh", "bridge"])
def test_edge_ros2_to_mapper_equals_bag(tmp_path, world_bag, radio, layout):
    import torch

    from common.feature_space import FeatureSpace
    from common.recording import RecordingReader
    from common.wire import decode_frame, encode_frame
    from edge.encoding import compress_features
    from encoders import EncoderConfig, make_encoder
    from mapper.service_config import load_mapper_config
    from mapper.service_map import create_map, flush, integrate, layer_arrays
    from query_client import Client

    ep_m = f"tcp/127.0.0.1:{free_tcp_port()}"
    ep_r = f"tcp/127.0.0.1:{free_tcp_port()}"
    rec = tmp_path / "rec"
    enc_args = ["encoder.kind=naradio", "encoder.model=auto", f"encoder.checkpoint={radio}", "pca.out_dim=0"]
    logs = [open(tmp_path / n, "wb") for n in ("mapper.log", "edge.log", "replay.log")]
    procs = []
    try:
        procs.append(_run(["mapper", "--mode", "router", "--listen", ep_m, *FAST_MAP], logs[0]))
        with Client(ZenohConfig(connect=[ep_m], connect_timeout_ms=60_000), timeout=20.0) as c:
            wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
            procs.append(_run(["edge", "--connect", ep_m, "--rate", "4", "--record", str(rec), "robot=r1", "threads=1",
                               "source.kind=ros2", f"source.ros_connect=[{ep_r}]", "source.ros_idle_timeout=3",
                               f"source.ros_keys={layout}", "publish.linger_s=8",
                               *TOPICS, *enc_args], logs[1]))
            wait_for(lambda: "r1" in c.robots(), 60, what="edge r1 alive")
            procs.append(subprocess.Popen([sys.executable, str(ROOT / "tests" / "ros2_replay.py"), str(world_bag),
                                           "--listen", ep_r, "--layout", layout, "--distro", "jazzy",
                                           "--wait-subs", "4", "--speed", "1"],
                                          stdout=logs[2], stderr=subprocess.STDOUT, env=zenoh_env(), cwd=str(ROOT)))
            assert procs[2].wait(90) == 0
            assert procs[1].wait(90) == 0, (tmp_path / "edge.log").read_text()[-3000:]
            st = c.wait_settled(mapped=N, timeout=90)
            assert st["frames"]["mapped"] == N, st["frames"]
            vox_remote, _ = c.layer("voxels")
            n_rays = st["map"]["n_rays"]
    finally:
        stop_all(procs, signal.SIGTERM, 20)
        for f in logs:
            f.close()

    # The bag source's frames of the same bag, encoded in-process like the edge does.
    ref_src = open_source(SourceConfig(kind="rosbag", path=str(world_bag), rgb_topic="/camera/color/image_raw",
                                       depth_topic="/camera/depth/image_rect_raw",
                                       camera_info_topic="/camera/depth/camera_info", pose_topic="/camera/pose",
                                       body_axes="RDF", robot="r1"))
    ref = list(ref_src)
    assert len(ref) == N
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        enc = make_encoder(EncoderConfig(kind="naradio", model="auto", checkpoint=radio))
        with torch.inference_mode():
            feats = [compress_features(None, enc.encode_with_global(f.rgb)[0]) for f in ref]
    finally:
        torch.set_num_threads(prev)
    fs = FeatureSpace.for_encoder(enc, None)
    reader = RecordingReader(rec)
    sent = [decode_frame(reader.read_bytes(i)) for i in range(len(reader))]
    assert len(sent) == N
    from common.config import load_config
    from edge.config import EdgeConfig

    pub = load_config(EdgeConfig, None, []).publish  # the edge's wire settings (defaults)
    local = []
    for f, x, s in zip(ref, feats, sent, strict=True):
        g = decode_frame(encode_frame(type(f)(**{**f.__dict__, "features": x, "feature_space": fs.id, "meta": {}}),
                                      feature_codec=pub.feature_codec, jpeg_quality=pub.jpeg_quality))
        assert s.stamp == g.stamp
        np.testing.assert_array_equal(s.pose, g.pose)
        np.testing.assert_array_equal(s.intrinsics, g.intrinsics)
        np.testing.assert_array_equal(s.depth, g.depth)
        np.testing.assert_array_equal(s.rgb, g.rgb)
        np.testing.assert_array_equal(s.features, g.features)
        local.append(g)
    cfg = load_mapper_config(None, FAST_MAP)
    m = create_map(cfg, fs)
    for g in local:
        integrate(m, g)
    flush(m)
    big = type(cfg.layers)(max_voxels=10 ** 9, max_rays=10 ** 9)
    vox_local, _ = layer_arrays(m, "voxels", big)
    rays_local, _ = layer_arrays(m, "rays", big)
    assert len(vox_local["xyz"]) > 50
    assert st["map"]["n_voxels"] == len(vox_local["xyz"]) == len(vox_remote["xyz"])
    assert n_rays == len(rays_local["origin"])
    o_r, o_l = np.lexsort(vox_remote["xyz"].T), np.lexsort(vox_local["xyz"].T)
    np.testing.assert_array_equal(vox_remote["xyz"][o_r], vox_local["xyz"][o_l])
    np.testing.assert_array_equal(vox_remote["rgb"][o_r], vox_local["rgb"][o_l])
