"""Zenoh session helpers shared by every process: config, open/close, signals, CLI flags.

Topology (docs/key_space.md#topology): the base station runs a session in ``router`` mode (the mapper or
``rayfronts router``); robots and laptops are ``client``s that connect to it. Multicast
scouting is off unless asked for.

How a session config is built (:func:`make_config`), later steps win:

1. the Zenoh JSON5 file ``config_file`` (e.g. one of ``deploy/zenoh/*.json5``; falls back to
   the ``RAYFRONTS_ZENOH_CONFIG`` environment variable), else Zenoh's defaults;
2. our keys: ``mode``, ``connect``, ``listen`` (only when set: they replace the file's),
   multicast scouting, shared memory, lease (``lease_ms``; without a config file and with
   ``lease_ms = 0`` the default :data:`DEFAULT_LEASE_MS` with :data:`DEFAULT_KEEP_ALIVE`
   keep-alives per lease, so a frozen or cut-off peer is declared gone within about 2 s
   with the CLI defaults instead of Zenoh's 10 s);
3. relative TLS / credential paths in the result are resolved against ``certs_dir``
   (falls back to ``RAYFRONTS_CERTS``, then ``/etc/rayfronts/certs``), so one shipped file
   serves every machine: each machine's certs dir holds ``ca.pem``, ``cert.pem``, ``key.pem``;
4. ``acl_file``: a JSON5 ``access_control`` object (from ``deploy/acl/make_acl.py``);
5. ``extra``: any Zenoh key → JSON value (e.g. ``{"transport/link/tx/lease": 2000}``).

Connecting (:func:`open_session`): a client whose router is not up fails at once inside
Zenoh, so ``connect_timeout_ms`` is implemented here by retrying, interruptibly (a stop
event): ``-1`` (default) keeps retrying until the router appears, so an edge can start
before its base station; ``0`` tries once; ``N > 0`` retries for N ms. Once connected, Zenoh
itself reconnects a client when the router comes back and re-declares its entities.

Closing: Zenoh serves callback subscribers/queryables from non-daemon threads that end only
when their session closes, so a process that exits with such a session still open would hang
at interpreter exit (the interpreter joins those threads before ``atexit`` runs). Use
:class:`SessionGuard` (a context manager that undeclares what it tracks and closes the
session) and :func:`install_signal_handlers`; as a last resort every session opened by
:func:`open_session` and still open is closed before the interpreter joins its threads
(:func:`close_open_sessions`), so a program that forgets ``close()`` (or fails before it)
still exits.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, TypeVar

from common.config import ConfigError, field_, split_key_value
from common.keys import DEFAULT_PREFIX

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

_Entity = TypeVar("_Entity")

MODES = ("router", "client", "peer")
DEFAULT_CERTS_DIR = "/etc/rayfronts/certs"
ENV_CONFIG = "RAYFRONTS_ZENOH_CONFIG"
ENV_CERTS = "RAYFRONTS_CERTS"
#: link lease (ms) of a session built without a config file: a silent link (SIGSTOPped or
#: partitioned peer) is closed about one lease after the last message it got, and the peer's
#: liveliness tokens go with it. Zenoh's own default is 10 s.
DEFAULT_LEASE_MS = 2000
#: keep-alive messages per lease (Zenoh's ``transport/link/tx/keep_alive``): one every 500 ms.
DEFAULT_KEEP_ALIVE = 4

#: config keys holding file paths that are resolved against ``certs_dir`` when relative.
PATH_KEYS = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/connect_private_key",
    "transport/link/tls/connect_certificate",
    "transport/auth/usrpwd/dictionary_file",
)


class ZenohConnectError(RuntimeError):
    """The session could not be opened (router unreachable, TLS refused, cancelled)."""


@dataclass
class ZenohConfig:
    """Zenoh session settings of one process (the ``zenoh`` section of process configs)."""

    prefix: str = field_(DEFAULT_PREFIX, "key-space prefix: all keys live under '<prefix>/...'")
    mode: str = field_("", "router | client | peer; empty = the config file's mode, else the "
                           "process default (client for edge/query, router for mapper/router)")
    connect: list[str] = field_([], "endpoints to connect to, e.g. ['tcp/192.168.1.10:7447'] "
                                    "(replace the config file's)")
    listen: list[str] = field_([], "endpoints to listen on, e.g. ['tcp/0.0.0.0:7447'] "
                                   "(replace the config file's)")
    config_file: str = field_("", "Zenoh JSON5 config file (e.g. deploy/zenoh/edge-tls.json5); "
                                  "empty = $RAYFRONTS_ZENOH_CONFIG or Zenoh defaults")
    certs_dir: str = field_("", "directory that relative TLS/credential paths resolve against "
                                "(ca.pem, cert.pem, key.pem); empty = $RAYFRONTS_CERTS or "
                                "/etc/rayfronts/certs")
    acl_file: str = field_("", "JSON5 access_control block (deploy/acl/make_acl.py) for router mode; "
                               "empty = none / the config file's")
    multicast_scouting: bool = field_(False, "UDP multicast discovery (off: explicit endpoints only)")
    shared_memory: bool | None = field_(None, "shared-memory transport between local processes; "
                                              "null = Zenoh default (on); false to measure the network")
    lease_ms: int = field_(0, "link lease in ms (a frozen or cut-off peer is seen gone after about this "
                              "long); 0 = the config file's lease, or 2000 (4 keep-alives per lease) "
                              "without a config file")
    connect_timeout_ms: int = field_(-1, "client mode: -1 = keep retrying until the router answers "
                                         "(start order does not matter); 0 = one try; N = retry N ms")
    connect_retry_s: float = field_(1.0, "client mode: wait between connection attempts (seconds, max)")
    extra: dict[str, Any] = field_({}, "more Zenoh config keys → JSON values, e.g. "
                                       "{'transport/link/tx/lease': 2000}; applied last")


# --------------------------------------------------------------------------- config
def _insert(c: zenoh.Config, key: str, value: Any, source: str) -> None:
    try:
        c.insert_json5(key, json.dumps(value))
    except Exception as e:  # zenoh.ZError: unknown key / wrong type
        raise ConfigError(f"zenoh config key {key!r} = {value!r} ({source}) rejected: {e}") from None


def _read_text(path: str, what: str) -> str:
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"{what} not found: {p}")
    return p.read_text()


def load_config_file(path: str) -> zenoh.Config:
    """``zenoh.Config`` from a JSON5 file, with a clear :class:`ConfigError` on problems."""
    import zenoh

    _read_text(path, "zenoh config file")
    try:
        return zenoh.Config.from_file(str(Path(path).expanduser()))
    except Exception as e:
        raise ConfigError(f"zenoh config file {path} is invalid: {e}") from None


def resolve_certs_dir(cfg: ZenohConfig) -> Path:
    """The directory relative TLS/credential paths resolve against (see module doc)."""
    return Path(cfg.certs_dir or os.environ.get(ENV_CERTS) or DEFAULT_CERTS_DIR).expanduser()


def make_config(cfg: ZenohConfig, extra: dict[str, Any] | None = None, default_mode: str = "client") -> zenoh.Config:
    """Build a ``zenoh.Config`` from ``cfg`` (see module doc for the order); raises ConfigError."""
    import zenoh

    if not isinstance(cfg, ZenohConfig):
        raise TypeError(f"make_config expects a ZenohConfig, got {type(cfg).__name__}")
    path = cfg.config_file or os.environ.get(ENV_CONFIG, "")
    c = load_config_file(path) if path else zenoh.Config()
    mode = cfg.mode or ("" if path else default_mode)
    if mode:
        if mode not in MODES:
            raise ConfigError(f"zenoh mode {mode!r} is not one of {', '.join(MODES)}")
        _insert(c, "mode", mode, "mode")
    _insert_endpoints(c, cfg)
    _insert(c, "scouting/multicast/enabled", bool(cfg.multicast_scouting), "multicast_scouting")
    if cfg.shared_memory is not None:
        _insert(c, "transport/shared_memory/enabled", bool(cfg.shared_memory), "shared_memory")
    _insert_lease(c, cfg, from_file=bool(path))
    if cfg.acl_file:
        _insert_acl(c, cfg.acl_file)
    for src, kv in (("zenoh.extra", cfg.extra), ("extra", extra)):
        for k, v in (kv or {}).items():
            _insert(c, k, v, src)
    _resolve_paths(c, resolve_certs_dir(cfg))
    return c


def _insert_endpoints(c: zenoh.Config, cfg: ZenohConfig) -> None:
    """``connect`` / ``listen`` endpoints (a str or a list of ``proto/address``) into ``c``."""
    for name, eps in (("connect", cfg.connect), ("listen", cfg.listen)):
        if isinstance(eps, str):
            eps = [eps]
        if eps:
            bad = [e for e in eps if not isinstance(e, str) or "/" not in e]
            if bad:
                raise ConfigError(f"zenoh {name} endpoint(s) {bad} are not of the form proto/address "
                                  "(e.g. tcp/192.168.1.10:7447)")
            _insert(c, f"{name}/endpoints", list(eps), name)


def _insert_lease(c: zenoh.Config, cfg: ZenohConfig, from_file: bool) -> None:
    """The link lease (ms) into ``c``: ``cfg.lease_ms``, else the defaults unless a config file gave them."""
    if cfg.lease_ms:
        if cfg.lease_ms < 100:
            raise ConfigError(f"zenoh lease_ms {cfg.lease_ms} is too small (>= 100 ms)")
        _insert(c, "transport/link/tx/lease", int(cfg.lease_ms), "lease_ms")
    elif not from_file:
        _insert(c, "transport/link/tx/lease", DEFAULT_LEASE_MS, "default lease")
        _insert(c, "transport/link/tx/keep_alive", DEFAULT_KEEP_ALIVE, "default keep-alive")


def _insert_acl(c: zenoh.Config, acl_file: str) -> None:
    """The access-control JSON5 file's content as ``access_control`` into ``c``."""
    text = _read_text(acl_file, "access-control file")
    try:
        c.insert_json5("access_control", text)
    except Exception as e:
        raise ConfigError(f"access-control file {acl_file} rejected by zenoh: {e}") from None


