"""``rayfronts console`` as the console tests run it: a mapper (router mode) with an edge on
the synthetic world (seed 0) and a console process on a free loopback port; a small HTTP
client (urllib) that returns (status, JSON) and reads server-sent events."""
from __future__ import annotations

import json
import signal
import socket
import ssl
import time
import urllib.error
import urllib.request
from pathlib import Path

from tests.support.ports import free_port
from tests.support.processes import Proc, stop_all, wait_for, wait_log
from tests.support.roles import client, edge_args, mapped, mapper_args

FRAMES = 40
#: what the console embeds as the mapper's web viewer (a real one: tests/test_browser_view.py)
VIEWER_URL = "http://127.0.0.1:9/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9%2Fproxy"
RATE_HZ = 3.0


def http(url: str, *, data: bytes | None = None, headers: dict | None = None, method: str | None = None,
         timeout: float = 60.0, context: ssl.SSLContext | None = None) -> tuple[int, dict | str]:
    """(status, JSON body, or the text when it is not JSON) of one HTTP(S) request (``context``:
    the TLS context of an https URL, e.g. one trusting the site CA)."""
    req = urllib.request.Request(url, data=data, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=timeout, context=context) as r:
            status, body = r.status, r.read()
    except urllib.error.HTTPError as e:
        status, body = e.code, e.read()
    try:
        return status, json.loads(body)
    except ValueError:
        return status, body.decode(errors="replace")


def post_json(url: str, obj, **kw) -> tuple[int, dict | str]:
    return http(url, data=json.dumps(obj).encode(), headers={"Content-Type": "application/json"}, method="POST", **kw)


def multipart(fields: dict[str, tuple[str, bytes, str] | str]) -> tuple[bytes, str]:
    """A multipart/form-data body: ``{name: value}`` or ``{name: (filename, bytes, content type)}``."""
    b = "rf-console-boundary-7d1f"
    out = b""
    for name, v in fields.items():
        if isinstance(v, tuple):
            fn, data, ct = v
            out += (f"--{b}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{fn}\"\r\n"
                    f"Content-Type: {ct}\r\n\r\n").encode() + data + b"\r\n"
        else:
            out += f"--{b}\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n{v}\r\n".encode()
    return out + f"--{b}--\r\n".encode(), f"multipart/form-data; boundary={b}"


def _read_head(s: socket.socket) -> tuple[int, bytes]:
    """(status, what was read after the response head) from a socket that sent a request."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = s.recv(65536)
        if not chunk:
            raise ConnectionError(f"no response head: {buf[:300]!r}")
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), rest


def raw_post(host: str, port: int, path: str, headers: dict[str, str], chunks: list[bytes],
             timeout: float = 60.0) -> tuple[int, dict]:
    """POST ``chunks`` over a raw HTTP/1.1 socket, chunked (``Transfer-Encoding: chunked``)
    unless ``headers`` has a Content-Length; (status, JSON body). Stops sending when the server
    answers or closes early (a refusal before the whole body was read)."""
    chunked = "Content-Length" not in headers
    hdrs = {"Host": f"{host}:{port}", "Connection": "close", **headers}
    if chunked:
        hdrs["Transfer-Encoding"] = "chunked"
    with socket.create_connection((host, port), timeout=timeout) as s:
        s.sendall((f"POST {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in hdrs.items())
                   + "\r\n").encode())
        try:
            for c in chunks:
                s.sendall(f"{len(c):x}\r\n".encode() + c + b"\r\n" if chunked else c)
            if chunked:
                s.sendall(b"0\r\n\r\n")
        except OSError:                      # the server answered and closed before the end
            pass
        status, rest = _read_head(s)
        while True:
            try:
                chunk = s.recv(65536)
            except OSError:
                break
            if not chunk:
                break
            rest += chunk
    body = rest
    if b"\r\n" in rest and not rest.lstrip().startswith(b"{"):   # a chunked reply: one or more chunks
        body, tail = b"", rest
        while tail:
            n, _, tail = tail.partition(b"\r\n")
            if not n.strip() or int(n, 16) == 0:
                break
            body, tail = body + tail[:int(n, 16)], tail[int(n, 16) + 2:]
    return status, json.loads(body)


def matches_openapi(spec: dict, path: str, method: str, reply, status: int = 200) -> None:
    """``reply`` validates against the schema the OpenAPI document gives for ``method path`` and ``status``."""
    from jsonschema import Draft202012Validator

    schema = spec["paths"][path][method]["responses"][str(status)]["content"]["application/json"]["schema"]
    assert "$ref" in schema, (path, method, status, schema)
    errors = list(Draft202012Validator({**schema, "components": spec["components"]}).iter_errors(reply))
    assert not errors, (path, method, status, [e.message for e in errors[:3]])


class EventStream:
    """A server-sent-event stream read over a raw socket (HTTP/1.0: no chunked framing; closing it is an
    immediate disconnect). ``status``: the response's; ``source``: the local address to connect from
    (any 127.x.y.z: another client address on loopback)."""

    def __init__(self, host: str, port: int, path: str, timeout: float = 60.0, source: str | None = None):
        self.s = socket.create_connection((host, port), timeout=timeout,
                                          source_address=(source, 0) if source else None)
        self.s.sendall(f"GET {path} HTTP/1.0\r\nHost: {host}:{port}\r\nAccept: text/event-stream\r\n\r\n".encode())
        self.status, self.buf = _read_head(self.s)

    def error(self) -> dict:
        """The JSON body of a refused stream (read to its end)."""
        while True:
            chunk = self.s.recv(65536)
            if not chunk:
                return json.loads(self.buf)
            self.buf += chunk

    def next(self) -> dict:
        """The next ``update`` event's JSON (keep-alive comments skipped)."""
        while True:
            while b"\n\n" in self.buf:
                block, self.buf = self.buf.split(b"\n\n", 1)
                lines = block.decode().splitlines()
                if any(ln.startswith("event: update") for ln in lines):
                    return json.loads("".join(ln[6:] for ln in lines if ln.startswith("data: ")))
            chunk = self.s.recv(65536)
            if not chunk:
                raise ConnectionError(f"stream closed: {self.buf[:300]!r}")
            self.buf += chunk

    def close(self) -> None:
        self.s.close()


