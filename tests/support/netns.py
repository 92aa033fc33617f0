"""Network namespaces for the partition and topology tests (root and iproute2)."""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess

import pytest


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    """``ip ARGS`` (text output captured; raises on failure with ``check``)."""
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


@contextlib.contextmanager
def network_namespaces(names, links):
    """Fresh network namespaces ``names`` (loopback up) joined by veth pairs ``links``, each
    ``(ns_left, ns_right, veth_left, veth_right, cidr_left, cidr_right)``, both ends up.
    Skips the test without root and iproute2 or when ``ip netns add`` fails; deletes the
    namespaces (and with them the veths) at exit."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2")
    made: list[str] = []
    try:
        for n in names:
            r = ip("netns", "add", n, check=False)
            if r.returncode != 0:
                pytest.skip(f"ip netns add failed: {r.stderr.strip()}")
            made.append(n)
            ip("-n", n, "link", "set", "lo", "up")
        for left, right, vl, vr, cl, cr in links:
            ip("link", "add", vl, "type", "veth", "peer", "name", vr)
            ip("link", "set", vl, "netns", left)
            ip("link", "set", vr, "netns", right)
            ip("-n", left, "addr", "add", cl, "dev", vl)
            ip("-n", right, "addr", "add", cr, "dev", vr)
            ip("-n", left, "link", "set", vl, "up")
            ip("-n", right, "link", "set", vr, "up")
        yield
    finally:
        for n in made:
            ip("netns", "del", n, check=False)