def _resolve_paths(c: zenoh.Config, certs_dir: Path) -> None:
    for key in PATH_KEYS:
        v = json.loads(c.get_json(key))
        if not isinstance(v, str) or not v:
            continue
        p = Path(v).expanduser()
        if not p.is_absolute():
            p = certs_dir / p
        if not p.is_file():
            raise ConfigError(f"zenoh {key}: file not found: {p} (set the certs dir with --certs DIR, "
                              f"zenoh.certs_dir or ${ENV_CERTS}, or give an absolute path)")
        c.insert_json5(key, json.dumps(str(p)))


def config_mode(c: zenoh.Config) -> str:
    """The mode of a built ``zenoh.Config`` (``router``/``client``/``peer``)."""
    m = json.loads(c.get_json("mode"))
    return m if isinstance(m, str) else "peer"


# --------------------------------------------------------------------------- open / close
_OPEN_SESSIONS: list = []          # sessions opened by open_session (closed ones pruned on open)
_OPEN_LOCK = threading.Lock()
_EXIT_HOOK_SET = False


def close_open_sessions() -> int:
    """Close every session opened by :func:`open_session` that is still open; the number
    closed. Runs before the interpreter joins non-daemon threads at exit (registered on the
    first open), so Zenoh's callback threads end and the process exits."""
    with _OPEN_LOCK:
        sessions, _OPEN_SESSIONS[:] = list(_OPEN_SESSIONS), []
    n = 0
    for s in sessions:
        if not s.is_closed():
            close_quietly(s)
            n += 1
    return n


