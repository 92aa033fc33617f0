"""Mutual TLS, user/password and access control with the shipped deploy/ files (Zenoh 1.10).

Certificates come from deploy/certs/make_certs.sh (in a tmp dir), the ACL from
deploy/acl/make_acl.py; the configs are the shipped deploy/zenoh/*.json5 with endpoint and
certs-dir overrides. Real sessions in separate processes over loopback.

Negative checks are ordered, not timed: after a denied message, the same client sends an
allowed one along the same path; once that has arrived, the denied one would have too.
"""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh  # noqa: F401,E402  (core dependency: a missing one fails)

from common.keys import KeySpace  # noqa: E402
from common.zenoh_session import free_tcp_port  # noqa: E402
from tests.support.site import MAKE_CERTS, ZDIR, tls_agent  # noqa: E402
from tests.support.zenoh_agent import Agent, Router, await_route, get_replies, lget_keys  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "deploy" / "acl"))
import make_acl  # noqa: E402

K = KeySpace()
pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    subprocess.run(["bash", str(MAKE_CERTS), "-o", str(out), "--robot", "r1", "--robot", "r2",
                    "--operator", "alice"], check=True, capture_output=True, timeout=60)
    return out


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("other")
    subprocess.run(["bash", str(MAKE_CERTS), "-o", str(out), "--robot", "r1", "--no-acl"],
                   check=True, capture_output=True, timeout=60)
    return out


def test_mutual_tls(closer, certs, other_ca):
    port = free_tcp_port()
    router = Router("--zenoh-config", str(ZDIR / "router-tls.json5"), "--certs", str(certs / "router"),
                    "--listen", f"tls/127.0.0.1:{port}")
    closer.append(router)
    assert f"tls/127.0.0.1:{port}" in router.banner
    mapper = tls_agent(closer, port, "mapper", certs / "mapper")
    edge = tls_agent(closer, port, "edge", certs / "robot-r1")
    assert mapper.connected and edge.connected, (mapper.hello, edge.hello)
    mapper.cmd("sub", name="f", key=K.frames_all)

    # no client certificate: the handshake is refused
    nocert = tls_agent(closer, port, "nocert", certs / "robot-r1",
                         extra={"transport/link/tls/connect_certificate": None,
                                "transport/link/tls/connect_private_key": None})
    # a certificate from another CA (trusting our router's CA, so only the client cert differs)
    foreign = tls_agent(closer, port, "foreign", certs / "robot-r1",
                          extra={"transport/link/tls/connect_certificate": str(other_ca / "robot-r1/cert.pem"),
                                 "transport/link/tls/connect_private_key": str(other_ca / "robot-r1/key.pem")})
    # a client that trusts another CA does not accept our router
    untrusting = tls_agent(closer, port, "untrusting", other_ca / "robot-r1")
    # plain TCP to the TLS port
    plain = Agent("plain", config_file=str(ZDIR / "edge.json5"), connect=[f"tcp/127.0.0.1:{port}"],
                  connect_timeout_ms=0)
    closer.append(plain)
    for a in (nocert, foreign, untrusting, plain):
        assert not a.connected, f"{a.name} connected: {a.hello}"
        assert "ZenohConnectError" in a.hello["error"]

    await_route(edge, mapper, "f", K.frames("r1"))
    edge.cmd("put", key=K.frames("r1"), payload="over-tls")
    assert [s["payload"] for s in mapper.received("f", n=1, timeout=10)] == ["over-tls"]
    rc, out = router.stop(signal.SIGTERM)
    assert rc == 0, out


