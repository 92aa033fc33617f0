"""The console page (``rayfronts console``) in real headless Debian chromium, driven over the
DevTools protocol (tests/support/browser.py); one browser for the module.

* On loopback (the shared ``console_world``): type a query, click Search: the page's rows equal
  the API's found list (ids, targets, confidences, centroids, in order, same map version); an
  image chosen in the file input gives an image query's answers.
* Remote, as the README's recipe: a console on every interface with a token and HTTPS
  (certificates from deploy/certs/make_certs.sh), opened as ``https://…/?token=…``: it sets an
  HttpOnly, Secure, SameSite=Lax cookie and redirects to the clean URL; the page and all its
  assets load (no 401 in the browser's network log), a search's rows equal the API's answer
  (fetched with ``Authorization: Bearer`` over TLS verified against the site CA); a wrong or
  missing token gets a one-line 401 and no cookie.

The screenshot is kept under ``$RAYFRONTS_ARTEFACTS`` (default ``out/test-artefacts``).
Chromium missing: fails under CI, skipped (saying so) elsewhere."""
from __future__ import annotations

import http.client as httpc
import os
import ssl
import subprocess
from pathlib import Path

import pytest

from tests.support.browser import Chromium, module_browser
from tests.support.console import VIEWER_URL, assert_rows_equal_api, http, search_in_page, wait_page
from tests.support.ports import free_port
from tests.support.processes import ROOT, Proc, stop_all, wait_for, wait_log

TOKEN = "t0k3n-for-the-browser-test"
COOKIE = "rayfronts_console_token"
_browser = module_browser()


@pytest.fixture(scope="module")
def browser(_browser):
    """One headless chromium for the module's tests, network and console events recorded."""
    for domain in ("Network", "Runtime", "Log"):
        _browser.call(f"{domain}.enable")
    return _browser


@pytest.mark.timeout(300)
def test_console_page_search_and_image_query(console_world, browser, tmp_path):
    from synthetic_world import World
    from tests.test_console_api import _car_png

    w = console_world
    w.wait_frozen()                  # the page's search and the API's see the same map
    artefacts = Path(os.environ.get("RAYFRONTS_ARTEFACTS", ROOT / "out" / "test-artefacts"))
    artefacts.mkdir(parents=True, exist_ok=True)
    shot = artefacts / "console.png"
    img = tmp_path / "car.png"
    img.write_bytes(_car_png(World.generate(0)))
    browser.navigate(w.url("/"))
    wait_page(browser, "document.readyState === 'complete' && !!document.getElementById('q')", 30, "the page")
    # the mapper's web viewer embedded beside the panel (--viewer-url)
    src = wait_page(browser, "(document.querySelector('#viewer iframe') || {}).src", 30, "the viewer frame")
    assert src == VIEWER_URL, src
    rows = search_in_page(browser, "vehicle")
    st, api = http(w.url("/api/search?q=vehicle&threshold=0.5"))
    assert st == 200, api
    assert_rows_equal_api(browser, rows, api)
    # robots' state from the stats
    robots = wait_page(browser, "[...document.querySelectorAll('#robots tr')].map(r => r.cells[1].textContent)",
                   30, "robots")
    assert "r1" in robots
    # an image query through the file input
    doc = browser.call("DOM.getDocument")["root"]["nodeId"]
    node = browser.call("DOM.querySelector", nodeId=doc, selector="#image")["nodeId"]
    browser.call("DOM.setFileInputFiles", files=[str(img)], nodeId=node)
    answers = wait_page(browser, "document.querySelectorAll('#answers tr').length", 60, "image query answers")
    assert answers > 0
    assert "<image>" in browser.evaluate("document.getElementById('status').textContent")
    shot.write_bytes(browser.screenshot())
    print(f"\nconsole screenshot: {shot}")


