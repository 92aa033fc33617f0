"""The mapper's ROS 2 output (``ros.enabled=true``) read by an outside decoder: a real mapper
process maps a synthetic-world edge; the test subscribes with a plain Zenoh session on the
rmw_zenoh keys, decodes with rosbags' (Jazzy) typestore and checks the points against the
map's own layers (via the query client), the rmw_zenoh graph tokens `ros2 topic list`
reads, and a standing query sent as a std_msgs/String."""
from __future__ import annotations

import signal
import time

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from common.zenoh_session import ZenohConfig, free_tcp_port
from tests.support.processes import proc_env, start_cli, stop_all, wait_for
from tests.support.roles import SampleLog, zenoh_client_config

JAZZY = get_typestore(Stores.ROS2_JAZZY)
MAP = ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0", "rerun.file=",
       "snapshots.on_exit=false", "layers.max_voxels=100000000", "layers.max_rays=100000000",
       "ros.enabled=true", "ros.rate_hz=2", "ros.frame_id=odom", "ros.max_rays=100000000", "queues.idle_flush_s=0.5",
       "queues.per_robot=1000"]


def _dds(t):
    pkg, sub, name = t.split("/")
    return f"{pkg}::{sub}::dds_::{name}_"


def _cloud(msg) -> dict[str, np.ndarray]:
    """PointCloud2 → {field: (N,) float32} read through the message's own field table."""
    assert msg.height == 1 and not msg.is_bigendian and msg.row_step == msg.point_step * msg.width
    raw = np.asarray(msg.data, np.uint8).reshape(msg.width, msg.point_step)
    out = {}
    for f in msg.fields:
        assert f.datatype == 7 and f.count == 1  # FLOAT32
        out[f.name] = raw[:, f.offset:f.offset + 4].copy().view("<f4").reshape(-1)
    return out


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_mapper_ros_output_decodes_and_equals_layers(tmp_path):
    from query_client import Client

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    logs = [open(tmp_path / n, "wb") for n in ("mapper.log", "edge.log")]
    env = proc_env()   # + the session's text cache: class names embedded once per session
    procs = [start_cli(["mapper", "--mode", "router", "--listen", ep, *MAP], logs[0], env=env)]
    s = None
    try:
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=20.0) as c:
            wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
            s = zenoh.open(zenoh_client_config(ep))
            subs = {n: SampleLog(s, f"0/rayfronts/{n}/*/*") for n in ("voxels", "frontiers", "rays")}
            qsub = SampleLog(s, "0/rayfronts/query/ros_vehicle/*/*")
            procs.append(start_cli(
                ["edge", "--connect", ep, "--rate", "0", "robot=r1", "source.resolution=96x128", "source.n_frames=12",
                 "source.depth_limit=20", "pca.out_dim=16", "pca.fit_frames=4", "publish.linger_s=8",
                 "publish.lossless=true"],      # exactly 12 mapped: no frame replaced at the edge
                logs[1], env=env))
            assert procs[1].wait(120) == 0
            st = c.wait_settled(mapped=12, timeout=60)
            assert st["frames"]["mapped"] == 12, st["frames"]
            vox_l, _ = c.layer("voxels")
            fr_l, _ = c.layer("frontiers")
            rays_l, _ = c.layer("rays")
            n_vox = st["map"]["n_voxels"]
            assert len(vox_l["xyz"]) == n_vox > 100

            def final(name, n):
                last = subs[name].latest()
                if last is None:
                    return None
                msg = JAZZY.deserialize_cdr(last[1], "sensor_msgs/msg/PointCloud2")
                return last if msg.width == n else None

            try:
                key, raw, att = wait_for(lambda: final("voxels", n_vox), 60, what="the final voxel cloud")
            except AssertionError as e:
                widths = [JAZZY.deserialize_cdr(r, "sensor_msgs/msg/PointCloud2").width
                          for _, r, _ in subs["voxels"].samples]
                raise AssertionError(f"{e}; voxel clouds seen: {widths}, map has {n_vox}; stats {c.stats()['map']}"
                                     ) from None
            # rmw_zenoh key with Jazzy's type hash, computed here by rosbags
            assert key == f"0/rayfronts/voxels/{_dds('sensor_msgs/msg/PointCloud2')}/" \
                          f"{JAZZY.hash_rihs01('sensor_msgs/msg/PointCloud2')}"
            assert att is not None and len(att) == 33 and att[16] == 16  # int64 seq, int64 time, 16-byte gid
            msg = JAZZY.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")
            assert msg.header.frame_id == "odom"
            assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb"]
            cl = _cloud(msg)
            xyz = np.stack([cl["x"], cl["y"], cl["z"]], 1)
            rgb_u = cl["rgb"].view("<u4")
            rgb = np.stack([(rgb_u >> 16) & 255, (rgb_u >> 8) & 255, rgb_u & 255], 1).astype(np.uint8)
            o_r, o_l = np.lexsort(xyz.T), np.lexsort(vox_l["xyz"].T)
            np.testing.assert_array_equal(xyz[o_r], vox_l["xyz"][o_l])
            np.testing.assert_array_equal(rgb[o_r], vox_l["rgb"][o_l])

            fkey, fraw, _ = wait_for(lambda: final("frontiers", len(fr_l["xyz"])), 30, what="the frontier cloud")
            fc = _cloud(JAZZY.deserialize_cdr(fraw, "sensor_msgs/msg/PointCloud2"))
            fxyz = np.stack([fc["x"], fc["y"], fc["z"]], 1)
            np.testing.assert_array_equal(fxyz[np.lexsort(fxyz.T)], fr_l["xyz"][np.lexsort(fr_l["xyz"].T)])

            rkey, rraw, _ = subs["rays"].latest()
            assert rkey.startswith(f"0/rayfronts/rays/{_dds('visualization_msgs/msg/MarkerArray')}/RIHS01_")
            ma = JAZZY.deserialize_cdr(rraw, "visualization_msgs/msg/MarkerArray")
            assert ma.markers[0].action == 3  # DELETEALL
            arrows = ma.markers[1:]
            assert len(arrows) == len(rays_l["origin"]) > 0
            o = np.array([[m.points[0].x, m.points[0].y, m.points[0].z] for m in arrows])
            tip = np.array([[m.points[1].x, m.points[1].y, m.points[1].z] for m in arrows])
            assert all(m.type == 0 and m.action == 0 and m.header.frame_id == "odom" for m in arrows)
            np.testing.assert_allclose(o, rays_l["origin"], atol=1e-6)
            np.testing.assert_allclose((tip - o) / 2.0, rays_l["direction"], atol=1e-5)  # ros.ray_length = 2
            col = np.array([[m.color.r, m.color.g, m.color.b, m.color.a] for m in arrows])
            assert np.all((col >= 0) & (col <= 1)) and np.all(col[:, 3] == 1)
            assert np.isclose(col[:, 0].max(), 1.0)  # the heaviest ray is red

            # the graph as `ros2 topic list` sees it: rmw_zenoh liveliness tokens
            toks = [str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/0/**", timeout=3.0) if r.ok is not None]
            pubs = {t.split("/")[9]: t.split("/")[10:12] for t in toks if t.split("/")[5] == "MP"}
            assert pubs["%rayfronts%voxels"] == [_dds("sensor_msgs/msg/PointCloud2"),
                                                 JAZZY.hash_rihs01("sensor_msgs/msg/PointCloud2")]
            assert pubs["%rayfronts%rays"][0] == _dds("visualization_msgs/msg/MarkerArray")
            assert "%rayfronts%frontiers" in pubs
            assert any(t.split("/")[5] == "MS" and t.split("/")[9] == "%rayfronts%query_text" for t in toks)
            assert any(t.split("/")[5] == "NN" and t.endswith("/rayfronts_mapper") for t in toks)

            # a standing query from ROS: std_msgs/String serialised by rosbags
            T = JAZZY.types
            h = JAZZY.hash_rihs01("std_msgs/msg/String")
            s.put(f"0/rayfronts/query_text/{_dds('std_msgs/msg/String')}/{h}",
                  bytes(JAZZY.serialize_cdr(T["std_msgs/msg/String"](data="vehicle"), "std_msgs/msg/String")))
            qkey, qraw, _ = wait_for(lambda: qsub.latest(), 30, what="the standing query cloud")
            qc = _cloud(JAZZY.deserialize_cdr(qraw, "sensor_msgs/msg/PointCloud2"))
            assert set(qc) == {"x", "y", "z", "score"} and len(qc["score"]) > 0
            ref = c.query("vehicle", top_k=1000)
            np.testing.assert_array_equal(np.stack([qc["x"], qc["y"], qc["z"]], 1), ref.voxel_xyz)
            np.testing.assert_allclose(qc["score"], ref.voxel_score, rtol=1e-6)
            assert "ros_vehicle" in c.stats()["standing_queries"]
            # a payload that is not a String is rejected, the mapper keeps serving
            s.put(f"0/rayfronts/query_text/{_dds('std_msgs/msg/String')}/{h}", b"\x00\x01\x00\x00\xff")
            time.sleep(0.5)
            assert c.mapper_alive()
    finally:
        if s is not None:
            s.close()
        stop_all(procs, signal.SIGTERM, 30)
        for f in logs:
            f.close()
    assert procs[0].returncode == 0, (tmp_path / "mapper.log").read_text()[-3000:]
