"""The README's "Run it as three machines on one" walkthrough, executed literally.

The commands are parsed from README.md (the ```bash blocks of that section) and run with
bash, with the venv's ``rayfronts`` first on PATH. A block whose comment says
``(keeps running; wait for `TEXT`)`` is started in the background and the test waits for
TEXT in its output; the other blocks run line by line and must exit 0. The only changes
made to the text: a loopback port that is already taken on this machine is replaced by a
free one (and then, for the rerun ports, given as an option). Between the robot and the
operator the test waits, as a person would, until the mapper has mapped what the edge sent.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from tests.support.ports import free_port, port_is_free
from tests.support.processes import ROOT, stop_process, wait_log

SECTION = "## Run it as three machines on one"
KEEPS = re.compile(r"keeps running; wait for `([^`]+)`")


def readme_blocks() -> list[dict]:
    text = (ROOT / "README.md").read_text()
    assert SECTION in text, f"README has no {SECTION!r} section"
    body = text.split(SECTION, 1)[1]
    body = body.split("\n## ", 1)[0]
    blocks = []
    for m in re.finditer(r"```bash\n(.*?)```", body, re.S):
        lines = m.group(1).splitlines()
        comments = " ".join(ln.lstrip("# ").strip() for ln in lines if ln.startswith("#"))
        cmds = [ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
        k = KEEPS.search(comments)
        blocks.append({"comment": comments, "commands": cmds, "wait_for": k.group(1) if k else None})
    return blocks


def planner_loop() -> str:
    """The ```python block of the README's "For planners" section."""
    text = (ROOT / "README.md").read_text()
    body = text.split("## For planners", 1)[1].split("\n## ", 1)[0]
    (code,) = re.findall(r"```python\n(.*?)```", body, re.S)
    return code


def test_readme_parses_into_the_walkthrough():
    blocks = readme_blocks()
    assert [b["commands"][0].split()[:2] for b in blocks][:3] == [["rayfronts", "router"], ["rayfronts", "mapper"],
                                                                  ["rayfronts", "edge"]]
    assert blocks[0]["wait_for"] and blocks[1]["wait_for"] and not blocks[2]["wait_for"]
    assert all(c.startswith("rayfronts query") for c in blocks[3]["commands"])
    assert all(c.startswith("rayfronts search") for c in blocks[4]["commands"])
    assert "from query_client import Client" in planner_loop()
    assert "--serve-web" in blocks[1]["commands"][0]


@pytest.mark.timeout(420)
def test_readme_walkthrough_runs_literally(tmp_path):
    blocks = readme_blocks()
    bindir = Path(sys.executable).parent
    assert (bindir / "rayfronts").exists(), f"the rayfronts command is not installed in {bindir} (pip install -e .)"
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}", RUST_LOG="error",
               PYTHONUNBUFFERED="1")
    # swap taken ports (another process on a shared machine) for free ones
    alltext = "\n".join(c for b in blocks for c in b["commands"])
    subst = {}
    for port in sorted({int(p) for p in re.findall(r"127\.0\.0\.1:(\d+)", alltext)}):
        if not port_is_free(port):
            subst[f"127.0.0.1:{port}"] = f"127.0.0.1:{free_port()}"
    extra_mapper = []
    for port, opt in ((9090, "--web-port"), (9876, "--grpc-port")):
        if not port_is_free(port):
            extra_mapper += [opt, str(free_port())]

    def fix(cmd: str) -> str:
        for a, b in subst.items():
            cmd = cmd.replace(a, b)
        if cmd.startswith("rayfronts mapper") and extra_mapper:
            cmd += " " + " ".join(extra_mapper)
        return cmd

    endpoint = fix("tcp/127.0.0.1:7447")
    background: list[tuple[str, subprocess.Popen, Path]] = []
    outputs: dict[str, str] = {}
    try:
        for i, b in enumerate(blocks):
            if b["commands"][0].startswith(("rayfronts query", "rayfronts search")):
                _wait_mapped(endpoint, timeout=120)
            for cmd in b["commands"]:
                cmd = fix(cmd)
                name = cmd.split()[1]
                if b["wait_for"]:
                    log = tmp_path / f"{i}_{name}.log"
                    p = subprocess.Popen(["bash", "-c", f"exec {cmd}"], cwd=tmp_path, env=env,
                                         stdout=open(log, "wb"), stderr=subprocess.STDOUT)
                    background.append((name, p, log))
                    wait_log(p, log, re.escape(b["wait_for"]), timeout=150)
                else:
                    r = subprocess.run(["bash", "-c", cmd], cwd=tmp_path, env=env, capture_output=True, text=True,
                                       timeout=240)
                    assert r.returncode == 0, f"{cmd}\nexit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
                    outputs[cmd] = r.stdout
        q = {c.split('"')[1] if '"' in c else "--stats": out for c, out in outputs.items() if "rayfronts query" in c}
        stats = json.loads(q["--stats"])
        assert stats["frames"]["mapped"] >= 30, stats["frames"]
        assert "query 'vehicle'" in q["vehicle"] and "voxel clusters" in q["vehicle"], q["vehicle"]
        wt = json.loads(q["water tower"])
        assert wt["query"] == "water tower" and len(wt["ray_origin"]) >= 1, wt.keys()
        # the planner's view: vehicles found with ids, goals in free space (one JSON object)
        (search_out,) = [out for c, out in outputs.items() if c.startswith("rayfronts search")]
        found = json.loads(search_out)
        assert found["found"] and all(isinstance(i["id"], int) and i["target"] == "vehicle" for i in found["found"])
        assert found["look_next"], found.keys()
        # "For planners": the Python loop, run as written against the same mapper
        loop = planner_loop().replace("tcp/127.0.0.1:7447", endpoint)
        r = subprocess.run([sys.executable, "-c", loop], cwd=ROOT, env=env, capture_output=True, text=True,
                           timeout=180)
        assert r.returncode == 0, r.stderr[-2000:]
        assert re.search(r"^goal cell state -?\d", r.stdout, re.M), r.stdout
        # the loop finds a vehicle (the CLI found some on the same map, at the same threshold),
        # and every instance it prints is the CLI's instance of that id, at the same centroid
        printed = re.findall(r"^found vehicle #(\d+) at (\[[^]]*\]) p=", r.stdout, re.M)
        assert printed, f"the planner loop printed no 'found vehicle #...' line:\n{r.stdout}"
        cli_found = {i["id"]: i for i in found["found"]}
        for i, at in printed:
            assert int(i) in cli_found, f"#{i} is not among the CLI's ids {sorted(cli_found)}"
            assert json.loads(at) == pytest.approx(cli_found[int(i)]["centroid"], abs=1e-6), (i, at, cli_found[int(i)])
        # the web viewer the mapper serves (rendering is tests/test_browser_view.py)
        web = 9090 if "--web-port" not in extra_mapper else int(extra_mapper[extra_mapper.index("--web-port") + 1])
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as resp:
            assert resp.status == 200 and b"rerun" in resp.read().lower()
    finally:
        codes = {}
        for name, p, _ in reversed(background):  # Ctrl-C, as the README says
            codes[name] = stop_process(p, signal.SIGINT, 60)
    assert all(c == 0 for c in codes.values()), {
        n: (c, (tmp_path / log.name).read_text()[-1500:])
        for (n, _, log), c in zip(reversed(background), codes.values(), strict=False)}


def _wait_mapped(endpoint: str, timeout: float) -> None:
    """What a person does between terminal 3 and 4: wait until the mapper has mapped and
    flushed everything it received."""
    from query_client.client import Client

    with Client(connect=endpoint, timeout=10.0) as c:
        c.wait_settled(received=1, timeout=timeout)
