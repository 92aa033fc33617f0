"""``python -m apps.cli`` children for the process-level tests: start, stop, wait.

Every process started with the default environment (:func:`proc_env`) gets
``RAYFRONTS_TEXT_CACHE`` pointing at one directory per pytest session, so only the first
edge of a session loads the MiniLM text model to embed its class names, and a mapper loads
it only for a query text no earlier process embedded (``encoders.text.base``; the
embeddings read back are the exact float32 rows).
"""
from __future__ import annotations

import atexit
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from apps.demo import zenoh_env
from apps.processes import stop_process, wait_for

ROOT = Path(__file__).resolve().parents[2]

__all__ = ["ROOT", "Proc", "cli_cmd", "proc_env", "start_cli", "stop_all", "stop_process", "text_cache_dir",
           "wait_for", "wait_log", "zenoh_env"]

_TEXT_CACHE: list[str] = []


def text_cache_dir() -> str:
    """The session's shared text-embedding cache directory (created on first use, removed
    at exit)."""
    if not _TEXT_CACHE:
        d = tempfile.mkdtemp(prefix="rayfronts-text-cache-")
        atexit.register(shutil.rmtree, d, True)
        _TEXT_CACHE.append(d)
    return _TEXT_CACHE[0]


def proc_env() -> dict:
    """The environment of the processes the tests start (Zenoh settings + the text cache)."""
    return {**zenoh_env(), "RAYFRONTS_TEXT_CACHE": text_cache_dir()}


def cli_cmd(*args) -> list[str]:
    """The argv of ``rayfronts <args>`` run by this interpreter."""
    return [sys.executable, "-m", "apps.cli", *args]


def start_cli(args, log, *, env: dict | None = None, prefix=(), nice: int = 0) -> subprocess.Popen:
    """``rayfronts <args>`` in the repository root, stdout and stderr into the open binary
    file ``log``; ``env`` defaults to :func:`proc_env`, ``prefix`` goes before the
    interpreter (``ip netns exec NS``), ``nice`` > 0 lowers its priority."""
    return subprocess.Popen([*prefix, *cli_cmd(*args)], stdout=log, stderr=subprocess.STDOUT,
                            env=proc_env() if env is None else env, cwd=str(ROOT),
                            preexec_fn=(lambda: os.nice(nice)) if nice else None)


class Proc:
    """A ``rayfronts`` child logging to ``<logdir>/<name>.log`` (see :func:`start_cli`)."""

    def __init__(self, name, args, logdir: Path, nice: int = 0, *, env: dict | None = None, prefix=()):
        self.name = name
        self.log = open(logdir / f"{name}.log", "ab")
        self.p = start_cli(args, self.log, env=env, prefix=prefix, nice=nice)

    def stop(self, sig=signal.SIGINT, timeout=30.0) -> int:
        """Stop it with ``sig``; an assertion error (after SIGKILL) if it outlives ``timeout``."""
        if self.p.poll() is None:
            self.p.send_signal(sig)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
                raise AssertionError(f"{self.name} did not exit within {timeout} s after {sig!r}") from None
        self.log.close()
        return self.p.returncode


def stop_all(procs, sig=signal.SIGINT, timeout: float = 30.0) -> None:
    """Teardown, in the given order: each process (a :class:`Proc` or a ``Popen``) still
    running gets ``sig``, then SIGKILL after ``timeout`` s; a :class:`Proc`'s log is closed."""
    for p in procs:
        stop_process(p.p if isinstance(p, Proc) else p, sig, timeout)
        if isinstance(p, Proc):
            p.log.close()


def wait_log(p: subprocess.Popen, log: Path, pattern: str, timeout: float, every: float = 0.2) -> re.Match:
    """The first match of the regular expression ``pattern`` in ``log`` (the output of ``p``),
    polled every ``every`` s; an assertion error at once if ``p`` exits first, or after
    ``timeout`` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        out = log.read_text(errors="replace") if log.exists() else ""
        m = re.search(pattern, out)
        if m:
            return m
        if p.poll() is not None:
            raise AssertionError(f"{shlex.join(map(str, p.args))} exited ({p.returncode}) before printing "
                                 f"{pattern!r}:\n{out[-3000:]}")
        time.sleep(every)
    tail = log.read_text(errors="replace")[-3000:] if log.exists() else ""
    raise AssertionError(f"{pattern!r} not in {log} after {timeout} s:\n{tail}")