@pytest.fixture(scope="module")
def tls_console(console_world, tmp_path_factory):
    """A console on every interface with ``--token`` and HTTPS (the site's certificates made by
    deploy/certs/make_certs.sh), in front of the shared mapper: (base URL on 127.0.0.1, an SSL
    context trusting the site CA)."""
    d = tmp_path_factory.mktemp("console-tls")
    r = subprocess.run(["bash", str(ROOT / "deploy" / "certs" / "make_certs.sh"), "-o", str(d / "certs"),
                        "--no-acl", "--host", "localhost", "--ip", "127.0.0.1"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    certs = d / "certs" / "router"
    port = free_port()
    p = Proc("console-tls", ["console", "--connect", console_world.ep, "--http", f"0.0.0.0:{port}",
                             "--token", TOKEN, "--tls-cert", str(certs / "cert.pem"), "--tls-key",
                             str(certs / "key.pem"), "--timeout", "60"], d)
    try:
        wait_log(p.p, d / "console-tls.log", r"console at https://", 120)
        ctx = ssl.create_default_context(cafile=str(certs / "ca.pem"))
        base = f"https://127.0.0.1:{port}"
        wait_for(lambda: http(base + "/api/config", timeout=5, context=ctx)[0] == 401, 60, what="console serving")
        yield base, ctx
    finally:
        stop_all([p])


def _responses(browser: Chromium, base: str) -> dict[str, set[int]]:
    """Path -> statuses of the responses from ``base`` in the browser's network log (no redirects)."""
    got: dict[str, set[int]] = {}
    for ev in list(browser.events):
        if ev["method"] == "Network.responseReceived" and ev["params"]["response"]["url"].startswith(base):
            r = ev["params"]["response"]
            got.setdefault(r["url"].split("?")[0].removeprefix(base), set()).add(r["status"])
    return got


def _raw(base: str, ctx: ssl.SSLContext, path: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    """(status, lower-cased headers, body) of one GET over TLS, no redirect followed."""
    host, port = base.split("//")[1].split(":")
    c = httpc.HTTPSConnection(host, int(port), context=ctx, timeout=30)
    try:
        c.request("GET", path, headers=headers or {})
        r = c.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        c.close()


@pytest.mark.timeout(300)
def test_console_over_https_with_a_token(console_world, tls_console, browser):
    import json

    base, ctx = tls_console
    console_world.wait_frozen()
    bearer = {"Authorization": f"Bearer {TOKEN}"}

    def refused() -> int:
        st, stats = http(base + "/api/stats", headers=bearer, context=ctx)
        assert st == 200, stats
        return stats["console"]["refused"]["token"]

    before = refused()
    # without the browser: no token, a wrong one -> one-line 401 saying what to set, no cookie
    for path in ("/", "/static/console.js", "/?token=wrong", "/api/config"):
        st, hdrs, body = _raw(base, ctx, path)
        err = json.loads(body)["error"]
        assert st == 401 and "set-cookie" not in hdrs and "\n" not in err, (path, st, hdrs, body)
        assert "?token=TOKEN" in err and "Authorization: Bearer TOKEN" in err, err
    st, hdrs, _ = _raw(base, ctx, f"/?token={TOKEN}")
    assert st == 303 and hdrs["location"] == "/", (st, hdrs)
    attrs = {a.strip().lower() for a in hdrs["set-cookie"].split(";")}
    assert {f"{COOKIE}={TOKEN}".lower(), "httponly", "secure", "samesite=lax", "path=/"} <= attrs, attrs
    assert _raw(base, ctx, "/static/console.js", {"Cookie": f"{COOKIE}={TOKEN}"})[0] == 200
    assert _raw(base, ctx, "/static/console.js", {"Cookie": f"{COOKIE}=wrong"})[0] == 401
    assert refused() == before + 5, "every 401 counted"

    # in chromium, as an operator opens the README's URL (the certificate is the site CA's, not the
    # browser's: its errors are ignored, the connection is still TLS)
    browser.call("Security.setIgnoreCertificateErrors", ignore=True)
    browser.events.clear()
    browser.navigate(f"{base}/?token={TOKEN}")
    wait_page(browser, "document.readyState === 'complete' && !!document.getElementById('q')", 30, "the page")
    got = _responses(browser, base)       # the page's script is loaded before 'complete'
    assert got.get("/static/console.js") == {200} and not [p for p, st in got.items() if 401 in st], got
    assert browser.evaluate("location.href") == base + "/", "redirected to the clean URL"
    assert COOKIE not in browser.evaluate("document.cookie"), "the cookie is HttpOnly"
    cookie = next(c for c in browser.call("Network.getCookies", urls=[base + "/"])["cookies"] if c["name"] == COOKIE)
    assert cookie["httpOnly"] and cookie["secure"] and cookie["sameSite"] == "Lax", cookie
    wait_page(browser, "document.querySelectorAll('#robots tr').length", 30, "robots (the page's /api/stats)")
    rows = search_in_page(browser, "vehicle")
    st, api = http(base + "/api/search?q=vehicle&threshold=0.5", headers=bearer, context=ctx)
    assert st == 200, api
    assert_rows_equal_api(browser, rows, api)
    # the network log: every request of the page got through, its script included
    got = _responses(browser, base)
    assert {"/", "/static/console.js", "/api/config", "/api/stats", "/api/search"} <= set(got), got
    assert all(st == {200} for path, st in got.items() if path != "/favicon.ico"), got
    assert got.get("/favicon.ico", {404}) == {404}, got                 # not served: 404, never 401
    logged = [ev["params"] for ev in browser.events if ev["method"] in ("Log.entryAdded", "Runtime.exceptionThrown",
                                                                         "Runtime.consoleAPICalled")]
    assert not [m for m in logged if "401" in json.dumps(m)], logged
    # a wrong token in the browser: refused although the cookie is valid; the cookie is unchanged
    browser.navigate(f"{base}/?token=wrong")
    text = wait_page(browser, "document.readyState === 'complete' && document.body.innerText", 30, "the 401 page")
    assert "missing or wrong token" in text and "?token=TOKEN" in text, text
    after = [c for c in browser.call("Network.getCookies", urls=[base + "/"])["cookies"] if c["name"] == COOKIE]
    assert after == [cookie], after
