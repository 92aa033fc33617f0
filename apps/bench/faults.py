"""``rayfronts bench faults``: the timing figures of the fault tests.

``tests/test_faults.py`` and ``tests/test_robustness.py`` assert what is functional (queries
answered during a flood, nothing lost, bounded queues and memory, a dead or frozen robot
marked gone within the configured lease); the speed figures live here, measured with the
same real processes over loopback:

* ``query``: a ``rayfronts mapper`` (router, ``query.lock_timeout_s`` = ``--lock-timeout``)
  maps ``--frames`` frames of one edge; ``--queries`` text queries are timed on the idle
  mapper (unloaded), then ``--floods`` edges (niced: they stand for the robots' own
  computers) flood it with looping frames at full rate and the same queries are timed
  again. Reported: p50 / p95 / max ms of both, the bound ``lock_timeout + 3 x the
  unloaded median`` and whether the flood p95 is within it, stale answers (served from the
  last consistent copy), the mapper's RSS, frames mapped / dropped.
* ``gone``: seconds from SIGKILL and from SIGSTOP of a looping edge to the ``gone_at`` the
  mapper reports (CLI defaults: the 2 s lease of ``common.zenoh_session``).
* ``decode``: CPU ms to reject each of :func:`hostile_frame_headers` (best of 5; the worst
  one is the figure) beside the CPU ms to decode a real frame, in this process.

The PCA basis is fitted first (``rayfronts edge fit-pca``, not timed). Processes get
``RAYFRONTS_TEXT_CACHE`` (a directory in the work dir) so edges after the first do not load
the text model. Wall-clock figures: the load average is in the meta block.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Iterator

import numpy as np

from apps.processes import stop_process, wait_for

if TYPE_CHECKING:
    from query_client.client import Client

HELP = "fault timings: query latency unloaded vs during an edge flood, gone-after-SIGKILL/SIGSTOP (real processes)"

MAP_ARGS = ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0", "rerun.file=",
            "snapshots.on_exit=false"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--floods", type=int, default=3, help="flooding edges (default 3)")
    parser.add_argument("--frames", type=int, default=10, help="frames of the first (unloaded) edge (default 10)")
    parser.add_argument("--queries", type=int, default=20, help="timed queries per phase (default 20)")
    parser.add_argument("--lock-timeout", type=float, default=0.25, help="mapper query.lock_timeout_s (default 0.25)")
    parser.add_argument("--resolution", default="96x128", help="frame size HxW (default 96x128)")
    parser.add_argument("--pca-dim", type=int, default=16, help="PCA dimension (default 16)")
    parser.add_argument("--only", choices=("query", "gone", "decode"), default=None, help="run one part only")
    parser.add_argument("--workdir", type=Path, default=None, help="keep logs here")


def sample_frame_bytes(**kw: Any) -> bytes:
    """A small valid frame message (48×64, 16-d features): the decode cost's reference."""
    from common.frame import Frame
    from common.wire import encode_frame

    return encode_frame(Frame("r1", 0, 0.0, np.eye(4), np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]),
                              np.ones((48, 64), np.float32), np.zeros((48, 64, 3), np.uint8),
                              features=np.zeros((16, 6, 8), np.float16), feature_space="x", **kw))


def hostile_frame_headers() -> Iterator[tuple[str, bytes]]:
    """(name, message bytes): frame headers built to be expensive to decode, each within the
    frame header's 64 KiB limit or just over it (the old decoder took 0.7-3.4 s on the first
    two). Shared with ``tests/test_faults.py``."""
    import struct

    import msgpack

    head = {"schema": "rayfronts.frame", "v": 1}

    def framed(hdr: bytes) -> bytes:
        return struct.pack("<I", len(hdr)) + hdr

    yield "8.9 MB map", framed(msgpack.packb({**head, **{f"k{i}": i for i in range(700_000)}}))
    yield "2 MB nested list", framed(b"\x91" * 2_000_000 + b"\xc0")
    yield "64 KiB nested list", framed(b"\x91" * 65_535 + b"\xc0")
    yield "64 KiB nested maps", framed(b"\x81\xa1a" * 21_000 + b"\xc0")
    yield "tree of ints", framed(msgpack.packb({**head, "x": [[[1] * 127] * 127] * 3 + [[[1] * 127] * 120]}))
    yield "tree of empty lists", framed(msgpack.packb({**head, "x": [[[[]] * 127] * 127] * 3 + [[[[]] * 127] * 120]}))
    yield "tree of empty maps", framed(msgpack.packb({**head, "x": [[[{}] * 127] * 127] * 3 + [[[{}] * 127] * 120]}))
    yield "one long list", framed(msgpack.packb({**head, "x": list(range(20_000))}))
    yield "64 KiB of strings", framed(msgpack.packb({**head, "x": ["a" * 16_000] * 4}))
    yield "huge shape", framed(msgpack.packb({**head, "robot": "r1", "seq": 0, "stamp": 0.0,
                                              "pose": {"__nd__": ["<f8", list(range(10_000)), 0, 8]}}))
    yield "binary in header", framed(msgpack.packb({**head, "robot": "r1", "x": b"\0" * 60_000}, use_bin_type=True))


