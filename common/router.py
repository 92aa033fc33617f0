"""``rayfronts router``: a Zenoh router for sites without ``zenohd``.

A Zenoh session in router mode relays pub/sub, queries and liveliness between the
clients (edges, laptops, a mapper running as client). With a TLS config and ``--acl`` it is
the site's authenticated, access-controlled entry point (see ``deploy/README.md``).
Runs until SIGINT/SIGTERM, then closes the session and exits with status 0.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import threading

from common.zenoh_session import (
    add_zenoh_arguments,
    install_signal_handlers,
    make_config,
    open_session,
    session_summary,
    zenoh_config_from_args,
)

HELP = "a Zenoh router for sites without zenohd"
DESCRIPTION = """\
Run a Zenoh router (no zenohd needed). Robots and laptops connect to it as clients.

examples:
  rayfronts router --listen tcp/0.0.0.0:7447
  rayfronts router --zenoh-config deploy/zenoh/router-tls.json5 --certs /etc/rayfronts/certs \\
                   --acl /etc/rayfronts/acl.json5
"""
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"

log = logging.getLogger("rayfronts.router")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_zenoh_arguments(parser, mode_default_help="router")
    parser.add_argument("--status-every", type=float, default=0.0, metavar="S",
                        help="log the connected clients/peers every S seconds (0 = only at start)")


def run(args: argparse.Namespace) -> int:
    cfg = zenoh_config_from_args(args)
    if cfg.mode and cfg.mode != "router":
        print(f"rayfronts router: --mode must be 'router' (got {cfg.mode!r})", file=sys.stderr)
        return 2
    if not cfg.listen and not cfg.config_file:
        cfg.listen = [DEFAULT_LISTEN]
    zc = make_config(cfg, default_mode="router")
    if json.loads(zc.get_json("mode")) != "router":
        print("rayfronts router: the config file sets a mode other than 'router'; "
              "pass --mode router to override", file=sys.stderr)
        return 2
    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        session = open_session(zc)
    except Exception as e:
        from common.zenoh_errors import explain_zenoh_error

        restore()
        print(f"rayfronts router: error: {explain_zenoh_error(e, cfg.listen)}", file=sys.stderr)
        return 1
    try:
        endpoints = json.loads(zc.get_json("listen/endpoints"))
        if isinstance(endpoints, dict):
            endpoints = endpoints.get("router", [])
        acl = json.loads(zc.get_json("access_control/enabled"))
        print(f"rayfronts router: zid {session.zid()} listening on {', '.join(endpoints) or '(none)'}"
              f"{' (access control on)' if acl else ''}; Ctrl-C to stop", flush=True)
        every = float(getattr(args, "status_every", 0.0) or 0.0)
        while not stop.wait(every if every > 0 else 3600.0):
            if every > 0:
                log.info("router status: %s", session_summary(session))
    finally:
        try:
            session.close()
        finally:
            restore()
    print("rayfronts router: stopped", flush=True)
    return 0
