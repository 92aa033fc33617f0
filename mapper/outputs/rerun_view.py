"""The operator's rerun view: blueprint, heat colour scale, label thinning, cone outlines, and
the loopback-bound rerun server (gRPC + web viewer) the mapper streams to.

Layout (sent with the recording, to the file and to the live stream)::

    +------------------------------------------+---------------------------+
    | 3D: world (map voxels, frontiers, rays,  | query legend (text)       |
    |     robots) + the SELECTED query:        | colour scale (image)      |
    |     heat, clusters, best rays, cones     | camera <robot>: rgb/depth |
    +------------------------------------------+---------------------------+

* One entity tree per query: ``world/queries/<q>/{heat,clusters,rays,search_volume}`` and
  ``scale/<q>/{legend,colour_scale}``. The selected query is the latest one asked (a new
  query text re-sends the blueprint); the other queries' trees stay in the blueprint panel,
  hidden (``EntityBehavior(visible=False)``), one click to show. So the heatmaps, which all
  colour the same voxels, never sit on top of each other.
* Heat: every voxel coloured by its score with :data:`HEAT_LUT` (dark blue → magenta → red →
  yellow), min-max over the map; the legend states the score range, and the colour-scale
  image shows the LUT with the low and high scores written at its ends. Heat points are
  drawn 10 % larger than the map's voxels so they cover them instead of z-fighting.
* Labels: only the best clusters whose centres are at least ``min_sep`` apart (in score
  order) are labelled (rank and score), and only the best ray; labels no longer pile up.
* Search volume: the cones of the best rays (half-angle as the map's, cut at the search
  range) as wire outlines: generator lines and rings.

Listen addresses: rerun's in-process servers bind every interface and take no address, so
the mapper runs rerun's own server binary (``rerun --serve-grpc|--serve-web --bind ADDR``,
shipped in the rerun-sdk wheel; web viewer assets bundled, no internet needed) as a child
process bound to ``rerun.bind`` (default 127.0.0.1), and streams to it with
``connect_grpc``. The child dies with the mapper (``PR_SET_PDEATHSIG``) and is stopped on close.
"""
from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import numpy as np
import numpy.typing as npt

from common import rerun_paths as paths

if TYPE_CHECKING:
    import rerun.blueprint

log = logging.getLogger("rayfronts.mapper.rerun")


def _lut() -> np.ndarray:
    """256×3 uint8: dark blue → magenta → red → yellow (none of them a typical scene colour)."""
    knots = np.array([[20, 20, 160], [170, 30, 200], [235, 40, 60], [255, 230, 40]], np.float32)
    t = np.linspace(0, len(knots) - 1, 256)
    i = np.minimum(t.astype(int), len(knots) - 2)
    f = (t - i)[:, None]
    return np.round(knots[i] * (1 - f) + knots[i + 1] * f).astype(np.uint8)


HEAT_LUT = _lut()


def heat_colors(scores: npt.ArrayLike) -> tuple[np.ndarray, float, float]:
    """(N×3 uint8 colours, low, high) of ``scores``, min-max normalised onto :data:`HEAT_LUT`."""
    s = np.asarray(scores, np.float32).reshape(-1)
    if s.size == 0:
        return np.zeros((0, 3), np.uint8), 0.0, 0.0
    fin = np.isfinite(s)
    lo = float(s[fin].min()) if fin.any() else 0.0
    hi = float(s[fin].max()) if fin.any() else 0.0
    t = (np.where(fin, s, lo) - lo) / (hi - lo) if hi > lo else np.ones_like(s)
    return HEAT_LUT[np.clip(np.round(t * 255), 0, 255).astype(np.int64)], lo, hi


