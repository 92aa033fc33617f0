"""Loopback ports for the tests (racy by nature, but unique per call)."""
from __future__ import annotations

import socket

from common.zenoh_session import free_tcp_port as free_port

__all__ = ["dead_endpoint", "free_port", "port_is_free"]


def port_is_free(port: int) -> bool:
    """Whether ``port`` on 127.0.0.1 can be bound now."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def dead_endpoint() -> str:
    """A loopback TCP endpoint nobody listens on (bound then closed)."""
    return f"tcp/127.0.0.1:{free_port()}"
