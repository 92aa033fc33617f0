"""Router, edge and laptop in three network namespaces (needs root and `ip netns`; skipped
otherwise). The edge (ns A) and the laptop (ns C) can reach only the base station (ns B),
over veth pairs on private subnets; shared memory is off so data really crosses the links."""
from __future__ import annotations

import os

import pytest
import zenoh  # noqa: F401,E402  (core dependency: a missing one fails)

from common.keys import KeySpace  # noqa: E402
from tests.support.netns import network_namespaces  # noqa: E402
from tests.support.zenoh_agent import Agent, Router, await_route, get_replies  # noqa: E402

K = KeySpace()
pytestmark = [pytest.mark.netns, pytest.mark.timeout(120)]


@pytest.fixture
def namespaces():
    tag = f"rf{os.getpid() % 100000}"
    a, b, c = f"{tag}a", f"{tag}b", f"{tag}c"
    # A <-> B on 10.213.1.0/24, C <-> B on 10.213.2.0/24; no forwarding between them
    links = [(left, right, f"{tag}{net}l", f"{tag}{net}r", f"10.213.{net}.1/24", f"10.213.{net}.2/24")
             for left, right, net in ((a, b, "1"), (c, b, "2"))]
    with network_namespaces([a, b, c], links):
        yield a, b, c


def test_three_namespaces_through_router(namespaces):
    a, b, c = namespaces
    items: list = []
    try:
        router = Router("--listen", "tcp/10.213.1.2:7447", "--listen", "tcp/10.213.2.2:7447",
                        argv_prefix=("ip", "netns", "exec", b))
        items.append(router)
        edge = Agent("edge", connect=["tcp/10.213.1.2:7447"], connect_timeout_ms=5000,
                     argv_prefix=("ip", "netns", "exec", a))
        items.append(edge)
        laptop = Agent("laptop", connect=["tcp/10.213.2.2:7447"], connect_timeout_ms=5000,
                       argv_prefix=("ip", "netns", "exec", c))
        items.append(laptop)
        assert edge.connected and laptop.connected, (edge.hello, laptop.hello)
        # the laptop cannot reach the edge's subnet directly
        direct = Agent("direct", connect=["tcp/10.213.1.2:7447"], connect_timeout_ms=0,
                       argv_prefix=("ip", "netns", "exec", c))
        items.append(direct)
        assert not direct.connected
        laptop.cmd("sub", name="f", key=K.frames_all)
        laptop.cmd("lsub", name="alive", key=K.alive_all)
        edge.cmd("token", key=K.alive("r1"))
        edge.cmd("queryable", key=K.feature_space("r1"), reply="fs")
        await_route(edge, laptop, "f", K.frames("r1"))
        for i in range(5):
            edge.cmd("put", key=K.frames("r1"), payload=f"f{i}" * 1000)
        got = laptop.received("f", n=5, timeout=15)
        assert [s["payload"] for s in got] == [f"f{i}" * 1000 for i in range(5)]
        assert [s["key"] for s in laptop.received("alive", n=1, timeout=15)] == [K.alive("r1")]
        assert get_replies(laptop, K.feature_space("r1")) == [
            {"key": K.feature_space("r1"), "payload": "fs"}]
    finally:
        for it in reversed(items):
            try:
                it.close() if isinstance(it, Agent) else it.stop()
            except Exception:
                pass
