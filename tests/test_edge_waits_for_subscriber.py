"""An edge started before its mapper holds its first frame until a subscriber matches the
frames key (``publish.wait_subscriber_s``), so a replay (``publish.lossless``) loses nothing to
a route still forming (a live camera keeps only its newest frame meanwhile); with no subscriber
it sends anyway once the wait is over. Real processes over a real Zenoh router."""
import signal
import time
from contextlib import contextmanager
from typing import Iterator

import pytest

from common.zenoh_session import ZenohConfig, free_tcp_port
from tests.support.processes import Proc, proc_env, stop_all, wait_for, wait_log

EDGE = ["--rate", "0", "source.kind=synthetic", "source.n_frames=6", "source.resolution=60x80",
        "source.depth_limit=20", "encoder.kind=label", "pca.out_dim=16", "pca.fit_frames=2", "publish.linger_s=1"]


def _log(p: Proc, tmp_path) -> str:
    return (tmp_path / f"{p.name}.log").read_text(errors="replace")


@contextmanager
def _router_and_edge(tmp_path, *edge_items: str) -> Iterator[tuple[str, dict, list[Proc], Proc]]:
    """A router on a free loopback port and an edge (``EDGE`` + ``edge_items``) connected to it;
    yields ``(endpoint, env, processes, edge)``; every process in ``processes`` (the caller may
    add some) is stopped, last started first."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = proc_env()
    procs: list[Proc] = []
    try:
        router = Proc("router", ["router", "--listen", ep], tmp_path, env=env)
        procs.append(router)
        wait_log(router.p, tmp_path / "router.log", "listening on", 60)
        edge = Proc("edge", ["edge", "--connect", ep, *edge_items, *EDGE], tmp_path, env=env)
        procs.append(edge)
        yield ep, env, procs, edge
    finally:
        stop_all(reversed(procs), signal.SIGTERM, 30)


@pytest.mark.timeout(300)
def test_edge_started_before_the_mapper_loses_no_frame(tmp_path):
    from query_client import Client

    # a replay (lossless): no frame replaced while the first one is held
    with _router_and_edge(tmp_path, "robot=early", "publish.wait_subscriber_s=120",
                          "publish.lossless=true") as (ep, env, procs, edge):
        wait_log(edge.p, tmp_path / "edge.log", "connected", 120)
        time.sleep(3.0)                       # the edge's first frame is ready long before a mapper exists
        assert edge.p.poll() is None, _log(edge, tmp_path)[-2000:]
        procs.append(Proc("mapper", ["mapper", "--mode", "client", "--connect", ep, "map.vox_size=0.5",
                                     "map.depth_limit=20", "layers.rate_hz=0", "snapshots.on_exit=false"],
                          tmp_path, env=env))
        assert edge.p.wait(180) == 0, _log(edge, tmp_path)[-3000:]
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=30.0) as c:
            st = wait_for(lambda: (lambda s: s if s["frames"]["received"] >= 6 else None)(c.stats(timeout=5.0)),
                          60, what="the mapper's frames")
        assert st["frames"]["received"] == 6, st["frames"]
        log = _log(edge, tmp_path)
        assert "sending anyway" not in log and "'frames_sent': 6" in log, log[-2000:]


@pytest.mark.timeout(180)
def test_edge_without_a_subscriber_sends_anyway_after_the_wait(tmp_path):
    with _router_and_edge(tmp_path, "robot=alone", "publish.wait_subscriber_s=1") as (_, _, _, edge):
        assert edge.p.wait(120) == 0, _log(edge, tmp_path)[-3000:]
        log = _log(edge, tmp_path)
        assert log.count("sending anyway") == 1, log[-3000:]     # asked once per session, not per frame
