"""The mapper's rerun web viewer (``rayfronts mapper --serve-web``) in headless Debian chromium.

Real processes on loopback: a router, the mapper with ``--serve-web``, an edge playing the
synthetic world, then one query. The page the mapper serves (rerun's own web viewer, served
locally: no internet) is loaded in headless chromium driven over the DevTools protocol (a
stdlib WebSocket client in tests/support/browser.py, no extra package). From the screenshot the test checks that
the 3D view draws the query's heatmap (pixels of the heat colour scale, several parts of the
scale) and the map (frontier / ray colours of the map layers), and that the camera view beside
it shows the robot's image. The screenshot is kept (path printed) as a test artefact under
``$RAYFRONTS_ARTEFACTS`` (default ``out/test-artefacts``).

Chromium missing: the test fails under CI (``CI`` set; set-up installs it with the test extra)
and is skipped, saying so, elsewhere.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from tests.support.browser import Chromium, analyse, chromium_exe, good, start_viewer_stack
from tests.support.ports import free_port
from tests.support.processes import ROOT, Proc, stop_all


# ----------------------------------------------------------------------------- the test
@pytest.mark.timeout(420)
def test_web_viewer_draws_map_and_heatmap(tmp_path):
    exe = chromium_exe()
    from query_client.client import Client

    ep = f"tcp/127.0.0.1:{free_port()}"
    grpc, web = free_port(), free_port()
    env = dict(os.environ, RUST_LOG="error", PYTHONUNBUFFERED="1")
    procs = []

    def start(name, args):
        p = Proc(name, args, tmp_path, env=env)
        procs.append(p)
        return p.p, tmp_path / f"{name}.log"

    browser = None
    artefacts = Path(os.environ.get("RAYFRONTS_ARTEFACTS", ROOT / "out" / "test-artefacts"))
    artefacts.mkdir(parents=True, exist_ok=True)
    shot = artefacts / "browser_view.png"
    try:
        url, e, elog = start_viewer_stack(start, ep, grpc, web)
        assert e.wait(240) == 0, elog.read_text()[-3000:]
        with Client(connect=ep, timeout=30.0) as c:
            end = time.monotonic() + 120
            while time.monotonic() < end:
                st = c.stats()
                f = st["frames"]   # every frame mapped or dropped (a busy mapper drops), the map flushed
                if f["received"] == 30 and f["mapped"] >= 5 and f["received"] == f["mapped"] + f["dropped"] \
                        and st.get("flushed_version") == st.get("map_version"):
                    break
                time.sleep(0.5)
            res = c.query("vehicle", top_k=5)
        assert len(res.cluster_xyz) > 0
        time.sleep(2.5)  # a layer publication logs the map to the stream
        browser = Chromium(exe)
        browser.call("Page.navigate", url=url)
        a, png = None, b""
        end = time.monotonic() + 150
        while time.monotonic() < end:
            time.sleep(4)
            png = browser.screenshot()
            a = analyse(png)
            if good(a):
                break
        shot.write_bytes(png)
        print(f"\nbrowser screenshot: {shot}  {a}")
        assert a is not None and good(a), f"screenshot {shot} lacks the map or the heatmap: {a}"
    finally:
        if browser is not None:
            browser.close()
        stop_all(reversed(procs), signal.SIGINT, 60)
