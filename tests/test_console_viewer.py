"""The console page (``rayfronts console``) with the mapper's real rerun web viewer embedded, in
headless Debian chromium driven over the DevTools protocol (tests/support/browser.py).

Real processes on loopback, as tests/test_browser_view.py: a router, the mapper with
``--serve-web``, an edge playing the synthetic world, and the console started with
``--viewer-url`` set to the viewer URL the mapper prints. In the browser, as an operator does:
type a target in the query box and press Enter (a search: the found instances are listed, the
same ids as the console API's answer), click Query (the mapper draws the query's heatmap in its
viewer), then choose an image in the file input (an image query's answers are listed). The
page's screenshot is cropped to the embedded frame (``getBoundingClientRect`` of the iframe)
and must show the heat colour scale (:data:`mapper.outputs.rerun_view.HEAT_LUT`, several parts
of it) and the map layers after the query, and not the heat scale before it (the control);
after the image query, the image query's heatmap. The screenshots are kept (paths printed)
under ``$RAYFRONTS_ARTEFACTS`` (default ``out/test-artefacts``).

Chromium missing: the test fails under CI (``CI`` set) and is skipped, saying so, elsewhere.
"""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from tests.support.browser import Chromium, analyse, chromium_exe, decode_png, heat_shown, start_viewer_stack
from tests.support.console import http
from tests.support.ports import free_port
from tests.support.processes import ROOT, Proc, proc_env, stop_all, wait_for, wait_log
from tests.support.roles import client
from tests.test_console_browser import _click, _wait

TARGET = "car"
WIDTH, HEIGHT = 1800, 1000   # browser window (CSS px = screenshot px): the frame is WIDTH - 430 px wide


