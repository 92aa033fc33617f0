"""Zenoh errors in the user's terms, and a listen-address check that runs before a session opens.

Zenoh's Python errors (``zenoh.ZError``) carry the Rust source location
(``... at /root/.cargo/.../orchestrator.rs:447.``) and describe the symptom, not what to do.
:func:`explain_zenoh_error` turns the ones a user meets into one sentence naming the cause and
the fix; anything unknown comes back with the Rust locations stripped.

:func:`check_listen_free` binds each ``tcp/HOST:PORT`` listen endpoint with a plain socket
(``SO_REUSEADDR``, so a port in ``TIME_WAIT`` still counts as free, as it does for Zenoh)
before a router-mode process spends seconds loading models, so "port in use" is reported at
once and in one line. It is only a pre-check: the real bind is still Zenoh's.
"""
from __future__ import annotations

import re
import socket
from typing import Iterable

_RUST_AT = re.compile(r"\s*\bat\s+/\S+?\.rs:\d+\.?")
_ENDPOINT = re.compile(r"(tcp|udp|tls|quic|ws)/(\[[0-9a-fA-F:.]*\]|[^:\s\]\[,)]+):(\d+)")


def strip_rust_locations(msg: str) -> str:
    """``"Unable to connect ... at /x/y.rs:447."`` → ``"Unable to connect ..."``."""
    out = _RUST_AT.sub("", str(msg))
    return re.sub(r"\s{2,}", " ", out).strip()


class ZenohListenError(RuntimeError):
    """A listen endpoint cannot be bound (the message says why and what to do)."""


def _endpoints_in(msg: str) -> list[str]:
    return sorted({m.group(0) for m in _ENDPOINT.finditer(msg)})


def explain_zenoh_error(err: BaseException | str, endpoints: Iterable[object] | None = None) -> str:
    """One sentence for a Zenoh error ``err`` (exception or text): cause and what to do.
    ``endpoints`` are the endpoints involved when the message does not name them."""
    raw = str(err)
    msg = strip_rust_locations(raw)
    low = raw.lower()
    eps = _endpoints_in(msg) or [str(e) for e in (endpoints or [])]
    where = ", ".join(eps) if eps else "the configured endpoint"
    if "address already in use" in low or "os error 98" in low:
        return (f"cannot listen on {where}: the address is already in use (another router or mapper "
                f"running there?); stop it or choose another port with --listen")
    if "cannot assign requested address" in low or "os error 99" in low:
        return (f"cannot listen on {where}: that address is not one of this machine's; use one of its "
                f"addresses, 127.0.0.1 (this machine only) or 0.0.0.0 (all interfaces)")
    if "permission denied" in low or "os error 13" in low:
        return f"cannot listen on {where}: permission denied (ports below 1024 need root); choose a port >= 1024"
    if "unable to connect to any of" in low or "connection refused" in low:
        return (f"no Zenoh router answers at {where}: start one there (`rayfronts router --listen ENDPOINT` "
                f"or `rayfronts mapper`), or point --connect at the running one")
    if "certificate" in low or ("tls" in low and ("handshake" in low or "invalid" in low)):
        return (f"TLS failed with {where} ({msg}): check --certs DIR (ca.pem, cert.pem, key.pem) and that "
                f"both sides use certificates from the same CA")
    if "unknown key" in low:
        return f"Zenoh rejected a config key ({msg}); check --zenoh-set / zenoh.extra against Zenoh's config"
    return msg


def _host_port(endpoint: str) -> tuple[str, int] | None:
    m = _ENDPOINT.fullmatch(endpoint.split("#", 1)[0].split("?", 1)[0])
    if not m or m.group(1) not in ("tcp", "tls", "ws"):
        return None
    host = m.group(2).strip("[]")
    return host, int(m.group(3))


def check_listen_free(endpoints: Iterable[str] | None) -> None:
    """Raise :class:`ZenohListenError` with :func:`explain_zenoh_error`'s sentence when a TCP listen
    endpoint cannot be bound now (port in use, address not local, privileged port)."""
    for ep in endpoints or ():
        hp = _host_port(str(ep))
        if hp is None or hp[1] == 0:
            continue
        host, port = hp
        fam = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            with socket.socket(fam, socket.SOCK_STREAM) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((host, port))
        except OSError as e:
            raise ZenohListenError(explain_zenoh_error(f"{e.strerror} (os error {e.errno})", [ep])) from None
