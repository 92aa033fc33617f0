"""`rayfronts router` and client sessions over real Zenoh, in separate processes.

Loopback only (unique free ports on 127.0.0.1), multicast off, shared memory off, every
wait bounded, every process closed. Helpers: tests/support/zenoh_agent.py.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import zenoh  # noqa: F401,E402  (core dependency: a missing one fails)

from common.keys import KeySpace  # noqa: E402
from common.zenoh_session import free_tcp_port  # noqa: E402
from tests.support.processes import cli_cmd  # noqa: E402
from tests.support.zenoh_agent import Agent, Router, await_route, get_replies, lget_keys  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
K = KeySpace()
pytestmark = pytest.mark.timeout(120)


def _client(closer, port, name, **kw):
    a = Agent(name, connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=kw.pop("connect_timeout_ms", 0), **kw)
    closer.append(a)
    assert a.connected, a.hello
    return a


def test_router_relays_pubsub_query_liveliness_and_stops_on_sigterm(closer):
    port = free_tcp_port()
    router = Router("--listen", f"tcp/127.0.0.1:{port}")
    closer.append(router)
    assert f"tcp/127.0.0.1:{port}" in router.banner
    mapper = _client(closer, port, "mapper")
    edge = _client(closer, port, "edge")
    laptop = _client(closer, port, "laptop")

    mapper.cmd("sub", name="frames", key=K.frames_all)
    mapper.cmd("lsub", name="alive", key=K.alive_all)
    mapper.cmd("queryable", key=K.mapper_query, reply="top-5: water tower")
    edge.cmd("queryable", key=K.feature_space("r1"), reply="fs:label-minilm")
    edge.cmd("token", key=K.alive("r1"))
    laptop.cmd("sub", name="layers", key=K.layers_all)
    await_route(edge, mapper, "frames", K.frames("r1"))
    await_route(mapper, laptop, "layers", K.layers("probe"))

    # pub/sub edge -> mapper
    for i in range(3):
        edge.cmd("put", key=K.frames("r1"), payload=f"frame{i}")
    got = mapper.received("frames", n=3, timeout=10)
    assert [s["payload"] for s in got] == ["frame0", "frame1", "frame2"]
    assert {s["key"] for s in got} == {K.frames("r1")}
    # query/reply in both directions
    assert get_replies(laptop, K.mapper_query, payload="water tower") == [
        {"key": K.mapper_query, "payload": "top-5: water tower"}]
    assert get_replies(mapper, K.feature_space("r1")) == [
        {"key": K.feature_space("r1"), "payload": "fs:label-minilm"}]
    # a query nobody serves returns no replies
    assert laptop.cmd("get", key=K.stats, timeout=1.0)["replies"] == []
    # mapper -> laptop layers
    mapper.cmd("put", key=K.layers("voxels"), payload="v1")
    assert [s["payload"] for s in laptop.received("layers", n=1, timeout=10)] == ["v1"]
    # liveliness: appear, then disappear when the token is undeclared
    alive = mapper.received("alive", n=1, timeout=10)
    assert alive[0]["key"] == K.alive("r1") and alive[0]["kind"].endswith("PUT")
    assert lget_keys(laptop, K.alive_all) == [K.alive("r1")]
    edge.cmd("untoken", key=K.alive("r1"))
    alive = mapper.received("alive", n=2, timeout=10)
    assert alive[1]["key"] == K.alive("r1") and alive[1]["kind"].endswith("DELETE")

    for a in (laptop, edge, mapper):
        assert a.close() == 0
    rc, out = router.stop(signal.SIGTERM)
    assert rc == 0, out
    assert "stopped" in out


def test_router_sigint_exit_code_zero(closer):
    router = Router("--listen", f"tcp/127.0.0.1:{free_tcp_port()}")
    closer.append(router)
    rc, out = router.stop(signal.SIGINT)
    assert rc == 0, out


#: a process whose main thread holds its stop event's lock, as inside ``stop.wait()``, when
#: SIGTERM lands (the instant a router that has just printed its banner begins to wait)
_SIGNAL_IN_WAIT = """
import os, signal, threading
from common.zenoh_session import install_signal_handlers
stop = threading.Event()
install_signal_handlers(stop)
with stop._cond:                      # CPython's Event: wait() holds this lock around its wait
    os.kill(os.getpid(), signal.SIGTERM)
    for _ in range(10000):            # the handler runs here, the lock still held
        pass
