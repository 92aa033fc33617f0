"""A query sees every frame mapped before it arrived (mapper.query_server, map_worker):
frames committed into the map's accumulation buffers become voxels at the next block or the
idle flush; a one-shot query asks the map worker to flush them first. Real mapper and edge
processes on loopback."""
from __future__ import annotations

import pytest

from common.zenoh_session import free_tcp_port
from tests.support.processes import Proc, wait_for
from tests.support.roles import client, edge_args, mapped, mapper_args

FRAMES = 5


@pytest.mark.timeout(180)
def test_query_right_after_frames_mapped_sees_their_voxels(tmp_path, procs, pca_file):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    # blocks every 100 frames and no idle flush for 10 min: without the query's flush the
    # FRAMES frames stay buffered (0 voxels) for the whole test
    procs.append(Proc("mapper", mapper_args(ep, ["queues.idle_flush_s=600", "map.vox_accum_period=100",
                                                 "map.ray_accum_period=100", "map.ray_accum_phase=0"]), tmp_path))
    with client(ep) as c:
        wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
        e = Proc("edge", edge_args(ep, pca_file, robot="r1", frames=FRAMES, rate=10.0), tmp_path)
        procs.append(e)
        assert e.p.wait(150) == 0
        wait_for(lambda: mapped(c) == FRAMES, 60, what=f"{FRAMES} frames mapped")
        before = c.stats(timeout=5.0)
        assert before["map"]["n_voxels"] == 0 and before["map"]["voxel_blocks"] == 0, before["map"]
        assert before["flushed_version"] != before["map_version"]          # buffered, not flushed
        r = c.query("car", top_k=5)
        assert r.frames_mapped == FRAMES
        assert len(r.voxel_xyz) == 5, r.timings
        assert r.timings.get("flush_pending", 0.0) == 0.0 and r.timings.get("flush_wait", -1.0) >= 0.0
        after = c.stats(timeout=5.0)
        assert after["map"]["n_voxels"] > 0 and after["flushed_version"] == after["map_version"]
        # nothing buffered now: the next query asks for no flush
        r2 = c.query("car", top_k=5)
        assert "flush_wait" not in r2.timings and len(r2.voxel_xyz) == 5
    assert procs[0].stop() == 0
