"""The field site of deploy/README.md on loopback, as the site tests build it: certificates
from deploy/certs/make_certs.sh, the shipped deploy/zenoh/*-tls.json5 configs, TLS agents and
planner clients with an identity's certificates, and the checks that the site still refuses
what it must (another CA, a robot forging another's frames or asking another's searches, an
operator publishing frames). Used by tests/test_zenoh_security.py and
tests/test_site_rehearsal.py."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from common.keys import KeySpace
from tests.support.processes import ROOT
from tests.support.zenoh_agent import Agent, await_route, lget_keys

ZDIR = ROOT / "deploy" / "zenoh"
MAKE_CERTS = ROOT / "deploy" / "certs" / "make_certs.sh"
K = KeySpace()


def make_certs(out: Path, *args: str) -> subprocess.Popen:
    """Start ``make_certs.sh -o out args...`` (wait with :func:`certs_done`)."""
    return subprocess.Popen(["bash", str(MAKE_CERTS), "-o", str(out), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def certs_done(p: subprocess.Popen, out: Path, timeout: float = 60.0) -> Path:
    """``out`` once the :func:`make_certs` run ``p`` has succeeded."""
    log, _ = p.communicate(timeout=timeout)
    assert p.returncode == 0, log[-2000:]
    return out


def tls_args(certs_dir: Path, cfg: str = "edge-tls.json5") -> list[str]:
    """A rayfronts role's arguments for the shipped TLS config ``cfg`` with the identity in ``certs_dir``."""
    return ["--zenoh-config", str(ZDIR / cfg), "--certs", str(certs_dir)]


def tls_agent(closer: list, port: int, name: str, certs_dir: Path, cfg: str = "edge-tls.json5", **kw) -> Agent:
    """A :class:`Agent` with the identity in ``certs_dir`` connecting over TLS to the router on
    ``port`` (shipped ``cfg``), registered with ``closer``."""
    a = Agent(name, config_file=str(ZDIR / cfg), certs_dir=str(certs_dir),
              connect=kw.pop("connect", [f"tls/localhost:{port}"]), connect_timeout_ms=0, **kw)
    closer.append(a)
    return a


def acl_router(closer: list, certs: Path, port: int) -> Agent:
    """The site router as an agent (mTLS with ``certs/router``, the ACL ``certs/acl.json5``) on
    ``tls/127.0.0.1:port``; an agent so that it can hold local subscribers (they bypass the ACL
    and so see whatever it lets in)."""
    router = Agent("router", config_file=str(ZDIR / "router-tls.json5"), certs_dir=str(certs / "router"),
                   listen=[f"tls/127.0.0.1:{port}"], acl_file=str(certs / "acl.json5"), default_mode="router")
    closer.append(router)
    assert router.connected, router.hello
    return router


def planner(certs_dir: Path, port: int, **kw):
    """A planner ``Client`` with the identity in ``certs_dir`` (shipped laptop-tls.json5); ``kw``
    as ``Client`` (e.g. ``robot=``)."""
    from common.zenoh_session import ZenohConfig
    from query_client import Client

    zc = ZenohConfig(config_file=str(ZDIR / "laptop-tls.json5"), certs_dir=str(certs_dir),
                     connect=[f"tls/localhost:{port}"], connect_timeout_ms=kw.pop("connect_timeout_ms", 60_000),
                     connect_retry_s=0.2)
    return Client(zc, timeout=kw.pop("timeout", 20.0), **kw)


def goal_of(reply) -> list[float]:
    """The README planner loop's choice: the best instance, else the best look-next goal."""
    return list(reply.found[0]["centroid"]) if reply.found else list(reply.look_next[0]["position"])


def answer_of(reply) -> tuple:
    """What a planner acts on, for comparing two answers of the same map (no timings/events)."""
    return (reply.map_version, reply.frames_mapped,
            [(i["id"], i["target"], tuple(i["centroid"]), i["voxels"]) for i in reply.found],
            [(tuple(g["position"]), g["heading_rad"], g["score"]) for g in reply.look_next])


def assert_still_refused(closer: list, router: Agent, port: int, certs: Path, other_ca: Path) -> None:
    """What the site refused before it still refuses: a planner with another CA's certificate
    does not connect; robot r1's certificate cannot ask robot r2's searches (one-line error),
    nor publish r2's frames; an operator cannot publish frames. Ordered, not timed: after each
    refused message the same client sends an allowed one along the same path."""
    from query_client import MapperUnavailable

    with pytest.raises(Exception, match="ZenohConnectError|TLS|connect"):
        planner(other_ca / "robot-r1", port, connect_timeout_ms=0)
    with planner(certs / "robot-r1", port, robot="r2") as spoof:      # r1's certificate, r2's searches
        with pytest.raises(MapperUnavailable, match="allowed to ask") as e:
            spoof.search(["car"], timeout=2.0)
        assert "\n" not in str(e.value)
    r1 = tls_agent(closer, port, "r1-forger", certs / "robot-r1")
    opa = tls_agent(closer, port, "op-publisher", certs / "operator-alice", cfg="laptop-tls.json5")
    router.cmd("sub", name="r2", key="rayfronts/robots/r2/**")
    router.cmd("sub", name="r1_status", key=K.edge_status("r1"))
    router.cmd("sub", name="r1_frames", key=K.frames("r1") + "/**")
    router.cmd("sub", name="r1_frames_plain", key=K.frames("r1"))
    await_route(r1, router, "r1_status", K.edge_status("r1"))
    r1.cmd("put", key=K.frames("r2"), payload="r1-as-r2")
    r1.cmd("put", key=K.frames("r2") + "/0_0", payload="r1-as-r2-tile")
    r1.cmd("put", key=K.edge_status("r1"), payload="r1-own")          # allowed, after them on the same link
    assert [s["payload"] for s in router.received("r1_status", n=1, timeout=10)] == ["r1-own"]
    assert router.received("r2") == []
    opa.cmd("put", key=K.frames("r1"), payload="forged-by-operator")
    opa.cmd("put", key=K.frames("r1") + "/0_0", payload="forged-tile-by-operator")
    assert lget_keys(opa, K.mapper_alive) == [K.mapper_alive]          # allowed, after them on the same link
    assert router.received("r1_frames") == [] and router.received("r1_frames_plain") == []