def reject_costs(repeats: int = 5) -> dict:
    """CPU ms (best of ``repeats``) to reject each hostile header and to decode a real frame;
    every hostile header must raise ``WireError`` (anything else is a bug and propagates)."""
    from common.wire import WireError, decode_frame

    def best_ms(data: bytes, hostile: bool) -> tuple[float, str]:
        best, reason = 1e9, ""
        for _ in range(repeats):
            t = time.process_time()
            try:
                decode_frame(data)
            except WireError as e:
                if not hostile:
                    raise
                reason = e.reason
            else:
                if hostile:
                    raise AssertionError("a hostile frame header was accepted")
            best = min(best, time.process_time() - t)
        return round(best * 1e3, 3), reason

    real_ms, _ = best_ms(sample_frame_bytes(), hostile=False)
    rows: dict[str, dict] = {}
    for name, data in hostile_frame_headers():
        ms, reason = best_ms(data, hostile=True)
        rows[name] = {"cpu_ms": ms, "reason": reason, "bytes": len(data)}
    worst = max(rows, key=lambda k: rows[k]["cpu_ms"])
    return {"real_frame_cpu_ms": real_ms, "worst": worst, "worst_cpu_ms": rows[worst]["cpu_ms"], "headers": rows}


def timed_queries(c: Client, n: int, text: str = "car", top_k: int = 5) -> list[dict]:
    """``n`` queries through client ``c``, each followed by a stats call: per query the wall
    seconds, the reply's voxel count, ``stale``, its server timings and the mapper's RSS.
    Shared with the flood test (which asserts only what is functional about them)."""
    out = []
    for _ in range(n):
        t = time.perf_counter()
        r = c.query(text, top_k=top_k)
        dt = time.perf_counter() - t
        st = c.stats()
        out.append({"s": dt, "voxels": len(r.voxel_xyz), "frames_mapped": r.frames_mapped,
                    "stale": bool(r.timings.get("stale", 0)), "timings": dict(r.timings),
                    "rss_mb": float(st.get("rss_mb", 0.0)), "stats": st})
    return out


def _ms(xs) -> dict:
    a = np.asarray(xs, float) * 1e3
    return {"n": int(a.size), "p50": round(float(np.median(a)), 2), "p95": round(float(np.percentile(a, 95)), 2),
            "max": round(float(a.max()), 2)}


class _Procs:
    def __init__(self, work: Path, env: dict):
        self.items: list[tuple[subprocess.Popen, IO[bytes]]]     # (process, its log file)
        self.work, self.env, self.items = work, env, []

    def start(self, name: str, args: list[str], nice: int = 0) -> subprocess.Popen:
        f = open(self.work / f"{name}.log", "ab")
        p = subprocess.Popen([sys.executable, "-m", "apps.cli", *args], stdout=f, stderr=subprocess.STDOUT,
                             env=self.env, preexec_fn=(lambda: os.nice(nice)) if nice else None)
        self.items.append((p, f))
        return p

    def stop_all(self) -> None:
        for p, f in reversed(self.items):
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
            stop_process(p, signal.SIGINT, 20)
            f.close()
        self.items.clear()


def _absent(r: dict) -> dict | None:
    """The robot entry ``r`` once the mapper reports it gone, else None (keep waiting)."""
    return r if not r["present"] else None


def _wait(fn, timeout: float, what: str, every: float = 0.05):
    return wait_for(fn, timeout, every, what, error=RuntimeError, prefix="bench faults: ")


