"""Each user mistake ends the command with exactly one line on stderr that names the cause,
and a non-zero exit code; no traceback, no Rust source path, and nothing is started first
(a wrong dataset path is reported before the edge connects; a taken port before the mapper
loads anything). Real processes (``python -m apps.cli``), run concurrently to keep it fast."""
from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support.ports import dead_endpoint
from tests.support.processes import ROOT, cli_cmd


@pytest.fixture(scope="module")
def busy_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    yield s.getsockname()[1]
    s.close()


def _cases(tmp: Path, busy: int):
    dead = dead_endpoint()
    not_image = tmp / "notes.jpg"
    not_image.write_text("this is not a picture\n")
    return {
        # name: (argv, words the line must contain, expected exit code)
        "dataset path": (["edge", "source.kind=replica", "source.path=/nonexistent/replica/room0", "--connect", dead],
                         ["source.path", "/nonexistent/replica/room0"], 2),
        "empty query": (["query", "   ", "--connect", dead], ["empty"], 2),
        "no query at all": (["query", "--connect", dead], ["query text"], 2),
        "bad image": (["query", "--image", str(not_image), "--connect", dead], ["notes.jpg", "image"], 2),
        "missing image": (["query", "--image", str(tmp / "nope.png"), "--connect", dead], ["nope.png", "not found"], 2),
        "model dir": (["edge", "encoder.kind=naradio", "encoder.model_dir=/nonexistent/models", "--connect", dead],
                      ["encoder.model_dir", "/nonexistent/models"], 2),
        "mapper text model dir": (["mapper", "text_model_dir=/nonexistent/text", "--listen", dead],
                                  ["text_model_dir", "/nonexistent/text"], 2),
        "mapper port in use": (["mapper", "--listen", f"tcp/127.0.0.1:{busy}"], [f"127.0.0.1:{busy}", "in use"], 1),
        "router port in use": (["router", "--listen", f"tcp/127.0.0.1:{busy}"], [f"127.0.0.1:{busy}", "in use"], 1),
        "no router": (["query", "tree", "--connect", dead, "--timeout", "0.5"], [dead, "router"], 1),
        "bad option value": (["query", "tree", "--top-k", "many"], ["--top-k", "many"], 2),
        "unknown option": (["mapper", "preset=online", "--no-such-option"], ["--no-such-option"], 2),
        "unknown edge action": (["edge", "fit-pcaa"], ["fit-pcaa", "fit-pca"], 2),
        "fit-pca without --out": (["edge", "fit-pca", "source.kind=synthetic"], ["--out"], 2),
    }


def test_each_mistake_is_one_line_naming_the_cause(tmp_path, busy_port):
    cases = _cases(tmp_path, busy_port)
    procs = {}
    t0 = time.monotonic()
    for name, (argv, _, _) in cases.items():
        procs[name] = subprocess.Popen(cli_cmd(*argv), cwd=ROOT, text=True,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    failures = []
    for name, p in procs.items():
        try:
            out, err = p.communicate(timeout=120)
        except subprocess.TimeoutExpired:  # e.g. the edge connected and waits instead of failing first
            p.kill()
            _, err = p.communicate()
            failures.append(f"{name}: still running after {time.monotonic() - t0:.0f} s")
            continue
        _, words, code = cases[name]
        lines = [ln for ln in err.splitlines() if ln.strip()]
        if p.returncode != code:
            failures.append(f"{name}: exit {p.returncode}, expected {code}; stderr={err!r}")
        if len(lines) != 1:
            failures.append(f"{name}: {len(lines)} stderr lines: {err!r}")
            continue
        line = lines[0]
        if not line.startswith("rayfronts "):
            failures.append(f"{name}: line does not name the command: {line!r}")
        for w in words:
            if w.lower() not in line.lower():
                failures.append(f"{name}: {w!r} not in {line!r}")
        for bad in ("Traceback", ".rs:", "Error(", "ZError"):
            if bad in line:
                failures.append(f"{name}: {bad!r} in {line!r}")
    assert not failures, "\n".join(failures)


HELPS = [
    (["edge", "fit-pca", "--help"], "rayfronts edge fit-pca"),
    (["edge", "robot=r1", "--help"], "rayfronts edge"),
    (["mapper", "preset=online", "--help"], "rayfronts mapper"),
    (["models", "check", "--help"], "rayfronts models check"),
    (["eval", "srchvol", "--help"], "rayfronts eval srchvol"),
    (["eval", "report", "--help"], "rayfronts eval report"),
    (["bench", "mapper", "--help"], "rayfronts bench mapper"),
]


def test_help_on_every_sub_action():
    procs = [(prog, subprocess.Popen(cli_cmd(*argv), cwd=ROOT, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)) for argv, prog in HELPS]
    failures = []
    for prog, p in procs:
        out, err = p.communicate(timeout=120)
        if p.returncode != 0 or not out.startswith(f"usage: {prog}") or err.strip():
            failures.append(f"{prog}: exit {p.returncode}, stdout={out[:120]!r}, stderr={err[-300:]!r}")
    assert not failures, "\n".join(failures)


def test_zenoh_errors_are_rephrased_without_rust_paths():
    from common.zenoh_errors import explain_zenoh_error, strip_rust_locations

    raw = ("Can not create a new TCP listener bound to tcp/127.0.0.1:7447: [127.0.0.1:7447: Address already in "
           "use (os error 98) at /root/.cargo/git/checkouts/zenoh-x/io/zenoh-link-commons/src/tcp.rs:61.] at "
           "/root/.cargo/git/checkouts/zenoh-x/io/zenoh-links/zenoh-link-tcp/src/unicast.rs:338.")
    line = explain_zenoh_error(raw)
    assert "tcp/127.0.0.1:7447" in line and "in use" in line and ".rs" not in line
    line = explain_zenoh_error("Unable to connect to any of [Single(tcp/10.0.0.5:7447)]!  at /a/b/orchestrator.rs:447.")
    assert "tcp/10.0.0.5:7447" in line and "rayfronts router" in line
    assert strip_rust_locations('Str("unknown key") at /x/zenoh/src/api/config.rs:86.') == 'Str("unknown key")'


def test_overview_help_imports_no_heavy_module():
    """`rayfronts --help` must not import torch, zenoh or rerun (it printed in 3 s before)."""
    code = ("import sys, contextlib, io\n"
            "from apps.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
            "    try:\n"
            "        main(['--help'])\n"
            "    except SystemExit:\n"
            "        pass\n"
            "assert 'COMMAND' in out.getvalue() and 'query' in out.getvalue()\n"
            "print(sorted(m for m in ('torch', 'zenoh', 'rerun', 'numpy', 'cv2') if m in sys.modules))\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