print("stopped" if stop.wait(10) else "not stopped", flush=True)
"""


def test_a_signal_landing_while_the_stop_wait_holds_its_lock_still_stops():
    """The handler must not set the event itself: set() would wait for a lock its own
    thread holds, forever (the router's SIGINT test hung so, killed after 15 s)."""
    import sys

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    try:
        r = subprocess.run([sys.executable, "-c", _SIGNAL_IN_WAIT], capture_output=True, text=True, env=env,
                           cwd=str(ROOT), timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("the signal handler deadlocked on the stop event's lock")
    assert (r.returncode, r.stdout.strip()) == (0, "stopped"), r.stderr[-2000:]


def test_router_rejects_bad_options():
    env = dict(os.environ, PYTHONPATH=str(ROOT), RUST_LOG="error")
    r = subprocess.run(cli_cmd("router", "--listen", "127.0.0.1:7447"),
                       capture_output=True, text=True, env=env, cwd=str(ROOT), timeout=60)
    assert r.returncode == 2 and "proto/address" in r.stderr
    r = subprocess.run(cli_cmd("router", "--zenoh-config", "/nonexistent.json5"),
                       capture_output=True, text=True, env=env, cwd=str(ROOT), timeout=60)
    assert r.returncode == 2 and "not found" in r.stderr


def test_client_started_before_router_connects_when_it_appears(closer):
    """connect_timeout_ms=-1: the edge keeps retrying (start order does not matter)."""
    port = free_tcp_port()
    edge = Agent("edge", connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=-1, connect_retry_s=0.2, wait=False)
    closer.append(edge)
    time.sleep(1.0)
    assert edge.proc.poll() is None and not edge.hello  # still waiting, not failed
    router = Router("--listen", f"tcp/127.0.0.1:{port}")
    closer.append(router)
    assert edge.wait_ready(30)["ok"], edge.hello
    mapper = _client(closer, port, "mapper")
    mapper.cmd("sub", name="f", key=K.frames_all)
    await_route(edge, mapper, "f", K.frames("r1"))
    edge.cmd("put", key=K.frames("r1"), payload="late-start")
    assert [s["payload"] for s in mapper.received("f", n=1, timeout=10)] == ["late-start"]


def test_one_try_fails_fast_without_router(closer):
    a = Agent("edge", connect=[f"tcp/127.0.0.1:{free_tcp_port()}"], connect_timeout_ms=0)
    closer.append(a)
    assert not a.connected and "ZenohConnectError" in a.hello["error"]
    b = Agent("edge2", connect=[f"tcp/127.0.0.1:{free_tcp_port()}"], connect_timeout_ms=600, connect_retry_s=0.1)
    closer.append(b)
    assert not b.connected and "ZenohConnectError" in b.hello["error"]


def test_clients_reconnect_after_router_restart(closer):
    port = free_tcp_port()
    router = Router("--listen", f"tcp/127.0.0.1:{port}")
    closer.append(router)
    mapper = _client(closer, port, "mapper")
    edge = _client(closer, port, "edge")
    mapper.cmd("sub", name="f", key=K.frames_all)
    await_route(edge, mapper, "f", K.frames("r1"))
    edge.cmd("put", key=K.frames("r1"), payload="before")
    assert mapper.received("f", n=1, timeout=10)[0]["payload"] == "before"
    rc, _ = router.stop()
    assert rc == 0
    router = Router("--listen", f"tcp/127.0.0.1:{port}")
    closer.append(router)
    # puts while the link is still down are lost; keep putting until one arrives (bounded)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        edge.cmd("put", key=K.frames("r1"), payload="after")
        if any(s["payload"] == "after" for s in mapper.received("f", n=2, timeout=0.5)):
            break
    assert any(s["payload"] == "after" for s in mapper.received("f")), "no data after the router came back"


def test_killed_edge_liveliness_is_lost(closer):
    port = free_tcp_port()
    closer.append(Router("--listen", f"tcp/127.0.0.1:{port}"))
    mapper = _client(closer, port, "mapper")
    edge = _client(closer, port, "edge")
    mapper.cmd("lsub", name="alive", key=K.alive_all)
    edge.cmd("token", key=K.alive("r7"))
    assert mapper.received("alive", n=1, timeout=10)[0]["kind"].endswith("PUT")
    edge.kill()  # no clean close
    ev = mapper.received("alive", n=2, timeout=20)
    assert len(ev) == 2 and ev[1]["key"] == K.alive("r7") and ev[1]["kind"].endswith("DELETE")