def test_access_control(closer, certs):
    port = free_tcp_port()
    # The router is an agent so that it can also hold a local ("router side") subscriber:
    # local entities bypass the ACL, so it sees whatever the ACL lets in.
    router = Agent("router", config_file=str(ZDIR / "router-tls.json5"), certs_dir=str(certs / "router"),
                   listen=[f"tls/127.0.0.1:{port}"], acl_file=str(certs / "acl.json5"), default_mode="router")
    closer.append(router)
    assert router.connected, router.hello
    mapper = tls_agent(closer, port, "mapper", certs / "mapper")
    r1 = tls_agent(closer, port, "r1", certs / "robot-r1")
    r2 = tls_agent(closer, port, "r2", certs / "robot-r2")
    op = tls_agent(closer, port, "op", certs / "operator-alice", cfg="laptop-tls.json5")
    for a in (mapper, r1, r2, op):
        assert a.connected, a.hello

    router.cmd("sub", name="all", key=K.everything)
    mapper.cmd("sub", name="frames", key=K.frames_all)
    mapper.cmd("sub", name="mapper_ns", key="rayfronts/mapper/**")
    mapper.cmd("lsub", name="alive", key=K.alive_all)
    mapper.cmd("queryable", key=K.mapper_query, reply="answer")
    mapper.cmd("queryable", key=K.mapper_fleet_search, reply="fleet")
    mapper.cmd("queryable", key=K.robot_unreachable_all, reply="unreachable")
    mapper.cmd("token", key=K.mapper_alive)
    r1.cmd("queryable", key=K.feature_space("r1"), reply="fs-r1")
    r1.cmd("token", key=K.alive("r1"))
    op.cmd("sub", name="layers", key=K.layers_all)
    op.cmd("sub", name="frames", key=K.frames_all)  # not allowed: must receive nothing
    op.cmd("lsub", name="alive", key=K.alive_all)
    op.cmd("lsub", name="mapper_alive", key=K.mapper_alive)
    r1.cmd("lsub", name="mapper_alive", key=K.mapper_alive)
    # routes exist before anything is tested (declarations travel asynchronously)
    await_route(r1, mapper, "frames", K.frames("r1"))
    await_route(r2, mapper, "frames", K.frames("r2"))
    await_route(mapper, op, "layers", K.layers("probe"))
    await_route(mapper, router, "all", K.layers("probe"))
    assert get_replies(op, K.mapper_query) == [{"key": K.mapper_query, "payload": "answer"}]
    assert get_replies(mapper, K.feature_space("r1")) == [{"key": K.feature_space("r1"), "payload": "fs-r1"}]

    # -- denied: laptop publishes robot frames; robot r1 impersonates r2 / the mapper
    op.cmd("put", key=K.frames("r1"), payload="forged-by-operator")
    r1.cmd("put", key=K.frames("r2"), payload="r1-as-r2")
    r1.cmd("put", key=K.layers("voxels"), payload="r1-forged-layer")
    r1.cmd("put", key=K.alive("r1"), payload="put-on-alive")  # only a token is allowed there
    r1.cmd("token", key=K.alive("r2"))
    r1.cmd("queryable", key=K.stats, reply="r1-fake-stats")
    # -- allowed, sent after the denied ones on the same links
    r1.cmd("put", key=K.frames("r1"), payload="r1-own")
    r2.cmd("put", key=K.frames("r2"), payload="r2-own")
    assert op.cmd("get", key=K.mapper_query, payload="water tower")["replies"] == [
        {"key": K.mapper_query, "payload": "answer"}]
    frames = mapper.received("frames", n=2, timeout=10)
    assert sorted(s["payload"] for s in frames) == ["r1-own", "r2-own"]
    mapper.cmd("put", key=K.layers("voxels"), payload="layer-1")
    assert [s["payload"] for s in op.received("layers", n=1, timeout=10)] == ["layer-1"]

    # what reached the router itself: only the allowed puts (+ the mapper's layer)
    seen = router.received("all", n=3, timeout=10)
    assert sorted(s["payload"] for s in seen) == ["layer-1", "r1-own", "r2-own"]
    # ... and the mapper never saw anything forged under its namespace or robots'
    assert [s["payload"] for s in mapper.received("mapper_ns")] == ["layer-1"]
    assert sorted(s["payload"] for s in mapper.received("frames")) == ["r1-own", "r2-own"]
    # the operator may not read raw frames (its own put is delivered locally, inside its
    # own session, which is no network traffic)
    assert [s["payload"] for s in op.received("frames")] == ["forged-by-operator"]

    # queries: mapper -> r1 feature space allowed; operator -> r1 denied; r1's fake stats unseen
    assert mapper.cmd("get", key=K.feature_space("r1"))["replies"] == [
        {"key": K.feature_space("r1"), "payload": "fs-r1"}]
    assert op.cmd("get", key=K.feature_space("r1"), timeout=2.0)["replies"] == []
    assert op.cmd("get", key=K.stats, timeout=2.0)["replies"] == []
    assert r1.cmd("get", key=K.mapper_query, timeout=2.0)["replies"] == []  # robots cannot query the mapper
    # fleet search: the operators ask it, a robot may not; a robot reports its own unreachable goals only
    assert op.cmd("get", key=K.mapper_fleet_search)["replies"] == [{"key": K.mapper_fleet_search, "payload": "fleet"}]
    assert r1.cmd("get", key=K.robot_unreachable("r1"))["replies"] == [
        {"key": K.robot_unreachable("r1"), "payload": "unreachable"}]
    assert r1.cmd("get", key=K.mapper_fleet_search, timeout=1.0)["replies"] == []
    assert r1.cmd("get", key=K.robot_unreachable("r2"), timeout=1.0)["replies"] == []

    # liveliness: r1's own token is visible, its forged r2 token is not
    assert [s["key"] for s in mapper.received("alive", n=1, timeout=10)] == [K.alive("r1")]
    assert [s["key"] for s in op.received("alive", n=1, timeout=10)] == [K.alive("r1")]
    assert lget_keys(op, K.alive_all) == [K.alive("r1")]
    assert [s["key"] for s in op.received("mapper_alive", n=1, timeout=10)] == [K.mapper_alive]
    assert [s["key"] for s in r1.received("mapper_alive", n=1, timeout=10)] == [K.mapper_alive]
    # the events above arrived after the forged token would have: it never shows up
    assert [s["key"] for s in mapper.received("alive")] == [K.alive("r1")]