def _track(session: zenoh.Session) -> zenoh.Session:
    global _EXIT_HOOK_SET
    with _OPEN_LOCK:
        _OPEN_SESSIONS[:] = [s for s in _OPEN_SESSIONS if not s.is_closed()]
        _OPEN_SESSIONS.append(session)
        if not _EXIT_HOOK_SET:
            # threading's pre-join hook (what concurrent.futures uses); atexit would run too late
            register = getattr(threading, "_register_atexit", None)
            try:
                if register is not None:
                    register(close_open_sessions)
                else:                                       # pragma: no cover - CPython < 3.9
                    import atexit

                    atexit.register(close_open_sessions)
                _EXIT_HOOK_SET = True
            except RuntimeError:                            # the interpreter is already shutting down
                pass
    return session


def open_session(cfg: ZenohConfig | zenoh.Config, *, stop: threading.Event | None = None,
                 extra: dict[str, Any] | None = None, default_mode: str = "client") -> zenoh.Session:
    """Open a ``zenoh.Session``.

    ``cfg`` is a :class:`ZenohConfig` (client mode retries per ``connect_timeout_ms``, and
    stops early when ``stop`` is set) or an already built ``zenoh.Config`` (one attempt).
    Raises :class:`ZenohConnectError` when no session could be opened.
    """
    import zenoh

    if isinstance(cfg, zenoh.Config):
        try:
            return _track(zenoh.open(cfg))
        except Exception as e:
            from common.zenoh_errors import explain_zenoh_error

            raise ZenohConnectError(explain_zenoh_error(e)) from e
    zc = make_config(cfg, extra=extra, default_mode=default_mode)
    retry = config_mode(zc) == "client" and cfg.connect_timeout_ms != 0
    deadline = None if cfg.connect_timeout_ms < 0 else time.monotonic() + cfg.connect_timeout_ms / 1000
    wait, warned = 0.1, False
    while True:
        try:
            return _track(zenoh.open(zc))
        except Exception as e:
            err = e
        from common.zenoh_errors import explain_zenoh_error  # one sentence, no Rust source paths

        if not retry or (deadline is not None and time.monotonic() >= deadline):
            eps = json.loads(zc.get_json("connect/endpoints"))
            raise ZenohConnectError(explain_zenoh_error(err, eps if isinstance(eps, list) else None)) from err
        if not warned:
            log.warning("zenoh: %s; retrying", explain_zenoh_error(err))
            warned = True
        wait = min(wait * 2, max(cfg.connect_retry_s, 0.05))
        if deadline is not None:
            wait = min(wait, max(deadline - time.monotonic(), 0.0))
        if stop is not None:
            if stop.wait(wait):
                raise ZenohConnectError("cancelled while waiting for the zenoh router")
        else:
            time.sleep(wait)
        zc = make_config(cfg, extra=extra, default_mode=default_mode)  # a Config is consumed by open


