"""Headless Debian chromium driven over the DevTools protocol with a stdlib WebSocket client
(no extra package): the browser tests (tests/test_browser_view.py, tests/test_console_browser.py),
and what a screenshot of the mapper's rerun web viewer shows
(:func:`analyse`, :func:`good`)."""
from __future__ import annotations

import base64
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections import deque

import numpy as np
import pytest

from tests.support.processes import stop_process, wait_log


class WS:
    def __init__(self, url, timeout=30):
        m = re.match(r"ws://([^:/]+):(\d+)(/.*)", url)
        host, port, path = m.group(1), int(m.group(2)), m.group(3)
        self.s = socket.create_connection((host, port), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall((f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        buf = b""
        while b"\r\n\r\n" not in buf:
            buf += self.s.recv(4096)
        head, self.rest = buf.split(b"\r\n\r\n", 1)
        assert b" 101 " in head.split(b"\r\n")[0], head

    def _recv(self, n):
        while len(self.rest) < n:
            chunk = self.s.recv(1 << 20)
            if not chunk:
                raise ConnectionError("websocket closed")
            self.rest += chunk
        out, self.rest = self.rest[:n], self.rest[n:]
        return out

    def send(self, text):
        data = text.encode()
        hdr = bytes([0x81])
        n = len(data)
        if n < 126:
            hdr += bytes([0x80 | n])
        elif n < 65536:
            hdr += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            hdr += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        self.s.sendall(hdr + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def recv(self):
        msg = b""
        while True:
            b0, b1 = self._recv(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._recv(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._recv(8))[0]
            payload = self._recv(n)
            op = b0 & 0x0F
            if op == 0x8:
                raise ConnectionError("websocket closed by the browser")
            if op in (0x9, 0xA):
                continue
            msg += payload
            if b0 & 0x80:
                return msg.decode()


class Chromium:
    FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync"]

    def __init__(self, exe, width=1400, height=900):
        self.ud = tempfile.mkdtemp(prefix="rf-chromium-")
        self.p = subprocess.Popen([exe, *self.FLAGS, f"--user-data-dir={self.ud}", "--remote-debugging-port=0",
                                   f"--window-size={width},{height}", "about:blank"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        port = None
        end = time.monotonic() + 60
        while time.monotonic() < end:
            line = self.p.stderr.readline()
            m = re.search(r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", line or "")
            if m:
                port = int(m.group(1))
                break
            if not line and self.p.poll() is not None:
                raise RuntimeError("chromium exited at start")
        assert port, "chromium did not print its DevTools address"
        threading.Thread(target=lambda: [None for _ in self.p.stderr], daemon=True).start()
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        page = next(t for t in pages if t.get("type") == "page")
        self.ws = WS(page["webSocketDebuggerUrl"])
        self._id = 0
        #: DevTools events received so far (``{"method", "params"}``; e.g. ``Network.responseReceived``
        #: once ``Network.enable`` was called), the newest 20000
        self.events: deque = deque(maxlen=20000)
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def call(self, method, **params):
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            m = json.loads(self.ws.recv())
            if "method" in m and "id" not in m:
                self.events.append(m)
            if m.get("id") == self._id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def evaluate(self, expr: str):
        """The value of the JavaScript expression ``expr`` in the page (promises awaited)."""
        r = self.call("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expr[:80]}: {r['exceptionDetails'].get('text')}")
        return r.get("result", {}).get("value")

    def navigate(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def close(self):
        stop_process(self.p, signal.SIGTERM, 10)


def module_browser(width: int = 1400, height: int = 900):
    """A module-scoped pytest fixture: one headless chromium (``width`` x ``height`` CSS px) for
    the module's tests, Page events on; assign it to a module-level name (``browser = module_browser()``)."""
    @pytest.fixture(scope="module")
    def browser():
        b = Chromium(chromium_exe(), width=width, height=height)
        try:
            b.call("Page.enable")
            yield b
        finally:
            b.close()

    return browser


def chromium_exe() -> str:
    """Debian's chromium: a failure under CI (set-up installs it), a visible skip elsewhere."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe:
        return exe
    if os.environ.get("CI"):
        pytest.fail("chromium is not installed: deploy/setup_dev.sh installs Debian's chromium with the test extra")
    pytest.skip("chromium is not installed here (apt-get install chromium); under CI this test fails instead")


# ------------------------------------------------------------ what a rerun web viewer screenshot shows
def decode_png(png: bytes) -> np.ndarray:
    """An RGB uint8 image (H, W, 3) from PNG bytes."""
    import cv2

    return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _near(img: np.ndarray, colours: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(mask of pixels within ``tol`` of one of ``colours``, index of the nearest colour)."""
    px = img.reshape(-1, 3).astype(np.float32)
    d = ((px[:, None, :] - colours[None].astype(np.float32)) ** 2).sum(-1)
    idx = d.argmin(1)
    return (d[np.arange(len(px)), idx] <= tol * tol).reshape(img.shape[:2]), idx.reshape(img.shape[:2])


def analyse(shot: bytes | np.ndarray) -> dict:
    """What the viewer shows in ``shot`` (PNG bytes or an RGB array cropped to the viewer; layout:
    blueprint panel left, 3D view, right column): heat-colour-scale pixels
    (:data:`mapper.outputs.rerun_view.HEAT_LUT`) in the 3D view and in which quarters of the scale,
    map-layer pixels, the spread of the camera view's colours."""
    from mapper.outputs.rerun_view import HEAT_LUT

    img = decode_png(shot) if isinstance(shot, bytes) else shot
    h, w = img.shape[:2]
    view = img[int(0.08 * h):int(0.92 * h), int(0.2 * w):int(0.72 * w)]
    lut = HEAT_LUT[::4]
    mask, idx = _near(view, lut, tol=30.0)
    quarters = np.bincount((idx[mask] * 4 // len(lut)).ravel(), minlength=4)
    map_cols = np.array([[0, 220, 160], [0, 200, 255]], np.uint8)  # frontiers, rays (mapper/outputs/rerun.py)
    mmask, _ = _near(view, map_cols, tol=40.0)
    cam = img[int(0.55 * h):int(0.95 * h), int(0.8 * w):]
    return {"heat_px": int(mask.sum()), "heat_quarters": [int(q) for q in quarters], "map_px": int(mmask.sum()),
            "view_px": int(view.shape[0] * view.shape[1]), "camera_std": float(cam.reshape(-1, 3).std(0).mean())}


def heat_shown(a: dict) -> bool:
    """The query's heatmap is drawn: >= 1 % of the 3D view in the heat scale, >= 2 quarters of it."""
    return a["heat_px"] >= 0.01 * a["view_px"] and sum(q >= 30 for q in a["heat_quarters"]) >= 2


def good(a: dict) -> bool:
    """Heatmap, map layers and the camera image all shown."""
    return heat_shown(a) and a["map_px"] >= 20 and a["camera_std"] > 8.0


def start_viewer_stack(start, ep: str, grpc_port: int, web_port: int) -> tuple[str, subprocess.Popen, object]:
    """Router on ``ep``, a mapper serving rerun's web viewer (``grpc_port``, ``web_port``) and an
    edge sending 30 label-encoded synthetic frames (started once the mapper answers, not awaited). ``start(name, argv)``
    launches one ``rayfronts`` process and returns ``(Popen, log path)``. Returns the viewer's
    URL, the edge's Popen and its log path."""
    r, rlog = start("router", ["router", "--listen", ep])
    wait_log(r, rlog, "listening on", 60)
    m, mlog = start("mapper", ["mapper", "--mode", "client", "--connect", ep, "--serve-web", "--grpc-port",
                               str(grpc_port), "--web-port", str(web_port), "map.vox_size=0.5", "map.depth_limit=20",
                               "layers.rate_hz=1", "snapshots.on_exit=false"])
    url = wait_log(m, mlog, r"web viewer at (http://127\.0\.0\.1:\d+/\?url=\S+)", 120).group(1)
    wait_log(m, mlog, "mapper up", 120)
    # the edge starts once the mapper answers through the router: a label edge publishes within a
    # second, and frames sent before the mapper's subscriber is routed are not received (a camera
    # stream, not a queue); the tests count all 30
    from common.zenoh_session import ZenohConfig
    from query_client import Client
    from tests.support.processes import wait_for
    with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=30.0) as c:
        wait_for(lambda: c.stats(timeout=5.0), 120, every=0.5, what="mapper answers through the router")
    e, elog = start("edge", ["edge", "--connect", ep, "--rate", "0", "robot=r1", "source.kind=synthetic",
                             "source.n_frames=30", "source.resolution=120x160", "source.depth_limit=20",
                             "encoder.kind=label", "pca.out_dim=32", "pca.fit_frames=4",
                             "publish.lossless=true"])   # the tests count all 30: no frame replaced at the edge
    return url, e, elog