def test_usrpwd_with_username_acl(closer, tmp_path):
    (tmp_path / "credentials.txt").write_text("mapper:pw-m\nrobot-r1:pw-1\n")
    acl = tmp_path / "acl.json5"
    acl.write_text(make_acl.render(make_acl.make_acl(["r1"], [], auth="usrpwd")))
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = Agent("router", config_file=str(ZDIR / "router-usrpwd.json5"), certs_dir=str(tmp_path),
                   listen=[ep], acl_file=str(acl), default_mode="router")
    closer.append(router)
    assert router.connected, router.hello

    def client(name, cfg, user, pw):
        a = Agent(name, config_file=str(ZDIR / cfg), connect=[ep], connect_timeout_ms=0,
                  extra={"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": pw})
        closer.append(a)
        return a

    bad = client("bad", "edge-usrpwd.json5", "robot-r1", "wrong")
    anon = Agent("anon", config_file=str(ZDIR / "edge.json5"), connect=[ep], connect_timeout_ms=0)
    closer.append(anon)
    assert not bad.connected and not anon.connected
    mapper = client("mapper", "laptop-usrpwd.json5", "mapper", "pw-m")
    r1 = client("r1", "edge-usrpwd.json5", "robot-r1", "pw-1")
    assert mapper.connected and r1.connected, (mapper.hello, r1.hello)
    mapper.cmd("sub", name="f", key=K.frames_all)
    await_route(r1, mapper, "f", K.frames("r1"))
    r1.cmd("put", key=K.frames("r2"), payload="denied")
    r1.cmd("put", key=K.frames("r1"), payload="allowed")
    assert [s["payload"] for s in mapper.received("f", n=1, timeout=10)] == ["allowed"]
    assert [s["payload"] for s in mapper.received("f")] == ["allowed"]