class SessionGuard:
    """Owns a session and the entities declared on it; closes everything on exit.

    >>> with SessionGuard(open_session(cfg)) as g:
    ...     g.add(g.session.declare_subscriber(key, cb))
    ...     g.add(g.session.liveliness().declare_token(alive))

    ``close()`` undeclares tracked entities in reverse order and closes the session; it is
    idempotent and never raises (errors are logged), so it is safe in ``finally`` blocks.
    """

    def __init__(self, session):
        self.session = session
        self._entities: list = []
        self._lock = threading.Lock()

    @classmethod
    def open(cls, cfg: ZenohConfig | zenoh.Config, **kw: Any) -> "SessionGuard":
        """Guard a session opened by :func:`open_session` (``kw``: its keyword arguments)."""
        return cls(open_session(cfg, **kw))

    def add(self, entity: _Entity) -> _Entity:
        """Track ``entity`` (subscriber, queryable, publisher, token, ...) and return it."""
        with self._lock:
            self._entities.append(entity)
        return entity

    @property
    def closed(self) -> bool:
        return self.session is None

    def close(self) -> None:
        with self._lock:
            ents, self._entities = self._entities, []
            s, self.session = self.session, None
        undeclare_all(reversed(ents))
        close_quietly(s)

    def __enter__(self) -> "SessionGuard":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def install_signal_handlers(stop_event: threading.Event,
                            signals: tuple = (signal.SIGINT, signal.SIGTERM)) -> Callable[[], None]:
    """SIGINT/SIGTERM set ``stop_event`` (clean shutdown); a second SIGINT raises
    KeyboardInterrupt. Returns a function restoring the previous handlers. Outside the main
    thread it does nothing (Python allows handlers only there).

    The event is set from a short-lived thread, not in the handler: the handler runs in the
    main thread wherever it was, and a main thread inside ``stop_event.wait()`` may hold the
    event's (non-reentrant) lock at that instant — ``set()`` there would wait on its own
    thread forever (a router signalled just as it began to wait hung so)."""
    if threading.current_thread() is not threading.main_thread():
        log.debug("install_signal_handlers: not the main thread; skipped")
        return lambda: None
    previous = {}
    signalled = [False]                 # no lock: the handler may interrupt any code

    def handler(signum, frame):
        if (signalled[0] or stop_event.is_set()) and signum == signal.SIGINT:   # is_set() takes no lock
            raise KeyboardInterrupt
        signalled[0] = True
        log.info("received %s; shutting down", signal.Signals(signum).name)
        threading.Thread(target=stop_event.set, name="signal-stop", daemon=True).start()

    for sig in signals:
        previous[sig] = signal.signal(sig, handler)

    def restore() -> None:
        for sig, h in previous.items():
            signal.signal(sig, h)

    return restore


