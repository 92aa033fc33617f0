"""Console access control: loopback-only by default, a bearer token otherwise, a per-address
rate limit and a request-body bound (docs/commands.md, ``rayfronts console``)."""
from __future__ import annotations

import hmac
import ipaddress
import socket
import threading
import time
from collections import deque

ENV_TOKEN = "RAYFRONTS_CONSOLE_TOKEN"
MAX_BODY_BYTES = 8 * 1024 * 1024


class ConsoleConfigError(ValueError):
    """A console start-up mistake (one line)."""


def is_loopback(host: str) -> bool:
    """True when ``host`` (name or address) resolves only to loopback addresses."""
    if host in ("localhost", ""):
        return host == "localhost"
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        try:
            addrs = {str(a[4][0]) for a in socket.getaddrinfo(host, None)}
        except OSError:
            return False
        return bool(addrs) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addrs)


def parse_http(hostport: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) -> (host, port); ConsoleConfigError when malformed."""
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit() or not (0 < int(port) < 65536):
        raise ConsoleConfigError(f"--http must be HOST:PORT, e.g. 127.0.0.1:8080 (got {hostport!r})")
    return host.strip("[]") or "127.0.0.1", int(port)


def require_token(host: str, token: str | None) -> None:
    """Refuse a non-loopback bind without a token (ConsoleConfigError, one line)."""
    if not is_loopback(host) and not token:
        raise ConsoleConfigError(f"--http {host} is not a loopback address: give --token TOKEN (or ${ENV_TOKEN}) "
                                 "so that only holders of the token can use the console, or use an SSH tunnel")


def token_ok(token: str | None, header: str | None, query_token: str | None) -> bool:
    """Whether a request carries the token as ``Authorization: Bearer TOKEN`` or ``?token=``."""
    if not token:
        return True
    got = None
    if header and header.lower().startswith("bearer "):
        got = header[7:].strip()
    elif query_token:
        got = query_token
    return got is not None and hmac.compare_digest(got.encode(), token.encode())


class RateLimiter:
    """At most ``per_minute`` requests per client address in any sliding 60 s window."""

    def __init__(self, per_minute: int = 600):
        self.per_minute = int(per_minute)
        self._hits: dict[str, deque] = {}
        self._lock = threading.Lock()

    def allow(self, addr: str, now: float | None = None) -> bool:
        if self.per_minute <= 0:
            return True
        now = time.monotonic() if now is None else now
        with self._lock:
            q = self._hits.setdefault(addr, deque())
            while q and q[0] <= now - 60.0:
                q.popleft()
            if len(q) >= self.per_minute:
                return False
            q.append(now)
            return True
