"""Loopback ports for the tests (racy by nature, but unique per call)."""
from __future__ import annotations

import socket

from common.zenoh_session import free_tcp_port as free_port

__all__ = ["dead_endpoint", "free_port", "open_loopback_router", "port_is_free"]


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


def open_loopback_router(port: int):
    """A plain Zenoh session in router mode listening on ``tcp/127.0.0.1:port``, multicast
    scouting off (for tests that talk to Zenoh without our session helpers)."""
    import json

    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"router"')
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)
