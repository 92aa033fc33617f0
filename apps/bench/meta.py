"""What every benchmark JSON says about the conditions it ran under.

The dispatcher (:mod:`apps.bench`) wraps each target's ``run`` and adds a ``meta`` block:
the machine (CPU model, logical / usable cores), the torch / Python threads in use, the
load average before and after, the wall time and the CPU time (user + sys, all threads) of
the benchmark process and of its finished children (``resource.getrusage``), and the timed
sections the target declared with :func:`timed`.

A **section** is the part of a run that a figure describes (e.g. "integrate 300 frames",
not rendering them first). Inside ``with timed("integrate", frames=n):`` the process CPU
time, wall time and load are taken at entry and exit; a section that counts frames reports
``frames_per_s`` and ``cpu_ms_per_frame`` (process CPU, all threads, per frame). CPU ms per
frame is the load-robust figure on a shared machine: other processes stretch the wall
time but not (much) the process's own CPU time. When the result counts frames
(top-level ``frames``) and a section named like the target's main loop exists, the
dispatcher also copies its ``cpu_ms_per_frame`` to the top level beside ``frames_per_s``.

:func:`interleaved` times several alternatives of one measurement in alternation (A B A
B ...) in one process, so a comparison (with / without kernels, NACLIP vs plain) sees the
same machine load on both sides.
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator

_SECTIONS: list[dict] = []
_LOCK = threading.Lock()


def cpu_model() -> str:
    """CPU model name (``/proc/cpuinfo``, else :func:`platform.processor`)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def machine() -> dict:
    """Static description of the host the figures come from."""
    return {"cpu_model": cpu_model(), "logical_cores": os.cpu_count() or 1, "usable_cores": usable_cores(),
            "arch": platform.machine(), "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version()}


def loadavg() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # pragma: no cover - not on Linux
        return []


def git_commit(path: str | None = None) -> dict:
    """``{"commit": sha or None, "dirty": bool or None}`` of the git checkout holding ``path``
    (default: this source tree); None values when it is not a git checkout."""
    import subprocess
    from pathlib import Path

    where = str(Path(path or __file__).resolve().parent)
    try:
        sha = subprocess.run(["git", "-C", where, "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", where, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip() != ""
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": sha, "dirty": dirty}


def cpu_seconds(children: bool = False) -> float:
    """User + system CPU seconds of this process (all threads), or of its waited-for children."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def os_threads() -> int:
    """OS threads of this process now (``/proc/self/status``), else Python threads."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Threads:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return threading.active_count()


def torch_threads() -> int | None:
    """Torch intra-op threads of the calling thread, if torch is loaded (never imports it)."""
    t = sys.modules.get("torch")
    return int(t.get_num_threads()) if t is not None else None


def _point() -> dict:
    return {"wall": time.perf_counter(), "cpu": cpu_seconds(), "cpu_children": cpu_seconds(True),
            "thread_cpu": time.thread_time(), "load": loadavg()}


def _span(a: dict, b: dict) -> dict:
    return {"wall_s": round(b["wall"] - a["wall"], 4), "cpu_s": round(b["cpu"] - a["cpu"], 4),
            "cpu_children_s": round(b["cpu_children"] - a["cpu_children"], 4),
            "load_before": a["load"], "load_after": b["load"]}


class Section:
    """One timed section (see module docstring); fields filled on exit."""

    def __init__(self, name: str, frames: int | None = None):
        self.name = name
        self.frames = frames
        self.result: dict = {}
        self._a: dict | None = None

    def __enter__(self) -> "Section":
        self._a = _point()
        return self

    def __exit__(self, *exc) -> None:
        b = _point()
        assert self._a is not None, "Section exited without being entered"
        r = _span(self._a, b)
        r["calling_thread_cpu_s"] = round(b["thread_cpu"] - self._a["thread_cpu"], 4)
        r["cpu_utilisation"] = round(r["cpu_s"] / r["wall_s"], 3) if r["wall_s"] > 0 else None
        if self.frames:
            r["frames"] = int(self.frames)
            r["frames_per_s"] = round(self.frames / r["wall_s"], 3) if r["wall_s"] > 0 else None
            r["cpu_ms_per_frame"] = round(1e3 * r["cpu_s"] / self.frames, 3)
            r["wall_ms_per_frame"] = round(1e3 * r["wall_s"] / self.frames, 3)
        self.result = r
        with _LOCK:
            _SECTIONS.append({"name": self.name, **r})

    def set_frames(self, n: int) -> None:
        """Set the frame count before the section ends (when it is known only then)."""
        self.frames = int(n)


def timed(name: str, frames: int | None = None) -> Section:
    """``with timed("integrate", frames=300) as s: ...`` then ``s.result`` (see module doc)."""
    return Section(name, frames)


def sections() -> list[dict]:
    with _LOCK:
        return list(_SECTIONS)


def reset() -> None:
    with _LOCK:
        _SECTIONS.clear()


@contextmanager
def run_meta(argv: list[str] | None = None) -> Iterator[dict]:
    """Wrap one benchmark run: yields a dict that holds the ``meta`` block on exit (its
    ``commit`` / ``dirty`` as at the start: the code that ran, whatever is committed during
    a long run)."""
    reset()
    out: dict = {}
    head = git_commit()
    a = _point()
    try:
        yield out
    finally:
        b = _point()
        span = _span(a, b)
        out.update({"machine": machine(), **head, "argv": list(argv) if argv is not None else None,
                    "load_before": span.pop("load_before"), "load_after": span.pop("load_after"),
                    "process": span, "torch_threads": torch_threads(), "os_threads_at_end": os_threads(),
                    "sections": sections(),
                    "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})


def attach(result: dict, meta: dict) -> dict:
    """``result`` with ``meta`` added; for a result counting frames, the main section's CPU ms
    per frame beside ``frames_per_s`` (main = the section named ``result['main_section']``,
    else the only section that counts frames)."""
    out = dict(result)
    out["meta"] = meta
    secs = [s for s in meta.get("sections", []) if s.get("frames")]
    if "main_section" in result:  # the target names its main section (None: no single one)
        main = result["main_section"]
        pick = [s for s in secs if s["name"] == main] if main else []
    else:
        pick = secs if len(secs) == 1 else []
    if pick and "cpu_ms_per_frame" not in out:
        out["cpu_ms_per_frame"] = pick[-1]["cpu_ms_per_frame"]
        out.setdefault("frames_per_s", pick[-1]["frames_per_s"])
    if not secs and "cpu_ms_per_frame" not in out and out.get("frames"):
        # no timed section: the whole run's CPU (set-up included), labelled as such
        out["cpu_ms_per_frame_whole_run"] = round(1e3 * meta["process"]["cpu_s"] / float(out["frames"]), 3)
    return out


def interleaved(fns: dict[str, Callable[[], object]], reps: int, warmup: int = 1,
                sync: Callable[[], object] | None = None) -> dict[str, list[float]]:
    """Time each callable of ``fns`` ``reps`` times in alternation (after ``warmup`` rounds):
    {name: [seconds, ...]}. ``sync()`` (e.g. CUDA synchronise) runs after each call."""
    for _ in range(max(0, warmup)):
        for f in fns.values():
            f()
            if sync is not None:
                sync()
    out: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(max(1, reps)):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            if sync is not None:
                sync()
            out[k].append(time.perf_counter() - t0)
    return out


def resolution_arg(s: str) -> tuple[int, int]:
    """argparse type for an image size ``HxW`` in pixels → ``(H, W)``, both at least 16."""
    try:
        h, w = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be HxW (e.g. 224x224), got {s!r}") from None
    if h < 16 or w < 16:
        raise argparse.ArgumentTypeError(f"resolution must be at least 16x16, got {s!r}")
    return h, w


def add_synthetic_map_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the benches that map the synthetic world in process (``bench mapper``,
    ``bench mission``): ``--seed``, ``--feature-dim``, ``--depth-limit`` (m), ``--threads``
    (torch CPU threads per mapping stage) and ``--override`` (map config ``KEY=VALUE``)."""
    parser.add_argument("--seed", type=int, default=0, help="world / route / feature seed (default 0)")
    parser.add_argument("--feature-dim", type=int, default=100, help="feature channels (default 100, PCA size)")
    parser.add_argument("--depth-limit", type=float, default=20.0, help="simulated sensor range in m (default 20)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads per mapping stage (default 1; more threads on a shared 2-core box "
                             "slow torch down)")
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE", help="map config overrides")
