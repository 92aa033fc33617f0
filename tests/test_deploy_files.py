"""The deployment kit (deploy/): certificate script, ACL generator, service units, images,
example configs. Checked against openssl, Zenoh and the real command-line parsers."""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
MAKE_CERTS = DEPLOY / "certs" / "make_certs.sh"
sys.path.insert(0, str(DEPLOY / "acl"))
import make_acl  # noqa: E402


def _strip_comments(text: str) -> str:
    return "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("//"))


def _subject(pem: Path) -> str:
    return subprocess.run(["openssl", "x509", "-in", str(pem), "-noout", "-subject", "-nameopt", "RFC2253"],
                          capture_output=True, text=True, check=True).stdout


def _run_certs(out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(MAKE_CERTS), "-o", str(out), *args], capture_output=True, text=True,
                          timeout=60)


def test_make_certs_layout_names_and_chain(tmp_path):
    out = tmp_path / "site"
    r = _run_certs(out, "--host", "base.lab", "--ip", "10.0.0.5", "--robot", "r1", "--robot", "jackal_2",
                   "--operator", "alice")
    assert r.returncode == 0, r.stderr
    ca = out / "ca" / "ca.pem"
    expect = {"router": "router", "mapper": "mapper", "robot-r1": "robot-r1", "robot-jackal_2": "robot-jackal_2",
              "operator-alice": "operator-alice"}
    for d, cn in expect.items():
        ident = out / d
        assert {p.name for p in ident.iterdir()} == {"ca.pem", "cert.pem", "key.pem"}
        assert (ident / "ca.pem").read_bytes() == ca.read_bytes()
        assert oct((ident / "key.pem").stat().st_mode & 0o777) == "0o600"
        v = subprocess.run(["openssl", "verify", "-CAfile", str(ca), str(ident / "cert.pem")],
                           capture_output=True, text=True)
        assert v.returncode == 0, v.stdout + v.stderr
        assert f"CN={cn}" in _subject(ident / "cert.pem")
        # the key matches the certificate
        pub_cert = subprocess.run(["openssl", "x509", "-in", str(ident / "cert.pem"), "-noout", "-pubkey"],
                                  capture_output=True, text=True, check=True).stdout
        pub_key = subprocess.run(["openssl", "pkey", "-in", str(ident / "key.pem"), "-pubout"],
                                 capture_output=True, text=True, check=True).stdout
        assert pub_cert == pub_key
    san = subprocess.run(["openssl", "x509", "-in", str(out / "router/cert.pem"), "-noout", "-ext",
                          "subjectAltName"], capture_output=True, text=True, check=True).stdout
    assert "DNS:base.lab" in san and "IP Address:10.0.0.5" in san
    # the site ACL for the same robots/operators
    acl = json.loads(_strip_comments((out / "acl.json5").read_text()))
    assert acl == make_acl.make_acl(["r1", "jackal_2"], ["alice"])


def test_make_certs_is_idempotent_and_extends(tmp_path):
    out = tmp_path / "site"
    assert _run_certs(out, "--robot", "r1").returncode == 0
    before = {p: p.read_bytes() for p in out.rglob("*.pem")}
    r = _run_certs(out, "--robot", "r1", "--robot", "r2")
    assert r.returncode == 0, r.stderr
    for p, data in before.items():
        assert p.read_bytes() == data, f"{p} was re-issued"
    assert (out / "robot-r2" / "cert.pem").is_file()
    assert "keeping CA" in r.stdout


