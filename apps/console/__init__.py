"""``rayfronts console``: the operator's console in a browser and an HTTP API any planner can
call (docs/commands.md). A Zenoh client of the mapper like ``rayfronts query``."""
from __future__ import annotations

import argparse
import os
import socket
import sys

HELP = "operator console in a browser + HTTP/JSON API for planners"
DESCRIPTION = """Serve the operator console (query/search box, found instances, look-next goals,
robots' state, the mapper's web viewer) and a JSON API (/api/query, /api/search, /api/occupancy/*,
/api/stats, /api/snapshot, server-sent-event streams; OpenAPI at /openapi.json, docs at /docs).

  rayfronts console --connect tcp/BASE:7447                       # http://127.0.0.1:8080
  rayfronts console --connect tcp/BASE:7447 --http 0.0.0.0:8443 --token SECRET \\
      --tls-cert cert.pem --tls-key key.pem                       # open https://BASE:8443/?token=SECRET

Binds loopback by default; any other address needs --token (or $RAYFRONTS_CONSOLE_TOKEN) and
HTTPS (--tls-cert/--tls-key; --insecure-http to serve plain HTTP anyway). Opening the page as
/?token=TOKEN sets an HttpOnly cookie; programs send 'Authorization: Bearer TOKEN'."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.zenoh_session import add_zenoh_arguments

    parser.add_argument("--http", default="127.0.0.1:8080", metavar="HOST:PORT",
                        help="address the console listens on (default 127.0.0.1:8080, loopback only)")
    parser.add_argument("--token", default=None, help="access token (default $RAYFRONTS_CONSOLE_TOKEN); "
                                                      "required when --http is not a loopback address")
    parser.add_argument("--tls-cert", default=None, metavar="PEM", help="serve HTTPS with this certificate")
    parser.add_argument("--tls-key", default=None, metavar="PEM", help="the certificate's private key")
    parser.add_argument("--insecure-http", action="store_true",
                        help="serve plain HTTP on a non-loopback --http (refused without it: the token would "
                             "travel in clear); a trusted network only")
    parser.add_argument("--viewer-url", default=None, metavar="URL",
                        help="the mapper's rerun web viewer (rayfronts mapper --serve-web) to embed in the page")
    parser.add_argument("--rate-limit", type=int, default=600, help="requests per minute per client address "
                                                                    "(default 600; 0 = no limit)")
    parser.add_argument("--max-streams", type=int, default=32,
                        help="open event streams (standing searches/queries) in all (default 32; 0 = no limit)")
    parser.add_argument("--max-streams-per-client", type=int, default=4,
                        help="open event streams per client address (default 4; 0 = no limit)")
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds to wait for the mapper (default 20)")
    parser.add_argument("--prefix", default=None, help="key-space prefix (default rayfronts)")
    add_zenoh_arguments(parser, mode_default_help="client")


def run(args: argparse.Namespace) -> int:
    from apps.console.security import ENV_TOKEN, ConsoleConfigError, parse_http, require_safe_listen

    token = args.token or os.environ.get(ENV_TOKEN) or None
    try:
        host, port = parse_http(args.http)
        if bool(args.tls_cert) != bool(args.tls_key):
            raise ConsoleConfigError("give both --tls-cert and --tls-key (or neither)")
        require_safe_listen(host, token, bool(args.tls_cert), args.insecure_http)
        if args.max_streams < 0 or args.max_streams_per_client < 0:
            raise ConsoleConfigError("--max-streams and --max-streams-per-client must be >= 0 (0 = no limit)")
        for f in (args.tls_cert, args.tls_key):
            if f and not os.path.isfile(f):
                raise ConsoleConfigError(f"no such file: {f}")
        if args.timeout <= 0:
            raise ConsoleConfigError(f"--timeout must be > 0 seconds (got {args.timeout})")
    except ConsoleConfigError as e:
        print(f"rayfronts console: error: {e}", file=sys.stderr)
        return 2
    try:
        import uvicorn

        from apps.console.app import create_app
    except ImportError as e:
        print(f"rayfronts console: error: {e.name} is missing: pip install '.[console]'", file=sys.stderr)
        return 1
    from query_client.cli import connect_client

    client = connect_client(args, "console")
    if client is None:
        return 1
    with client:
        app = create_app(client, token=token, viewer_url=args.viewer_url, rate_per_minute=args.rate_limit,
                         timeout=args.timeout, tls=bool(args.tls_cert), max_streams=args.max_streams,
                         max_streams_per_client=args.max_streams_per_client)
        scheme = "https" if args.tls_cert else "http"
        shown = f"[{host}]" if ":" in host else host
        try:   # listen first: the address line is printed once a connection can no longer be refused
            sock = _listen(host, port)
        except OSError as e:
            print(f"rayfronts console: error: cannot listen on {host}:{port} (in use?): {e.strerror}", file=sys.stderr)
            return 1
        config = uvicorn.Config(app, log_level="warning", ssl_certfile=args.tls_cert, ssl_keyfile=args.tls_key,
                                timeout_graceful_shutdown=2)
        print(f"console at {scheme}://{shown}:{sock.getsockname()[1]}/", flush=True)
        try:
            uvicorn.Server(config).run(sockets=[sock])
        except SystemExit as e:
            return int(e.code or 1)
        finally:
            sock.close()
    return 0


def _listen(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` and listening (port 0: any free one)."""
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(fam, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(2048)
    except OSError:
        sock.close()
        raise
    return sock