class ConsoleWorld:
    """mapper + edge (``FRAMES`` frames at ``RATE_HZ``) + console, started in ``logdir``."""

    def __init__(self, logdir: Path, pca: Path):
        self.logdir = logdir
        self.ep = f"tcp/127.0.0.1:{free_port()}"
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.procs: list[Proc] = []
        # the world is shared by the session's console tests, which may run many minutes after
        # its edge ended: keep the gone robots listed (no eviction after fleet.gone_evict_s)
        self.mapper = self.start("mapper", mapper_args(self.ep, ["queues.idle_flush_s=0.5", "fleet.gone_evict_s=-1",
                                                                  f"snapshots.dir={logdir / 'snaps'}"]))
        self.pca = pca
        self.edge = self.start("edge", edge_args(self.ep, pca, frames=FRAMES, rate=RATE_HZ))
        self.edges = [self.edge]
        self.console = self.start("console", ["console", "--connect", self.ep, "--http", f"127.0.0.1:{self.port}",
                                              "--timeout", "60", "--viewer-url", VIEWER_URL])
        wait_log(self.console.p, logdir / "console.log", r"console at http://", 120)
        wait_for(lambda: http(self.base + "/api/config", timeout=5)[0] == 200, 60, what="console serving")

    def start(self, name: str, args: list[str]) -> Proc:
        p = Proc(name, args, self.logdir)
        self.procs.append(p)
        return p

    def more_frames(self, robot: str = "r2", frames: int = 8) -> None:
        """A second edge playing ``frames`` more frames (the map changes again)."""
        self.edges.append(self.start(f"edge-{robot}", edge_args(self.ep, self.pca, robot=robot, frames=frames,
                                                                 rate=RATE_HZ)))

    def url(self, path: str) -> str:
        return self.base + path

    def wait_mapped(self, n: int, timeout: float = 180.0) -> None:
        with client(self.ep) as c:
            wait_for(lambda: mapped(c) >= n, timeout, what=f"{n} frames mapped")
            wait_for(lambda: c.stats()["text_warm_up_s"], 120, what="text model warm-up")

    def wait_frozen(self, timeout: float = 180.0) -> None:
        """The edge has sent all its frames and the mapper has integrated and flushed them."""
        for e in self.edges:
            assert e.p.wait(timeout=timeout) == 0, (self.logdir / f"{e.name}.log").read_text()[-2000:]
        with client(self.ep) as c:
            c.wait_settled(timeout=60)

    def close(self) -> None:
        stop_all(reversed(self.procs), signal.SIGINT, 30)


# ------------------------------------------------------------ the page in a browser (tests/support/browser.py)
ROWS = "[...document.querySelectorAll('#instances tr')].map(r => [...r.cells].map(c => c.textContent))"


def wait_page(browser, expr: str, timeout: float, what: str):
    """The truthy value of the JavaScript ``expr`` in the page, polled every 0.3 s up to ``timeout`` s."""
    end = time.monotonic() + timeout
    last = None
    while time.monotonic() < end:
        last = browser.evaluate(expr)
        if last:
            return last
        time.sleep(0.3)
    status = browser.evaluate("(document.getElementById('status') || {}).textContent")
    raise AssertionError(f"{what} not shown after {timeout} s (last {last!r}, status {status!r})")


def click(browser, element_id: str) -> None:
    """A real mouse click at the element's centre."""
    x, y = browser.evaluate(f"(() => {{ const r = document.getElementById('{element_id}').getBoundingClientRect();"
                            " return [r.x + r.width / 2, r.y + r.height / 2]; })()")
    for kind in ("mousePressed", "mouseReleased"):
        browser.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)


def search_in_page(browser, text: str) -> list[list[str]]:
    """Type ``text`` in the query box, click Search; the found-instance rows once shown."""
    browser.evaluate("document.getElementById('instances').replaceChildren()")
    browser.evaluate("document.getElementById('q').value = ''; document.getElementById('q').focus()")
    browser.call("Input.insertText", text=text)
    click(browser, "search")
    return wait_page(browser, ROWS + ".length && " + ROWS, 60, "found instances")


def assert_rows_equal_api(browser, rows: list[list[str]], api: dict, at_least: int = 2) -> None:
    """The page's instance rows are the API's found list: same ids and targets in the same order,
    confidences (3 decimals) and centroids (2 decimals) as shown; the same map version."""
    found = api["found"]
    assert len(found) >= at_least, f"something to check: >= {at_least} instances found, got {found}"
    assert [r[0] for r in rows] == [str(f["id"]) for f in found], (rows, found)
    assert [r[1] for r in rows] == [f["target"] for f in found], (rows, found)
    for r, f in zip(rows, found, strict=True):
        assert abs(float(r[2]) - f["confidence"]) <= 5e-4 + 1e-9, (r, f)
        shown = [float(x) for x in r[3].split(",")]
        assert len(shown) == 3, (r, f)
        assert all(abs(a - b) <= 5e-3 + 1e-9 for a, b in zip(shown, f["centroid"], strict=True)), (r, f)
    status = browser.evaluate("document.getElementById('status').textContent")
    assert status.startswith(f"map v{api['map_version']},") and f"{len(found)} found" in status, (status, api)
