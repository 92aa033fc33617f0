"""The mapper's rerun web viewer (``rayfronts mapper --serve-web``) in headless Debian chromium,
embedded in the console page (``rayfronts console --viewer-url``) and on its own page; one set of
processes and one browser for the module.

Real processes on loopback: a router, the mapper with ``--serve-web``, an edge playing the
synthetic world (30 frames, all mapped or dropped and flushed before the tests), and the console
started with ``--viewer-url`` set to the viewer URL the mapper prints. The pages (rerun's own web
viewer, served locally: no internet) are driven over the DevTools protocol (a stdlib WebSocket
client in tests/support/browser.py, no extra package).

1. The console, as an operator uses it (first: its control needs a map no query was made on):
   type a target in the query box and press Enter (a search: the page's rows equal the API's
   found list); the embedded frame draws the map but not the heat colour scale (the control);
   click Query: the frame (``getBoundingClientRect`` of the iframe, cropped from the page's
   screenshot) shows the heat colour scale (:data:`mapper.outputs.rerun_view.HEAT_LUT`, several
   parts of it) and the map layers; then an image chosen in the file input: the image query's
   answers are listed and its heatmap drawn.
2. The viewer's own page after a query made with ``query_client.Client``: the 3D view draws the
   heatmap and the map (frontier / ray colours of the map layers), and the camera view beside it
   shows the robot's image.

The screenshots are kept (paths printed) under ``$RAYFRONTS_ARTEFACTS`` (default
``out/test-artefacts``). Chromium missing: the tests fail under CI (``CI`` set; set-up installs it
with the test extra) and are skipped, saying so, elsewhere.
"""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.support.browser import Chromium, analyse, decode_png, good, heat_shown, module_browser, start_viewer_stack
from tests.support.console import ROWS, assert_rows_equal_api, http
from tests.support.console import click as _click
from tests.support.console import wait_page as _wait
from tests.support.ports import free_port
from tests.support.processes import ROOT, Proc, proc_env, stop_all, wait_log
from tests.support.roles import client

TARGET = "car"
WIDTH, HEIGHT = 1800, 1000   # console test's window (CSS px = screenshot px): the frame is WIDTH - 430 px wide
VIEWER_SIZE = (1400, 900)    # the viewer page's test
ARTEFACTS = Path(os.environ.get("RAYFRONTS_ARTEFACTS", ROOT / "out" / "test-artefacts"))
browser = module_browser(WIDTH, HEIGHT)    # one chromium for the module


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """Router, mapper serving the web viewer, the edge's 30 frames mapped (>= 5) or dropped and
    flushed, a console embedding the viewer: ``ep``, ``viewer`` (URL), ``base`` (console URL)."""
    d = tmp_path_factory.mktemp("viewer")
    ep = f"tcp/127.0.0.1:{free_port()}"
    grpc, web, port = free_port(), free_port(), free_port()
    env = {**proc_env(), "RUST_LOG": "error", "PYTHONUNBUFFERED": "1"}
    procs: list[Proc] = []

    def start(name: str, args: list[str]) -> tuple:
        p = Proc(name, args, d, env=env)
        procs.append(p)
        return p.p, d / f"{name}.log"

    try:
        viewer, e, elog = start_viewer_stack(start, ep, grpc, web)
        c, clog = start("console", ["console", "--connect", ep, "--http", f"127.0.0.1:{port}", "--timeout", "60",
                                    "--viewer-url", viewer])
        base = wait_log(c, clog, r"console at (http://\S+)", 120).group(1).rstrip("/")
        assert e.wait(240) == 0, elog.read_text()[-3000:]
        with client(ep) as cl:
            cl.wait_settled(mapped=5, received=30, timeout=120)   # a busy mapper drops some of the 30
        yield SimpleNamespace(ep=ep, viewer=viewer, base=base)
    finally:
        stop_all(reversed(procs), signal.SIGINT, 60)


