"""Zenoh config building (common.zenoh_session) from the files shipped in deploy/zenoh/.

The tests load the shipped files themselves (no copies) and override endpoints and
certificate locations the way a deployment does (flags / certs dir / extra keys). Router
configs are proven by opening real sessions on free loopback ports; client configs are
exercised end to end in test_zenoh_net.py / test_zenoh_security.py.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh  # noqa: F401  (core dependency: a missing one fails, never skips)

from common.config import ConfigError, load_config  # noqa: E402
from common.zenoh_session import (  # noqa: E402
    ZenohConfig,
    add_zenoh_arguments,
    free_tcp_port,
    make_config,
    open_session,
    parse_zenoh_set,
    zenoh_config_from_args,
)

ROOT = Path(__file__).resolve().parents[1]
ZDIR = ROOT / "deploy" / "zenoh"
sys.path.insert(0, str(ROOT / "deploy" / "acl"))
import make_acl  # noqa: E402

TLS_KEYS = ["root_ca_certificate", "connect_certificate", "connect_private_key"]


def _get(c, key):
    return json.loads(c.get_json(key))


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(["bash", str(ROOT / "deploy/certs/make_certs.sh"), "-o", str(out), "--robot", "r1",
                    "--operator", "alice"], check=True, capture_output=True, timeout=60)
    return out


def test_shipped_files_exist():
    names = {p.name for p in ZDIR.glob("*.json5")}
    for role in ("router", "edge", "laptop"):
        for variant in ("", "-tls", "-usrpwd"):
            assert f"{role}{variant}.json5" in names


@pytest.mark.parametrize("role,mode", [("router", "router"), ("edge", "client"), ("laptop", "client")])
def test_plain_files_with_endpoint_override(role, mode):
    f = ZDIR / f"{role}.json5"
    c = make_config(ZenohConfig(config_file=str(f)))
    assert _get(c, "mode") == mode
    assert _get(c, "scouting/multicast/enabled") is False
    assert _get(c, "transport/link/tx/lease") == 3000
    if mode == "client":
        assert _get(c, "connect/endpoints") == ["tcp/rayfronts-base:7447"]
        c = make_config(ZenohConfig(config_file=str(f), connect=["tcp/10.1.2.3:7447"]))
        assert _get(c, "connect/endpoints") == ["tcp/10.1.2.3:7447"]
    else:
        assert _get(c, "listen/endpoints") == ["tcp/0.0.0.0:7447"]
        c = make_config(ZenohConfig(config_file=str(f), listen=["tcp/127.0.0.1:7999"]))
        assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:7999"]
    # our keys win over the file's, extra wins over everything
    c = make_config(ZenohConfig(config_file=str(f), mode="peer", lease_ms=1500, shared_memory=False,
                                extra={"transport/link/tx/lease": 2500}))
    assert _get(c, "mode") == "peer"
    assert _get(c, "transport/shared_memory/enabled") is False
    assert _get(c, "transport/link/tx/lease") == 2500


@pytest.mark.parametrize("role", ["router", "edge", "laptop"])
def test_tls_files_resolve_paths_against_certs_dir(role, certs):
    ident = {"router": "router", "edge": "robot-r1", "laptop": "operator-alice"}[role]
    c = make_config(ZenohConfig(config_file=str(ZDIR / f"{role}-tls.json5"), certs_dir=str(certs / ident)))
    assert _get(c, "transport/link/tls/enable_mtls") is True
    assert _get(c, "transport/link/protocols") == ["tls"]
    assert _get(c, "transport/link/tls/root_ca_certificate") == str(certs / ident / "ca.pem")
    assert _get(c, "transport/link/tls/connect_certificate") == str(certs / ident / "cert.pem")
    assert _get(c, "transport/link/tls/connect_private_key") == str(certs / ident / "key.pem")
    if role == "router":
        assert _get(c, "transport/link/tls/listen_certificate") == str(certs / ident / "cert.pem")
        assert _get(c, "listen/endpoints") == ["tls/0.0.0.0:7447"]
    else:
        assert _get(c, "connect/endpoints") == ["tls/rayfronts-base:7447"]


def test_certs_dir_from_environment(certs, monkeypatch):
    monkeypatch.setenv("RAYFRONTS_CERTS", str(certs / "robot-r1"))
    monkeypatch.setenv("RAYFRONTS_ZENOH_CONFIG", str(ZDIR / "edge-tls.json5"))
    c = make_config(ZenohConfig())
    assert _get(c, "mode") == "client"
    assert _get(c, "transport/link/tls/root_ca_certificate") == str(certs / "robot-r1" / "ca.pem")


def test_absolute_path_override_via_extra(certs, tmp_path):
    other = certs / "operator-alice" / "cert.pem"
    c = make_config(ZenohConfig(config_file=str(ZDIR / "edge-tls.json5"), certs_dir=str(certs / "robot-r1"),
                                extra={"transport/link/tls/connect_certificate": str(other)}))
    assert _get(c, "transport/link/tls/connect_certificate") == str(other)


def test_missing_cert_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match=r"root_ca_certificate: file not found: .*ca\.pem"):
        make_config(ZenohConfig(config_file=str(ZDIR / "edge-tls.json5"), certs_dir=str(tmp_path)))


@pytest.mark.parametrize("cfg,match", [
    (ZenohConfig(mode="bridge"), "mode 'bridge'"),
    (ZenohConfig(connect=["127.0.0.1:7447"]), "proto/address"),
    (ZenohConfig(extra={"no/such/key": 1}), "no/such/key"),
    (ZenohConfig(config_file="/nonexistent/z.json5"), "not found"),
    (ZenohConfig(lease_ms=5), "too small"),
    (ZenohConfig(acl_file="/nonexistent/acl.json5"), "access-control file not found"),
])
def test_bad_settings_raise_config_error(cfg, match):
    with pytest.raises(ConfigError, match=match):
        make_config(cfg)


def test_invalid_json5_file(tmp_path):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'client', connect: { endpoints: [ }")
    with pytest.raises(ConfigError, match="invalid"):
        make_config(ZenohConfig(config_file=str(bad)))


def test_default_mode_and_multicast_off():
    c = make_config(ZenohConfig())
    assert _get(c, "mode") == "client" and _get(c, "scouting/multicast/enabled") is False
    assert _get(make_config(ZenohConfig(), default_mode="router"), "mode") == "router"
    assert _get(make_config(ZenohConfig(multicast_scouting=True)), "scouting/multicast/enabled") is True


def test_yaml_section_overrides():
    cfg = load_config(ZenohConfig, overrides=["connect=[tcp/10.0.0.1:7447]", "lease_ms=2000", "shared_memory=false",
                                              "prefix=site1", "extra={transport/link/tx/keep_alive: 5}"])
    assert cfg.connect == ["tcp/10.0.0.1:7447"] and cfg.prefix == "site1"
    c = make_config(cfg)
    assert _get(c, "transport/link/tx/lease") == 2000
    assert _get(c, "transport/link/tx/keep_alive") == 5
    with pytest.raises(ConfigError, match="connect_timeout_ms"):
        load_config(ZenohConfig, overrides=["connect_timeout=5"])


def test_cli_arguments_roundtrip(certs):
    p = argparse.ArgumentParser()
    add_zenoh_arguments(p)
    a = p.parse_args(["--zenoh-config", str(ZDIR / "edge-tls.json5"), "--connect", "tls/localhost:1",
                      "--connect", "tls/127.0.0.1:2", "--certs", str(certs / "robot-r1"), "--mode", "client",
                      "--zenoh-set", "transport/link/tx/lease=1234", "--zenoh-set", "id=\"aa\""])
    base = ZenohConfig(prefix="p2", extra={"transport/link/tx/keep_alive": 3})
    cfg = zenoh_config_from_args(a, base)
    assert cfg.prefix == "p2" and cfg.connect == ["tls/localhost:1", "tls/127.0.0.1:2"]
    assert cfg.extra == {"transport/link/tx/keep_alive": 3, "transport/link/tx/lease": 1234, "id": "aa"}
    c = make_config(cfg)
    assert _get(c, "connect/endpoints") == ["tls/localhost:1", "tls/127.0.0.1:2"]
    assert _get(c, "transport/link/tx/lease") == 1234
    # nothing given: base unchanged
    assert zenoh_config_from_args(p.parse_args([]), base) == base
    assert parse_zenoh_set(["a=1", "b=word", "c={\"x\": [1]}"]) == {"a": 1, "b": "word", "c": {"x": [1]}}
    with pytest.raises(ConfigError):
        parse_zenoh_set(["novalue"])


def _open_and_close(cfg: ZenohConfig):
    s = open_session(cfg, default_mode="router")
    try:
        assert len(str(s.zid())) >= 16
    finally:
        s.close()
    assert s.is_closed()


def test_router_configs_open_real_sessions(certs, tmp_path):
    """Zenoh 1.10 accepts the shipped router configs, with the generated ACL (cert and usrpwd)."""
    _open_and_close(ZenohConfig(config_file=str(ZDIR / "router.json5"), listen=[f"tcp/127.0.0.1:{free_tcp_port()}"]))
    _open_and_close(ZenohConfig(config_file=str(ZDIR / "router-tls.json5"), certs_dir=str(certs / "router"),
                                listen=[f"tls/127.0.0.1:{free_tcp_port()}"], acl_file=str(certs / "acl.json5")))
    (tmp_path / "credentials.txt").write_text((ZDIR / "credentials.example.txt").read_text())
    acl_u = tmp_path / "acl-usrpwd.json5"
    acl_u.write_text(make_acl.render(make_acl.make_acl(["r1", "r2"], ["alice"], auth="usrpwd")))
    _open_and_close(ZenohConfig(config_file=str(ZDIR / "router-usrpwd.json5"), certs_dir=str(tmp_path),
                                listen=[f"tcp/127.0.0.1:{free_tcp_port()}"], acl_file=str(acl_u)))


def test_acl_with_unknown_message_is_rejected(tmp_path):
    acl = make_acl.make_acl(["r1"])
    acl["rules"][0]["messages"] = ["publish"]  # not a Zenoh 1.10 ACL message
    f = tmp_path / "acl.json5"
    f.write_text(json.dumps(acl))
    with pytest.raises((ConfigError, Exception)) as ei:
        _open_and_close(ZenohConfig(listen=[f"tcp/127.0.0.1:{free_tcp_port()}"], acl_file=str(f)))
    assert "publish" in str(ei.value) or "unknown variant" in str(ei.value)


def test_make_acl_structure():
    acl = make_acl.make_acl(["r1", "r2"], ["alice", "bob"], prefix="site")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    for r in acl["rules"]:
        assert set(r["messages"]) <= set(make_acl.ALL_MESSAGES) and r["permission"] == "allow"
        assert set(r["flows"]) <= {"ingress", "egress"}
        assert all(k.startswith("site/") for k in r["key_exprs"])
    assert set(rules["mapper_all"]["messages"]) == set(make_acl.ALL_MESSAGES)
    # what a robot sends or receives names it (its prefix, its planner keys under
    # site/mapper/robots/<robot>/) or is shared and read-only (liveliness of mapper and shards,
    # the map's feature space, the shards' routing announcements); only declarations of the
    # mapper's subscriptions, which carry no data, may name every robot
    pol = {p["id"]: p for p in acl["policies"]}
    shared = {"site/mapper/alive", "site/mapper/shards/*", "site/mapper/feature_space", "site/mapper/shards/*/routing"}
    for robot in ("r1", "r2"):
        mine = (f"site/robots/{robot}/", f"site/mapper/robots/{robot}/")
        for rid in pol[f"robot_{robot}"]["rules"]:
            r = rules[rid]
            for k in r["key_exprs"]:
                if r["messages"] == ["declare_subscriber"] and r["flows"] == ["egress"]:
                    assert k.startswith("site/robots/*/"), (rid, k)
                    continue
                assert k.startswith(mine) or k in shared, (rid, k)
                if "ingress" in r["flows"] and {"put", "declare_queryable", "liveliness_token"} & set(r["messages"]):
                    assert k.startswith(f"site/robots/{robot}/"), (rid, k)
    # nobody but the mapper may put/serve anything under site/mapper/**
    for rid, r in rules.items():
        if rid == "mapper_all" or "ingress" not in r["flows"]:
            continue
        if {"put", "delete", "declare_queryable", "reply", "liveliness_token"} & set(r["messages"]):
            assert not any(k.startswith("site/mapper/") for k in r["key_exprs"]), rid
    subj = {s["id"]: s for s in acl["subjects"]}
    assert subj["robot_r1"]["cert_common_names"] == ["robot-r1"]
    assert subj["operators"]["cert_common_names"] == ["operator-alice", "operator-bob"]
    both = make_acl.make_acl(["r1"], auth="both")
    assert {s["id"] for s in both["subjects"]} >= {"robot_r1_cert", "robot_r1_user"}
    for bad in (["a/b"], ["r1", "r1"], ["*"]):
        with pytest.raises(ValueError):
            make_acl.make_acl(bad)


def test_a_program_that_never_closes_its_session_still_exits(tmp_path):
    """Zenoh serves a callback subscriber from a non-daemon thread that ends only when its
    session closes; a session from open_session is closed before the interpreter joins
    threads, so a program that forgets close() (a failed test, a crashed script) exits."""
    prog = tmp_path / "forgets_close.py"
    prog.write_text(
        "from common.zenoh_session import ZenohConfig, open_session\n"
        "s = open_session(ZenohConfig(mode='peer', listen=['tcp/127.0.0.1:0']))\n"
        "sub = s.declare_subscriber('rayfronts/x/**', lambda sample: None)\n"
        "q = s.declare_queryable('rayfronts/y', lambda query: None)\n"
        "kept = [s, sub, q]\n"
        "print('leaving with the session open', flush=True)\n")
    out = subprocess.run([sys.executable, str(prog)], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "leaving with the session open" in out.stdout
