"""Shared fixtures. Torch thread counts are set here, per module, never at import time (an
import-time ``torch.set_num_threads`` leaks into every test collected after it)."""
import os
import signal
import sys
import tempfile
from pathlib import Path

import pytest
import torch

# The tests start many ``python -m apps.cli`` children, each importing torch, sympy,
# transformers, ... The venv is installed with ``pip --no-compile`` (deploy/setup_dev.sh), so
# with PYTHONDONTWRITEBYTECODE set (as some container images do) every child would compile
# those sources again: ~3 s of CPU per process start. Children keep their bytecode in one
# cache under the venv instead (the source tree stays free of __pycache__; a changed source
# invalidates its entry as usual). This process is unaffected (read at interpreter start).
if os.environ.pop("PYTHONDONTWRITEBYTECODE", None):
    _cache = Path(sys.prefix) if os.access(sys.prefix, os.W_OK) else Path(tempfile.gettempdir())
    os.environ.setdefault("PYTHONPYCACHEPREFIX", str(_cache / "rayfronts-pycache"))


def _torch_threads(n: int):
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def torch_two_threads():
    """Run a module's tests with 2 torch threads (the build machine's core count), then
    restore the previous setting."""
    yield from _torch_threads(2)


@pytest.fixture(scope="module")
def torch_one_thread():
    """Run a module's tests with 1 torch thread, as the map runs per stage (tiny tensors and
    spare threads on a busy 2-core box spend their time in OpenMP barriers), then restore
    the previous setting."""
    yield from _torch_threads(1)


@pytest.fixture
def procs():
    """The test's :class:`tests.support.Proc` children; those still running at teardown are
    SIGKILLed (a test stops the ones whose exit it checks)."""
    from tests.support.processes import stop_all

    started: list = []
    yield started
    stop_all(reversed(started), signal.SIGKILL)


@pytest.fixture(scope="session")
def pca_file(tmp_path_factory):
    """A fixed PCA basis (``rayfronts edge fit-pca``, :func:`tests.support.fit_pca`) so
    restarted edges share one feature space; fitted once per session."""
    from tests.support.roles import fit_pca

    return fit_pca(tmp_path_factory.mktemp("pca") / "pca.npz")


@pytest.fixture(scope="session")
def console_world(tmp_path_factory, pca_file):
    """A mapper + edge on the synthetic world and ``rayfronts console`` in front of it
    (:class:`tests.support.console.ConsoleWorld`), shared by the console tests."""
    from tests.support.console import ConsoleWorld

    w = ConsoleWorld(tmp_path_factory.mktemp("console"), pca_file)
    yield w
    w.close()


@pytest.fixture
def closer():
    """Collects :class:`tests.support.zenoh_agent.Agent` / ``Router`` children and closes them
    (reverse order) whatever happens."""
    from tests.support.zenoh_agent import Agent

    items: list = []
    yield items
    for it in reversed(items):
        try:
            it.close() if isinstance(it, Agent) else it.stop()
        except Exception:
            pass