def _frame_rect(browser: Chromium) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the embedded viewer frame in the page, in screenshot pixels."""
    r = browser.evaluate("(() => { const r = document.querySelector('#viewer iframe').getBoundingClientRect();"
                         " return [r.left, r.top, r.right, r.bottom]; })()")
    return tuple(int(round(v)) for v in r)


def _frame_shows(browser: Chromium, timeout: float, heat: bool = True) -> tuple[dict, bytes]:
    """(analysis of the frame's crop, page PNG) once the frame shows the map (and the heatmap
    when ``heat``), or the last ones after ``timeout`` s."""
    a, png = {}, b""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        png = browser.screenshot()
        x0, y0, x1, y1 = _frame_rect(browser)
        img = decode_png(png)
        assert img.shape[:2] == (HEIGHT, WIDTH), img.shape
        a = analyse(img[y0:y1, x0:x1])
        a["frame"] = [x0, y0, x1, y1]
        if (heat_shown(a) or not heat) and a["map_px"] >= 20:
            break
        time.sleep(0.5)
    return a, png


@pytest.mark.timeout(300)
def test_console_embeds_the_live_viewer(stack, browser, tmp_path):
    from synthetic_world import World
    from tests.test_console_api import _car_png

    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    shot, shot_img = ARTEFACTS / "console_viewer.png", ARTEFACTS / "console_viewer_image.png"
    img_file = tmp_path / "car.png"
    img_file.write_bytes(_car_png(World.generate(0)))
    browser.navigate(stack.base + "/")
    _wait(browser, "document.readyState === 'complete' && !!document.getElementById('q')", 30, "the page")
    src = _wait(browser, "(document.querySelector('#viewer iframe') || {}).src", 30, "the viewer frame")
    assert src == stack.viewer, (src, stack.viewer)
    # type the target, press Enter: a search, its instances listed
    browser.evaluate("document.getElementById('q').focus()")
    browser.call("Input.insertText", text=TARGET)
    for kind in ("rawKeyDown", "char", "keyUp"):
        browser.call("Input.dispatchKeyEvent", type=kind, key="Enter", code="Enter", windowsVirtualKeyCode=13,
                     **({"text": "\r"} if kind == "char" else {}))
    rows = _wait(browser, ROWS + ".length && " + ROWS, 90, "found instances")
    st, api = http(f"{stack.base}/api/search?q={TARGET}&threshold=0.5")
    assert st == 200, api
    assert_rows_equal_api(browser, rows, api, at_least=1)
    # control: before any query the frame draws the map (waited for) but not the heat colour scale
    before, _ = _frame_shows(browser, 30, heat=False)
    print(f"\nbefore the query: {before}")
    assert before["map_px"] >= 20, f"the frame does not draw the map: {before}"
    assert not heat_shown(before), f"heat colours in the frame before any query: {before}"
    # click Query: the mapper logs the query's heatmap to the viewer's stream
    _click(browser, "query")
    _wait(browser, f"document.getElementById('status').textContent.startsWith('query \"{TARGET}\"')"
                   " && document.querySelectorAll('#answers tr').length", 60, "query answers")
    a, png = _frame_shows(browser, 90)
    shot.write_bytes(png)
    print(f"\nconsole + viewer screenshot: {shot}  {a}")
    assert heat_shown(a) and a["map_px"] >= 20, f"the embedded viewer in {shot} lacks the heatmap or map: {a}"
    # an image query through the file input
    doc = browser.call("DOM.getDocument")["root"]["nodeId"]
    node = browser.call("DOM.querySelector", nodeId=doc, selector="#image")["nodeId"]
    browser.call("DOM.setFileInputFiles", files=[str(img_file)], nodeId=node)
    _wait(browser, "document.getElementById('status').textContent.includes('<image>')"
                   " && document.querySelectorAll('#answers tr').length", 60, "image query answers")
    a_img, png = _frame_shows(browser, 30)
    shot_img.write_bytes(png)
    print(f"console + viewer after the image query: {shot_img}  {a_img}")
    assert heat_shown(a_img), f"the embedded viewer in {shot_img} lacks the image query's heatmap: {a_img}"


@pytest.mark.timeout(300)
def test_web_viewer_draws_map_and_heatmap(stack, browser):
    from query_client.client import Client

    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    shot = ARTEFACTS / "browser_view.png"
    with Client(connect=stack.ep, timeout=30.0) as c:
        res = c.query("vehicle", top_k=5)
    assert len(res.cluster_xyz) > 0
    w, h = VIEWER_SIZE
    browser.call("Emulation.setDeviceMetricsOverride", width=w, height=h, deviceScaleFactor=1, mobile=False)
    try:
        browser.navigate(stack.viewer)
        _wait(browser, "document.readyState === 'complete'", 30, "the viewer page")
        a, png = None, b""
        end = time.monotonic() + 150
        while time.monotonic() < end:   # until the stream shows the map layers, the heatmap and the camera
            time.sleep(1)
            try:
                png = browser.screenshot()
            except RuntimeError as err:     # the page is being replaced (navigation still committing)
                print(f"screenshot: {err}")
                continue
            a = analyse(png)
            if good(a):
                break
        shot.write_bytes(png)
        print(f"\nbrowser screenshot: {shot}  {a}")
        assert decode_png(png).shape[:2] == (h, w)
        assert a is not None and good(a), f"screenshot {shot} lacks the map or the heatmap: {a}"
    finally:
        browser.call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1,
                     mobile=False)