def _frame_rect(browser: Chromium) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the embedded viewer frame in the page, in screenshot pixels."""
    r = browser.evaluate("(() => { const r = document.querySelector('#viewer iframe').getBoundingClientRect();"
                         " return [r.left, r.top, r.right, r.bottom]; })()")
    return tuple(int(round(v)) for v in r)


def _viewer_shows_heat(browser: Chromium, timeout: float) -> tuple[dict, bytes]:
    """(analysis of the frame's crop, page PNG) once the frame shows the heatmap and the map, or
    the last ones after ``timeout`` s."""
    a, png = {}, b""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        png = browser.screenshot()
        x0, y0, x1, y1 = _frame_rect(browser)
        img = decode_png(png)
        assert img.shape[:2] == (HEIGHT, WIDTH), img.shape
        a = analyse(img[y0:y1, x0:x1])
        a["frame"] = [x0, y0, x1, y1]
        if heat_shown(a) and a["map_px"] >= 20:
            break
        time.sleep(2)
    return a, png


@pytest.mark.timeout(300)
def test_console_embeds_the_live_viewer(tmp_path):
    from synthetic_world import World
    from tests.test_console_api import _car_png

    exe = chromium_exe()
    ep = f"tcp/127.0.0.1:{free_port()}"
    grpc, web, port = free_port(), free_port(), free_port()
    env = {**proc_env(), "PYTHONUNBUFFERED": "1"}
    procs: list[Proc] = []

    def start(name: str, args: list[str]) -> tuple:
        p = Proc(name, args, tmp_path, env=env)
        procs.append(p)
        return p.p, tmp_path / f"{name}.log"

    artefacts = Path(os.environ.get("RAYFRONTS_ARTEFACTS", ROOT / "out" / "test-artefacts"))
    artefacts.mkdir(parents=True, exist_ok=True)
    shot, shot_img = artefacts / "console_viewer.png", artefacts / "console_viewer_image.png"
    img_file = tmp_path / "car.png"
    img_file.write_bytes(_car_png(World.generate(0)))
    browser = None
    try:
        viewer, e, elog = start_viewer_stack(start, ep, grpc, web)
        c, clog = start("console", ["console", "--connect", ep, "--http", f"127.0.0.1:{port}", "--timeout", "60",
                                    "--viewer-url", viewer])
        base = wait_log(c, clog, r"console at (http://\S+)", 120).group(1).rstrip("/")
        assert e.wait(240) == 0, elog.read_text()[-3000:]

        with client(ep) as cl:
            last: list[dict] = [{}]

            def settled() -> bool:
                s = last[0] = cl.stats(timeout=5.0)
                f = s["frames"]   # every frame mapped or dropped (a busy mapper drops), the map flushed
                return (f["received"] == 30 and f["mapped"] >= 5 and f["received"] == f["mapped"] + f["dropped"]
                        + f["rejected_total"] and s.get("flushed_version") == s.get("map_version"))

            try:
                wait_for(settled, 120, what="the 30 frames mapped (>= 5) or dropped, the map flushed")
            except AssertionError as err:
                s = last[0]
                raise AssertionError(f"{err}: frames {s.get('frames')}, map version {s.get('map_version')}, "
                                     f"flushed {s.get('flushed_version')}") from None

        browser = Chromium(exe, width=WIDTH, height=HEIGHT)
        browser.call("Page.enable")
        browser.navigate(base + "/")
        _wait(browser, "document.readyState === 'complete' && !!document.getElementById('q')", 30, "the page")
        src = _wait(browser, "(document.querySelector('#viewer iframe') || {}).src", 30, "the viewer frame")
        assert src == viewer, (src, viewer)
        # type the target, press Enter: a search, its instances listed
        browser.evaluate("document.getElementById('q').focus()")
        browser.call("Input.insertText", text=TARGET)
        for kind in ("rawKeyDown", "char", "keyUp"):
            browser.call("Input.dispatchKeyEvent", type=kind, key="Enter", code="Enter", windowsVirtualKeyCode=13,
                         **({"text": "\r"} if kind == "char" else {}))
        ids = _wait(browser, "[...document.querySelectorAll('#instances tr')].map(r => r.cells[0].textContent)",
                    90, "found instances")
        st, api = http(f"{base}/api/search?" + browser.evaluate("searchParams().toString()"))  # the page's request
        assert st == 200 and api["found"], api
        assert ids == [str(f["id"]) for f in api["found"]], (ids, api["found"])   # every row, in order
        # control: before any query the frame shows the map but not the heat colour scale
        time.sleep(3)
        x0, y0, x1, y1 = _frame_rect(browser)
        before = analyse(decode_png(browser.screenshot())[y0:y1, x0:x1])
        print(f"\nbefore the query: {before}")
        assert not heat_shown(before), f"heat colours in the frame before any query: {before}"
        # click Query: the mapper logs the query's heatmap to the viewer's stream
        _click(browser, "query")
        _wait(browser, f"document.getElementById('status').textContent.startsWith('query \"{TARGET}\"')"
                       " && document.querySelectorAll('#answers tr').length", 60, "query answers")
        a, png = _viewer_shows_heat(browser, 90)
        shot.write_bytes(png)
        print(f"\nconsole + viewer screenshot: {shot}  {a}")
        assert heat_shown(a) and a["map_px"] >= 20, f"the embedded viewer in {shot} lacks the heatmap or map: {a}"
        # an image query through the file input
        doc = browser.call("DOM.getDocument")["root"]["nodeId"]
        node = browser.call("DOM.querySelector", nodeId=doc, selector="#image")["nodeId"]
        browser.call("DOM.setFileInputFiles", files=[str(img_file)], nodeId=node)
        _wait(browser, "document.getElementById('status').textContent.includes('<image>')"
                       " && document.querySelectorAll('#answers tr').length", 60, "image query answers")
        a_img, png = _viewer_shows_heat(browser, 30)
        shot_img.write_bytes(png)
        print(f"console + viewer after the image query: {shot_img}  {a_img}")
        assert heat_shown(a_img), f"the embedded viewer in {shot_img} lacks the image query's heatmap: {a_img}"
    finally:
        if browser is not None:
            browser.close()
        stop_all(reversed(procs), signal.SIGINT, 60)
