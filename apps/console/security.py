"""Console access control: loopback-only by default, a bearer token (or the cookie a valid
``?token=`` sets) and TLS otherwise, a per-address rate limit, a request-body bound that also
holds for chunked uploads, and caps on open event streams (docs/commands.md, ``rayfronts console``)."""
from __future__ import annotations

import hmac
import ipaddress
import json
import socket
import threading
import time
from collections import Counter, deque

ENV_TOKEN = "RAYFRONTS_CONSOLE_TOKEN"
MAX_BODY_BYTES = 8 * 1024 * 1024
#: the HttpOnly cookie that holds the token after the page was opened with ``?token=``
COOKIE = "rayfronts_console_token"
#: the one-line body of a 401
TOKEN_HELP = ("missing or wrong token: open the page as https://HOST:PORT/?token=TOKEN (it sets a cookie) "
              "or send 'Authorization: Bearer TOKEN' (the token is --token or $" + ENV_TOKEN + ")")


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


def require_safe_listen(host: str, token: str | None, tls: bool, insecure_http: bool) -> None:
    """Refuse a non-loopback bind without a token, or without TLS unless ``insecure_http``
    (ConsoleConfigError, one line naming the options)."""
    if is_loopback(host):
        return
    if not token:
        raise ConsoleConfigError(f"--http {host} is not a loopback address: give --token TOKEN (or ${ENV_TOKEN}) "
                                 "so that only holders of the token can use the console, or use an SSH tunnel")
    if not tls and not insecure_http:
        raise ConsoleConfigError(f"--http {host} is not a loopback address: give --tls-cert PEM --tls-key PEM "
                                 "(HTTPS: the token travels with every request), or --insecure-http to serve "
                                 "plain HTTP anyway (a trusted network only)")


def presented_token(header: str | None, query_token: str | None, cookie: str | None) -> str | None:
    """The token a request presents: ``Authorization: Bearer``, else ``?token=``, else the cookie."""
    if header and header.lower().startswith("bearer "):
        return header[7:].strip()
    if query_token is not None:
        return query_token
    return cookie


def token_ok(token: str | None, header: str | None, query_token: str | None, cookie: str | None = None) -> bool:
    """Whether a request carries the token (the first one presented decides, see :func:`presented_token`)."""
    if not token:
        return True
    got = presented_token(header, query_token, cookie)
    return got is not None and hmac.compare_digest(got.encode(), token.encode())


def token_cookie(token: str, secure: bool) -> str:
    """The ``Set-Cookie`` value after a valid ``?token=``: HttpOnly, SameSite=Lax, path /,
    Secure when the console serves HTTPS (a browser drops Secure cookies over plain HTTP)."""
    return f"{COOKIE}={token}; Path=/; HttpOnly; SameSite=Lax" + ("; Secure" if secure else "")


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


class StreamSlots:
    """Open server-sent-event streams: at most ``per_client`` per client address and ``total``
    in all (0 = no limit). :meth:`acquire` returns None or the one-line refusal."""

    def __init__(self, per_client: int = 4, total: int = 32):
        self.per_client = int(per_client)
        self.total = int(total)
        self._open: dict[str, int] = {}
        self._lock = threading.Lock()
        self.refused = 0

    @property
    def open(self) -> int:
        with self._lock:
            return sum(self._open.values())

    def acquire(self, addr: str) -> str | None:
        with self._lock:
            mine, n = self._open.get(addr, 0), sum(self._open.values())
            if self.per_client > 0 and mine >= self.per_client:
                self.refused += 1
                return (f"too many event streams from {addr} ({mine} open, limit {self.per_client} per client): "
                        "close one, or raise --max-streams-per-client")
            if self.total > 0 and n >= self.total:
                self.refused += 1
                return f"too many event streams open ({n}, limit {self.total} in total): raise --max-streams"
            self._open[addr] = mine + 1
            return None

    def release(self, addr: str) -> None:
        with self._lock:
            left = self._open.get(addr, 0) - 1
            if left > 0:
                self._open[addr] = left
            else:
                self._open.pop(addr, None)


class BodyCap:
    """ASGI middleware: a request body over ``max_body`` bytes is refused with 413 and a one-line
    JSON error — from its Content-Length before anything is read, and for a chunked upload (no
    Content-Length) as soon as the chunks read so far pass the limit: such a body is read (at
    most ``max_body`` bytes held) before the app sees it. Refusals counted in
    ``refused["body_too_large"]``."""

    def __init__(self, app, max_body: int = MAX_BODY_BYTES, refused: Counter | None = None):
        self.app = app
        self.max_body = int(max_body)
        self.refused = Counter() if refused is None else refused

    async def _refuse(self, send) -> None:
        self.refused["body_too_large"] += 1
        body = json.dumps({"error": f"request body too large (limit {self.max_body // (1024 * 1024)} MiB)"}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or ())
        n = headers.get(b"content-length")
        if n is not None:
            if not n.isdigit() or int(n) > self.max_body:
                await self._refuse(send)
                return
            await self.app(scope, receive, send)
            return
        if b"transfer-encoding" not in headers:       # no body at all
            await self.app(scope, receive, send)
            return
        chunks, size = [], 0
        while True:
            msg = await receive()
            if msg["type"] != "http.request":          # the client went away mid-upload
                return
            chunks.append(msg.get("body", b""))
            size += len(chunks[-1])
            if size > self.max_body:
                await self._refuse(send)
                return
            if not msg.get("more_body", False):
                break
        replay = [{"type": "http.request", "body": b"".join(chunks), "more_body": False}]

        async def receive_again():
            return replay.pop() if replay else await receive()

        await self.app(scope, receive_again, send)