def colour_scale_image(lo: float, hi: float, width: int = 320, height: int = 56) -> np.ndarray:
    """RGB image of the LUT (left = low score) with the low/high scores written below it."""
    import cv2

    img = np.full((height, width, 3), 255, np.uint8)
    bar = HEAT_LUT[np.linspace(0, 255, width).astype(int)]
    img[: height // 2] = bar[None]
    font, sc = cv2.FONT_HERSHEY_SIMPLEX, 0.45
    cv2.putText(img, f"{lo:.3f}", (2, height - 8), font, sc, (0, 0, 0), 1, cv2.LINE_AA)
    txt = f"{hi:.3f}"
    (tw, _), _ = cv2.getTextSize(txt, font, sc, 1)
    cv2.putText(img, txt, (width - tw - 2, height - 8), font, sc, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def thin_labels(xyz: npt.ArrayLike, scores: npt.ArrayLike, min_sep: float, max_labels: int = 5) -> list[int]:
    """Indices (score order, best first) of the points to label: each at least ``min_sep``
    from every point already labelled, at most ``max_labels``."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    keep: list[int] = []
    for i in order:
        if len(keep) >= max_labels:
            break
        if all(np.linalg.norm(xyz[i] - xyz[j]) >= min_sep for j in keep):
            keep.append(int(i))
    return keep


def cone_outlines(origins: npt.ArrayLike, dirs: npt.ArrayLike, half_angle_deg: float, length: float,
                  n_lines: int = 8, rings: Sequence[float] = (0.25, 0.5, 1.0),
                  ring_pts: int = 24) -> list[np.ndarray]:
    """Line strips outlining each cone (apex ``o``, axis ``d``, half-angle, cut at ``length``)."""
    th = math.radians(min(max(float(half_angle_deg), 0.1), 89.0))
    strips: list[np.ndarray] = []
    for o, d in zip(np.asarray(origins, np.float64).reshape(-1, 3), np.asarray(dirs, np.float64).reshape(-1, 3),
                    strict=False):
        n = np.linalg.norm(d)
        if not np.isfinite(n) or n == 0:
            continue
        d = d / n
        a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(d, a)
        u /= np.linalg.norm(u)
        v = np.cross(d, u)
        r = math.tan(th)
        for k in range(n_lines):
            phi = 2 * math.pi * k / n_lines
            tip = o + length * (d + r * (math.cos(phi) * u + math.sin(phi) * v))
            strips.append(np.stack([o, tip]).astype(np.float32))
        ang = np.linspace(0, 2 * math.pi, ring_pts + 1)
        for f in rings:
            c = o + f * length * d
            ring = c + f * length * r * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v)
            strips.append(ring.astype(np.float32))
    return strips


def build_blueprint(selected: str | None, queries: Iterable[str], robots: Sequence[str],
                    eye: tuple[list, list] | None = None) -> rerun.blueprint.Blueprint:
    """The operator blueprint: 3D map + ``selected`` query (others hidden), legend, colour
    scale and one camera view per robot."""
    import rerun.blueprint as rrb

    overrides: dict[Any, rrb.EntityBehavior]          # rerun's key type: EntityPath | str
    overrides = {paths.QUERIES(q): rrb.EntityBehavior(visible=False) for q in queries if q != selected}
    kw: dict[str, Any] = {}
    if eye is not None:
        pos, target = eye
        kw["eye_controls"] = rrb.EyeControls3D(position=pos, look_target=target, eye_up=[0.0, 0.0, 1.0])
    title = f"map + query '{selected}'" if selected else "map"
    view3d = rrb.Spatial3DView(name=title, origin=paths.WORLD, contents=[f"+ {paths.WORLD}/**"], overrides=overrides,
                               **kw)
    side: list[rrb.View] = []
    if selected:
        side.append(rrb.TextDocumentView(name="query", origin=f"{paths.SCALE(selected)}/legend"))
        side.append(rrb.Spatial2DView(name="colour scale", origin=f"{paths.SCALE(selected)}/colour_scale"))
    for r in robots:
        side.append(rrb.Spatial2DView(name=f"camera {r}", origin=paths.ROBOTS(r, paths.IMAGE),
                                      contents=["+ $origin/rgb", "+ $origin/depth"]))
    layout: rrb.View | rrb.Container
    if not side:
        layout = view3d
    else:
        shares = ([2, 1] if selected else []) + [3] * len(robots)
        layout = rrb.Horizontal(view3d, rrb.Vertical(*side, row_shares=shares), column_shares=[3, 1])
    return rrb.Blueprint(layout, rrb.BlueprintPanel(state="expanded"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed"), auto_views=False)


def eye_for(xyz: npt.ArrayLike) -> tuple[list, list] | None:
    """A camera looking down at the map from its south-west, far enough to see all of it."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(xyz) == 0:
        return None
    lo, hi = np.percentile(xyz, 2, axis=0), np.percentile(xyz, 98, axis=0)
    c = (lo + hi) / 2
    r = max(float(np.linalg.norm(hi - lo)) / 2, 5.0)
    pos = c + r * np.array([-1.2, -1.2, 1.1])
    return [float(v) for v in pos], [float(v) for v in c]


# ---------------------------------------------------------------------- the rerun server
def _free(host: str, port: int) -> bool:
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
            return True
        except OSError:
            return False


def rerun_binary() -> str:
    """The ``rerun`` executable shipped in the rerun-sdk wheel (``rerun_cli/rerun``; not the
    Python wrapper script, which would leave the real server behind when stopped)."""
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        cand = Path(spec.origin).with_name("rerun")
        if cand.is_file() and os.access(cand, os.X_OK):
            return str(cand)
    found = shutil.which("rerun")
    if not found:
        raise FileNotFoundError("the rerun executable (from the rerun-sdk package) was not found")
    return found


def _pdeathsig():  # the server dies with the mapper, even on SIGKILL
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


class RerunServer:
    """``rerun --serve-grpc`` (or ``--serve-web``) bound to ``bind``, as a child process.

    ``url`` is the gRPC proxy URL to stream to; ``web_url`` (with ``serve_web``) the page
    that opens the viewer connected to it."""

    def __init__(self, bind: str = "127.0.0.1", grpc_port: int = 9876, serve_web: bool = False,
                 web_port: int = 9090, memory_limit: str = "512MiB", log_file: str | None = None,
                 timeout_s: float = 20.0):
        from common.zenoh_errors import ZenohListenError

        for what, port in (("rerun.grpc_port", grpc_port), ("rerun.web_port", web_port if serve_web else None)):
            if port is not None and not _free(bind, port):
                raise ZenohListenError(f"cannot serve rerun on {bind}:{port} ({what}): the port is in use; "
                                       f"stop what listens there or choose another port")
        cmd = [rerun_binary(), "--serve-web" if serve_web else "--serve-grpc", "--bind", bind,
               "--port", str(grpc_port), "--server-memory-limit", memory_limit]
        if serve_web:
            cmd += ["--web-viewer-port", str(web_port)]
        env = dict(os.environ, RERUN_ANALYTICS="0")
        out = open(log_file, "ab") if log_file else subprocess.DEVNULL
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env,
                                     preexec_fn=_pdeathsig if sys.platform.startswith("linux") else None)
        host = f"[{bind}]" if ":" in bind else bind
        connect_host = "127.0.0.1" if bind in ("0.0.0.0", "::") else host
        self.url = f"rerun+http://{connect_host}:{grpc_port}/proxy"
        self.web_url = None
        if serve_web:
            from urllib.parse import quote

            self.web_url = f"http://{connect_host}:{web_port}/?url={quote(self.url, safe='')}"
        end = time.monotonic() + timeout_s
        ports = [grpc_port] + ([web_port] if serve_web else [])
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the rerun server exited at start (code {self.proc.returncode}): {' '.join(cmd)}")
            if all(not _free(bind, p) for p in ports):
                return
            time.sleep(0.05)
        self.close()
        raise RuntimeError(f"the rerun server did not listen on {bind}:{ports} within {timeout_s:.0f} s")

    def close(self) -> None:
        p = self.proc
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