def run(args: argparse.Namespace) -> dict:
    from apps.bench.meta import timed
    from apps.demo import zenoh_env
    from common.zenoh_session import DEFAULT_LEASE_MS, ZenohConfig, free_tcp_port
    from query_client import Client

    work = Path(args.workdir or tempfile.mkdtemp(prefix="rayfronts-bench-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    out: dict = {"lock_timeout_s": args.lock_timeout, "resolution": args.resolution, "workdir": str(work)}
    if args.only in (None, "decode"):
        with timed("rejecting hostile headers"):
            out["decode"] = reject_costs()
        if args.only == "decode":
            return out
    env = {**zenoh_env(), "RAYFRONTS_TEXT_CACHE": str(work / "text-cache")}
    pca = work / f"pca{args.pca_dim}.npz"
    src = [f"source.resolution={args.resolution}", "source.depth_limit=20"]
    if not pca.is_file():
        r = subprocess.run([sys.executable, "-m", "apps.cli", "edge", "fit-pca", "--out", str(pca), "--frames", "4",
                            *src, "source.n_frames=40", f"pca.out_dim={args.pca_dim}"],
                           env=env, capture_output=True, text=True, timeout=300)
        if r.returncode != 0:
            raise RuntimeError(f"edge fit-pca failed: {r.stderr.strip()[-500:]}")

    def edge(ep, robot, frames, rate, loop=False):
        return ["edge", "--connect", ep, "--rate", str(rate), f"robot={robot}", *src, f"source.n_frames={frames}",
                f"pca.basis={pca}", f"pca.out_dim={args.pca_dim}", "zenoh.connect_retry_s=0.2",
                *(["publish.loop=true"] if loop else [])]

    def robot(c, name):
        return c.stats(timeout=5.0)["robots"].get(name, {})

    ps = _Procs(work, env)
    try:
        if args.only in (None, "query"):
            ep = f"tcp/127.0.0.1:{free_tcp_port()}"
            ps.start("mapper", ["mapper", "--mode", "router", "--listen", ep, *MAP_ARGS, "queues.idle_flush_s=0.5",
                                f"query.lock_timeout_s={args.lock_timeout}"])
            with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000, connect_retry_s=0.2), timeout=30) as c:
                _wait(c.mapper_alive, 120, "the mapper")
                e0 = ps.start("edge0", edge(ep, "r0", args.frames, 10.0))
                e0.wait(300)
                c.wait_settled(mapped=args.frames, timeout=120)                # the first frames
                timed_queries(c, 1)                                   # the text model / first copy
                with timed("unloaded queries"):
                    unloaded = timed_queries(c, args.queries)
                floods = [f"f{i}" for i in range(1, args.floods + 1)]
                for f in floods:
                    ps.start(f"flood-{f}", edge(ep, f, 400, 0.0, loop=True), nice=10)
                _wait(lambda: all(robot(c, f).get("mapped", 0) >= 2 for f in floods), 300, "the floods mapping")
                with timed("queries under flood"):
                    loaded = timed_queries(c, args.queries)
                st = c.stats()
            u = _ms([q["s"] for q in unloaded])
            fl = _ms([q["s"] for q in loaded])
            bound = args.lock_timeout * 1e3 + 3 * u["p50"]
            slowest = max(loaded, key=lambda q: q["s"])
            out["query"] = {
                "floods": args.floods, "unloaded_ms": u, "flood_ms": fl, "bound_ms": round(bound, 2),
                "flood_p95_within_bound": fl["p95"] <= bound,
                "stale_answers": sum(q["stale"] for q in loaded),
                "mapper_rss_mb_max": round(max(q["rss_mb"] for q in loaded), 1),
                "frames_mapped": st["frames"]["mapped"], "frames_dropped": st["frames"]["dropped"],
                "slowest_query_timings_ms": {k: round(float(v), 2) for k, v in slowest["timings"].items()},
            }
            ps.stop_all()
        if args.only in (None, "gone"):
            ep = f"tcp/127.0.0.1:{free_tcp_port()}"
            ps.start("mapper-gone", ["mapper", "--mode", "router", "--listen", ep, *MAP_ARGS])
            gone: dict = {"lease_ms": DEFAULT_LEASE_MS}
            with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000, connect_retry_s=0.2), timeout=30) as c:
                for how, sig in (("sigkill", signal.SIGKILL), ("sigstop", signal.SIGSTOP)):
                    name = f"g{how}"
                    p = ps.start(f"edge-{how}", edge(ep, name, 400, 5.0, loop=True))
                    _wait(lambda name=name: robot(c, name).get("mapped", 0) >= 2, 300, f"{name} mapping")
                    p.send_signal(sig)
                    t = time.time()
                    r = _wait(lambda name=name: _absent(robot(c, name)), 60, f"{name} gone")
                    gone[f"after_{how}_s"] = round(r["gone_at"] - t, 3)
                    p.send_signal(signal.SIGCONT)
                    p.kill()
                    p.wait()
            out["gone"] = gone
    finally:
        ps.stop_all()
    return out
