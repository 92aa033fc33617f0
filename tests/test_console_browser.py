"""The console page (``rayfronts console``) in real headless Debian chromium, driven over the
DevTools protocol (tests/support/browser.py): type a query, click Search, the list of found
instances shows the same ids as the API's answer; an image chosen in the file input gives an
image query's answers. The screenshot is kept under ``$RAYFRONTS_ARTEFACTS`` (default
``out/test-artefacts``). Chromium missing: fails under CI, skipped (saying so) elsewhere."""
from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from tests.support.browser import Chromium, chromium_exe
from tests.support.console import VIEWER_URL, http
from tests.support.processes import ROOT


def _wait(browser: Chromium, expr: str, timeout: float, what: str):
    end = time.monotonic() + timeout
    last = None
    while time.monotonic() < end:
        last = browser.evaluate(expr)
        if last:
            return last
        time.sleep(0.3)
    status = browser.evaluate("document.getElementById('status').textContent")
    raise AssertionError(f"{what} not shown after {timeout} s (last {last!r}, status {status!r})")


def _click(browser: Chromium, element_id: str) -> None:
    """A real mouse click at the element's centre."""
    x, y = browser.evaluate(f"(() => {{ const r = document.getElementById('{element_id}').getBoundingClientRect();"
                            " return [r.x + r.width / 2, r.y + r.height / 2]; })()")
    for kind in ("mousePressed", "mouseReleased"):
        browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)


@pytest.mark.timeout(300)
def test_console_page_search_and_image_query(console_world, tmp_path):
    from synthetic_world import World
    from tests.test_console_api import _car_png

    exe = chromium_exe()
    w = console_world
    w.wait_mapped(10)
    artefacts = Path(os.environ.get("RAYFRONTS_ARTEFACTS", ROOT / "out" / "test-artefacts"))
    artefacts.mkdir(parents=True, exist_ok=True)
    shot = artefacts / "console.png"
    img = tmp_path / "car.png"
    img.write_bytes(_car_png(World.generate(0)))
    browser = Chromium(exe)
    try:
        browser.call("Page.enable")
        browser.navigate(w.url("/"))
        _wait(browser, "document.readyState === 'complete' && !!document.getElementById('q')", 30, "the page")
        # the mapper's web viewer embedded beside the panel (--viewer-url)
        src = _wait(browser, "(document.querySelector('#viewer iframe') || {}).src", 30, "the viewer frame")
        assert src == VIEWER_URL, src
        # type the query and click Search
        browser.evaluate("document.getElementById('q').focus()")
        browser.call("Input.insertText", text="vehicle")
        _click(browser, "search")
        rows = _wait(browser, "[...document.querySelectorAll('#instances tr')].map(r => r.cells[0].textContent)",
                     60, "found instances")
        st, api = http(w.url("/api/search?q=vehicle"))
        assert st == 200 and api["found"]
        assert set(rows) & {str(f["id"]) for f in api["found"]}, (rows, api["found"])
        # robots' state from the stats
        robots = _wait(browser, "[...document.querySelectorAll('#robots tr')].map(r => r.cells[1].textContent)",
                       30, "robots")
        assert "r1" in robots
        # an image query through the file input
        doc = browser.call("DOM.getDocument")["root"]["nodeId"]
        node = browser.call("DOM.querySelector", nodeId=doc, selector="#image")["nodeId"]
        browser.call("DOM.setFileInputFiles", files=[str(img)], nodeId=node)
        answers = _wait(browser, "document.querySelectorAll('#answers tr').length", 60, "image query answers")
        assert answers > 0
        assert "<image>" in browser.evaluate("document.getElementById('status').textContent")
        shot.write_bytes(browser.screenshot())
        print(f"\nconsole screenshot: {shot}")
    finally:
        browser.close()
