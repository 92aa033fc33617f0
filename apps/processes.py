"""Child-process chores shared by the benchmarks and the tests: poll until a condition holds,
stop a process (a signal, a bounded wait, then SIGKILL). Standard library only."""
from __future__ import annotations

import signal
import subprocess
import time


def wait_for(fn, timeout: float = 60.0, every: float = 0.2, what: str = "condition", *,
             error: type[Exception] = AssertionError, prefix: str = ""):
    """Call ``fn`` every ``every`` s until it returns something truthy and return that. An
    exception from ``fn`` counts as "not yet" (the mapper is still starting, say). After
    ``timeout`` s raise ``error`` naming ``what`` and the last value or exception."""
    end = time.monotonic() + timeout
    last = None
    while time.monotonic() < end:
        try:
            last = fn()
            if last:
                return last
        except Exception as e:  # not up yet etc.
            last = e
        time.sleep(every)
    raise error(f"{prefix}timed out waiting for {what} (last: {last!r})")


def stop_process(p: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 30.0) -> int | None:
    """If ``p`` still runs: send ``sig``, wait up to ``timeout`` s, then SIGKILL and reap it.
    Returns its exit code."""
    if p.poll() is None:
        p.send_signal(sig)
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    return p.returncode