@pytest.mark.parametrize("args", [["--robot", "a/b"], ["--robot", "r 1"], ["--bogus"], []])
def test_make_certs_rejects_bad_input(tmp_path, args):
    cmd = ["bash", str(MAKE_CERTS), *([] if not args else ["-o", str(tmp_path / "x")]), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.strip()


def test_shipped_acl_example_matches_generator_and_opens():
    import zenoh

    from common.zenoh_session import ZenohConfig, free_tcp_port, open_session

    f = DEPLOY / "acl" / "acl.example.json5"
    assert json.loads(_strip_comments(f.read_text())) == make_acl.make_acl(["r1", "r2"], ["alice"])
    s = open_session(ZenohConfig(listen=[f"tcp/127.0.0.1:{free_tcp_port()}"], acl_file=str(f)),
                     default_mode="router")
    try:
        assert isinstance(s, zenoh.Session) and len(str(s.zid())) >= 16
    finally:
        s.close()


def test_make_acl_cli(tmp_path):
    out = tmp_path / "acl.json5"
    r = subprocess.run([sys.executable, str(DEPLOY / "acl/make_acl.py"), "--robot", "r9", "--operator", "bob",
                        "--auth", "both", "--prefix", "site", "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert json.loads(_strip_comments(out.read_text())) == make_acl.make_acl(["r9"], ["bob"], "site", "both")
    r = subprocess.run([sys.executable, str(DEPLOY / "acl/make_acl.py"), "--robot", "bad/id"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "invalid robot id" in r.stderr


def _env_example() -> dict[str, str]:
    env = {}
    for line in (DEPLOY / "systemd" / "rayfronts.env.example").read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            k, v = line.split("=", 1)
            env[k.strip()] = v.strip()
    return env


def _unit(name: str) -> dict[str, dict[str, str]]:
    sections: dict[str, dict[str, str]] = {}
    cur = None
    for line in (DEPLOY / "systemd" / name).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"\[(\w+)\]", line)
        if m:
            cur = sections.setdefault(m.group(1), {})
            continue
        k, v = line.split("=", 1)
        cur[k] = v
    return sections


@pytest.mark.parametrize("unit,sub", [("rayfronts-router.service", "router"),
                                      ("rayfronts-mapper.service", "mapper"),
                                      ("rayfronts-edge.service", "edge"),
                                      ("rayfronts-console.service", "console")])
def test_systemd_units_run_real_subcommands(unit, sub):
    u = _unit(unit)
    assert set(u) == {"Unit", "Service", "Install"}
    assert u["Service"]["EnvironmentFile"] == "/etc/rayfronts/rayfronts.env"
    assert u["Service"]["KillSignal"] == "SIGTERM"
    env = _env_example()
    exec_start = u["Service"]["ExecStart"]
    for var in re.findall(r"\$\{(\w+)\}", exec_start):
        assert var in env, f"{unit}: {var} not in rayfronts.env.example"
    argv = shlex.split(re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], exec_start))
    assert argv[0].endswith("/bin/rayfronts") and argv[1] == sub
    from apps.cli import build_parser

    parser = build_parser(sub)
    args = parser.parse_args(argv[1:])  # unknown flags would exit with status 2
    assert args.command == sub
    if hasattr(args, "zenoh_acl") and "--acl" in argv:
        assert args.zenoh_acl == env["RAYFRONTS_ACL"]


def test_dockerfiles():
    edge = (DEPLOY / "docker" / "Dockerfile.edge").read_text()
    mapper = (DEPLOY / "docker" / "Dockerfile.mapper").read_text()
    assert re.search(r"^FROM nvcr\.io/nvidia/l4t-jetpack:\$\{L4T_TAG\}", edge, re.M)
    assert re.search(r"^ARG L4T_TAG=r36\.", edge, re.M)
    edge_code = re.sub(r"#.*", "", edge)
    assert "rerun" not in edge_code and "[mapper" not in edge_code and 'pip install ".[edge]"' in edge_code
    assert re.search(r"^FROM nvidia/cuda:", mapper, re.M)
    assert "libopenvdb-dev" in mapper and "libboost-iostreams-dev" in mapper
    assert 'pip install ".[mapper,label]"' in mapper
    for text in (edge, mapper):
        for src in re.findall(r"^COPY (\S+(?: \S+)*) \S+$", text, re.M):
            for s in src.split():
                assert (ROOT / s).exists(), f"COPY source {s} missing"
        assert 'ENTRYPOINT ["rayfronts"]' in text
        assert "COPY apps ./apps" in text   # the rayfronts command is apps.cli:main


def test_example_configs_use_existing_keys():
    from common.config import load_config
    from edge.config import edge_config_schema
    from mapper.service_config import MapperConfig
    edge = load_config(edge_config_schema(), DEPLOY / "examples" / "edge.yaml")
    assert edge.zenoh.connect and edge.robot == "r1"
    mapper = load_config(MapperConfig, DEPLOY / "examples" / "mapper.yaml")
    assert mapper.zenoh.mode == "router" and mapper.zenoh.acl_file


def test_readme_covers_the_topics():
    text = (DEPLOY / "README.md").read_text().lower()
    for topic in ("base station", "jetson", "laptop", "make_certs.sh", "make_acl.py", "bandwidth",
                  "rerun", "troubleshooting", "peer", "shared memory", "wait_before_close", "7447", "9876",
                  "rayfronts_certs", "--connect", "openvdb"):
        assert topic in text, topic


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="bash + openssl test")
def test_scripts_are_executable():
    assert os.access(MAKE_CERTS, os.X_OK)
    assert os.access(DEPLOY / "acl" / "make_acl.py", os.X_OK)
