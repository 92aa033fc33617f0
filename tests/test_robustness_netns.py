"""Edge, mapper and client in three network namespaces, shared memory off (needs root and
``ip netns``; skipped otherwise). Topology as on a robot site: the edge (zA) and the operator
laptop (zC) each reach only the base station (zB), which runs the mapper as the router."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import uuid

import pytest

from tests.support.netns import network_namespaces
from tests.support.processes import ROOT, Proc, cli_cmd, proc_env, stop_all


@pytest.fixture
def netns():
    tag = uuid.uuid4().hex[:6]
    a, b, c = f"rfA{tag}", f"rfB{tag}", f"rfC{tag}"
    va, vb, vc, vb2 = f"va{tag}", f"vb{tag}", f"vc{tag}", f"vd{tag}"
    with network_namespaces([a, b, c], [(a, b, va, vb, "10.77.0.1/24", "10.77.0.2/24"),
                                        (c, b, vc, vb2, "10.78.0.3/24", "10.78.0.2/24")]):
        yield a, b, c


CLIENT = textwrap.dedent("""
    import json, sys
    from common.zenoh_session import ZenohConfig
    from query_client import Client
    ep, n = sys.argv[1], int(sys.argv[2])
    with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60000, shared_memory=False), timeout=20) as c:
        st = c.wait_settled(mapped=n, timeout=150)
        robots = c.robots()
        r = c.query("car", top_k=3)
        print(json.dumps({"mapped": st["frames"]["mapped"], "robots": robots, "voxels": len(r.voxel_xyz),
                          "rejected": st["frames"]["rejected_total"]}))
""")


@pytest.mark.netns
@pytest.mark.timeout(300)
def test_three_namespaces_no_shm(netns, tmp_path):
    a, b, c = netns
    env = proc_env()   # + the session's text cache: class names embedded once per session
    pca = tmp_path / "pca.npz"
    r = subprocess.run(cli_cmd("edge", "fit-pca", "--out", str(pca), "--frames", "3", "source.resolution=96x128",
                               "source.n_frames=20", "pca.out_dim=16"),
                       env=env, cwd=str(ROOT), capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr.decode()[-1500:]
    shm = ["--zenoh-set", "transport/shared_memory/enabled=false"]

    def spawn(ns, name, args):
        return Proc(name, args, tmp_path, env=env, prefix=("ip", "netns", "exec", ns))

    mapper = spawn(b, "mapper", ["mapper", "--mode", "router", "--listen", "tcp/0.0.0.0:7447", *shm,
                                 "preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0"])
    edge = spawn(a, "edge", ["edge", "--connect", "tcp/10.77.0.2:7447", *shm, "--rate", "4", "robot=r1",
                             "source.resolution=96x128", "source.n_frames=16", "source.depth_limit=20",
                             f"pca.basis={pca}", "pca.out_dim=16", "publish.linger_s=30"])
    try:
        out = subprocess.run(["ip", "netns", "exec", c, sys.executable, "-c", CLIENT, "tcp/10.78.0.2:7447", "12"],
                             env=env, cwd=str(ROOT), capture_output=True, text=True, timeout=240)
        assert out.returncode == 0, out.stderr[-2000:]
        res = json.loads(out.stdout.strip().splitlines()[-1])
        assert res["mapped"] >= 12 and res["voxels"] > 0 and res["rejected"] == 0
        assert res["robots"] == ["r1"]   # the laptop sees the edge's liveliness through the router
    finally:
        stop_all((edge, mapper), signal.SIGINT, 30)
    assert mapper.p.returncode == 0 and edge.p.returncode == 0