# --------------------------------------------------------------------------- helpers
def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A currently free TCP port on ``host`` (for tests; racy by nature, but unique per call)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def session_summary(session: zenoh.Session) -> dict:
    """zid, connected routers/peers and links of an open session (for logs and ``router``)."""
    info = session.info
    out: dict[str, Any] = {"zid": str(info.zid()), "routers": [str(z) for z in info.routers_zid()],
           "peers": [str(z) for z in info.peers_zid()]}
    try:
        out["links"] = [{"zid": str(lk.zid), "src": str(lk.src), "dst": str(lk.dst)} for lk in info.links()]
    except Exception:  # not in every zenoh build
        pass
    return out


# --------------------------------------------------------------------------- CLI
def add_zenoh_arguments(parser: argparse.ArgumentParser, *, mode_default_help: str = "client") -> None:
    """Add the Zenoh options every ``rayfronts`` subcommand accepts (dests ``zenoh_*``)."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", dest="zenoh_config", metavar="FILE", default=None,
                   help="Zenoh JSON5 config file (e.g. deploy/zenoh/edge-tls.json5); "
                        f"default ${ENV_CONFIG} or Zenoh defaults")
    g.add_argument("--connect", dest="zenoh_connect", metavar="ENDPOINT", action="append", default=None,
                   help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable; "
                        "replaces the config file's)")
    g.add_argument("--listen", dest="zenoh_listen", metavar="ENDPOINT", action="append", default=None,
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; replaces the config file's)")
    g.add_argument("--mode", dest="zenoh_mode", choices=MODES, default=None,
                   help=f"Zenoh mode (default: the config file's, else {mode_default_help})")
    g.add_argument("--certs", dest="zenoh_certs", metavar="DIR", default=None,
                   help=f"directory with ca.pem/cert.pem/key.pem for TLS configs (default ${ENV_CERTS} "
                        f"or {DEFAULT_CERTS_DIR})")
    g.add_argument("--acl", dest="zenoh_acl", metavar="FILE", default=None,
                   help="access_control JSON5 block for router mode (deploy/acl/make_acl.py)")
    g.add_argument("--zenoh-set", dest="zenoh_set", metavar="KEY=JSON", action="append", default=None,
                   help="any Zenoh config key, e.g. transport/link/tx/lease=2000 (repeatable; applied last)")


def parse_zenoh_set(items: list[str] | None) -> dict[str, Any]:
    """``["a/b=1", "c=\"x\""]`` → ``{"a/b": 1, "c": "x"}`` (values are JSON; bare words are strings)."""
    out: dict[str, Any] = {}
    for item in items or ():
        k, raw = split_key_value(item, "--zenoh-set", "key=json")
        try:
            out[k] = json.loads(raw)
        except json.JSONDecodeError:
            out[k] = raw
    return out


def zenoh_config_from_args(args: argparse.Namespace, base: ZenohConfig | None = None) -> ZenohConfig:
    """``base`` (default ``ZenohConfig()``) with the command-line options applied on top."""
    cfg = base if base is not None else ZenohConfig()
    ch: dict[str, Any] = {}
    if getattr(args, "zenoh_config", None):
        ch["config_file"] = args.zenoh_config
    if getattr(args, "zenoh_connect", None):
        ch["connect"] = list(args.zenoh_connect)
    if getattr(args, "zenoh_listen", None):
        ch["listen"] = list(args.zenoh_listen)
    if getattr(args, "zenoh_mode", None):
        ch["mode"] = args.zenoh_mode
    if getattr(args, "zenoh_certs", None):
        ch["certs_dir"] = args.zenoh_certs
    if getattr(args, "zenoh_acl", None):
        ch["acl_file"] = args.zenoh_acl
    if getattr(args, "zenoh_set", None):
        ch["extra"] = {**cfg.extra, **parse_zenoh_set(args.zenoh_set)}
    return replace(cfg, **ch)


def _quietly(call: Callable[[], Any], level: int, failed: str, *args: Any) -> None:
    """``call()``; an exception is logged at ``level`` as ``failed % args`` (formatted only
    then: the repr of an undeclared Zenoh entity is not taken on the way)."""
    try:
        call()
    except Exception as e:  # already undeclared / closed, session gone
        log.log(level, failed + ": %s", *args, e)


def follow_tokens(session: Any, key_expr: str, on_sample: Callable[[Any], None], timeout: float = 1.0) -> Any:
    """Follow the liveliness tokens on ``key_expr``: a subscriber (with history) calls
    ``on_sample`` for every arrival and departure, and the tokens there now are replayed
    through it once (a liveliness get, at most ``timeout`` s). Returns the subscriber; Zenoh
    errors are raised."""
    sub = session.liveliness().declare_subscriber(key_expr, on_sample, history=True)
    for r in session.liveliness().get(key_expr, timeout=timeout):
        if r.ok is not None:
            on_sample(r.ok)
    return sub


def undeclare_all(entities: Iterable[Any]) -> None:
    """Undeclare Zenoh entities (subscribers, queryables, publishers, liveliness tokens) in the
    given order; ``None`` entries are skipped, and one already undeclared or whose session is
    gone is logged at DEBUG, not raised."""
    for ent in entities:
        if ent is not None:
            _quietly(ent.undeclare, logging.DEBUG, "undeclare %r", ent)


def close_quietly(obj: Any, what: str = "the zenoh session") -> None:
    """``obj.close()`` if there is an ``obj`` (a Zenoh session, a recording, a rerun logger);
    a failure is one warning line naming ``what``, not an exception (used at shutdown)."""
    if obj is not None:
        _quietly(obj.close, logging.WARNING, "closing %s failed", what)
