"""The ``rayfronts`` command: one entry point, one subcommand per job (docs/commands.md).

This is an application (``apps``), above the roles: each subcommand lives in the part
that owns it and is resolved lazily by module name, so a robot with only the edge installed
can still run ``rayfronts edge`` and a laptop with only the client ``rayfronts query``. A subcommand module provides::

    HELP = "one line for the overview"
    def add_arguments(parser: argparse.ArgumentParser) -> None: ...
    def run(args: argparse.Namespace) -> int: ...

Config-driven subcommands take ``--config FILE`` and trailing ``key=value`` overrides
(see :mod:`common.config`); unknown keys are errors naming the closest valid key.

Start-up: ``rayfronts --help`` (no subcommand) imports no subcommand module, so it prints in
well under a second (no torch, zenoh or rerun import); ``rayfronts NAME ...`` imports only
NAME's module.

Errors: a user mistake (bad option or config key, missing file or directory, unreachable
router, port in use, empty query, unreadable image, ...) ends the process with exactly one
line on stderr, ``rayfronts NAME: error: <cause and what to do>``, and a non-zero exit code
(2 for usage/config errors, 1 otherwise). Errors from Zenoh are rephrased
(:func:`common.zenoh_errors.explain_zenoh_error`). An unexpected exception (a bug) is also one
line, naming the exception; ``--log-level DEBUG`` or ``RAYFRONTS_TRACEBACK=1`` shows the
traceback. If threads are still running after the error (an open Zenoh session), the
process exits at once with that code instead of hanging at interpreter shutdown.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from typing import NoReturn

#: subcommand -> module implementing it (imported only when that subcommand runs).
SUBCOMMANDS: dict[str, str] = {
    "demo": "apps.demo",
    "edge": "edge.cli",
    "mapper": "mapper.cli",
    "query": "query_client.cli",
    "search": "query_client.search_cli",
    "router": "common.router",
    "world": "synthetic_world.cli",
    "bench": "apps.bench",
    "eval": "apps.evaluation.cli",
    "models": "edge.models_cli",
    "console": "apps.console",
    "export": "apps.export",
}

_FALLBACK_HELP = {
    "demo": "run router, mapper, edge and a query client on the built-in synthetic world",
    "edge": "the onboard process: source -> encoder -> PCA -> Zenoh",
    "mapper": "the base-station process: map, queries, layers, snapshots, rerun",
    "query": "operator queries (one-shot or --watch)",
    "search": "search for planners: found instances, look-next goals, rays beyond the map",
    "router": "a Zenoh router for sites without zenohd",
    "world": "render the synthetic world to a recording directory and a rerun file",
    "bench": "throughput / latency / memory benchmarks (JSON output)",
    "eval": "the paper's benchmarks (search volume; 3D semantic segmentation)",
    "models": "prepare model directories (download/convert on a machine with internet)",
    "console": "operator console in a browser + HTTP/JSON API for planners",
    "export": "write the map as standard files (PLY, OpenVDB, Nav2 map_server, snapshot)",
}


#: exception class names (anywhere in the MRO) that are user mistakes, not bugs; matched by
#: name so the dispatcher need not import the roles' modules to classify their errors.
USER_ERRORS = frozenset({
    "ConfigError", "SourceError", "ModelFileError", "ZenohConnectError", "ZenohListenError", "QueryError",
    "MapperUnavailable", "PCAError", "FeatureSpaceError", "InvalidKey", "RecordingError", "SnapshotError",
    "WireError", "MessageError", "UserError", "ZError", "OSError",
})
#: of those, the ones that are usage errors (exit code 2)
USAGE_ERRORS = frozenset({"ConfigError", "InvalidKey", "UserError"})


class OneLineParser(argparse.ArgumentParser):
    """argparse errors as one line (``rayfronts query: error: ... (see --help)``), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _names(e: BaseException) -> set[str]:
    return {c.__name__ for c in type(e).__mro__}


def error_line(prog: str, e: BaseException) -> tuple[str, int]:
    """(the one stderr line for exception ``e``, exit code)."""
    names = _names(e)
    msg = str(e) or type(e).__name__
    if isinstance(e, OSError) and getattr(e, "strerror", None) and getattr(e, "filename", None):
        msg = f"{e.strerror}: {e.filename}"
    if "ZError" in names or ".rs:" in msg or "Zenoh" in type(e).__name__:
        from common.zenoh_errors import explain_zenoh_error

        msg = explain_zenoh_error(msg)
    msg = " ".join(msg.split())  # one line, whatever the message held
    if names & USER_ERRORS:
        return f"{prog}: error: {msg}", (2 if names & USAGE_ERRORS else 1)
    line = (f"{prog}: internal error: {type(e).__name__}: {msg} "
            "(rerun with --log-level DEBUG for the traceback)")
    return line, 1


class _Unavailable:
    def __init__(self, name: str, err: Exception):
        self.HELP = f"{_FALLBACK_HELP.get(name, '')} [unavailable: {err}]"
        self._err = err
        self._name = name

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("rest", nargs=argparse.REMAINDER)

    def run(self, args: argparse.Namespace) -> int:
        print(f"rayfronts {self._name}: not available here: {self._err}", file=sys.stderr)
        return 2


def _load(name: str):
    try:
        return importlib.import_module(SUBCOMMANDS[name])
    except ImportError as e:
        return _Unavailable(name, e)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="rayfronts",
        description="RayFronts over Zenoh: open-set semantic voxels and ray frontiers, "
        "split into edge, mapper and query client.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--log-level", default="INFO", help="logging level (DEBUG, INFO, WARNING, ERROR)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    for name in SUBCOMMANDS:
        if name != only:  # help line only: the module is imported when its subcommand runs
            sub.add_parser(name, help=_FALLBACK_HELP.get(name, ""))
            continue
        mod = _load(name)
        p = sub.add_parser(name, help=getattr(mod, "HELP", _FALLBACK_HELP.get(name, "")),
                           description=getattr(mod, "DESCRIPTION", None) or getattr(mod, "HELP", None),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def _exit_if_threads_linger(code: int) -> None:
    """After an error line: a process whose Zenoh session or worker threads are still alive
    would hang at interpreter exit (Zenoh 1.10 pitfall), so leave at once with ``code``."""
    import threading

    if threading.active_count() > 1:
        sys.stdout.flush()
        sys.stderr.flush()
        logging.shutdown()
        os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """Run ``rayfronts ARGV...`` and return its exit code. As the process's entry point
    (``argv`` None: the command line) an error leaves at once when threads linger
    (:func:`_exit_if_threads_linger`); called with ``argv`` (tests, other programs) it only
    returns the code, never ends the caller's process."""
    entry_point = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    # Load only the requested subcommand's module (fast start, and a broken optional part
    # does not break the others); none at all for the overview.
    only = next((a for a in argv if a in SUBCOMMANDS), None)
    parser = build_parser(only)
    args = parser.parse_args(argv)
    level = str(args.log_level).upper()
    logging.basicConfig(level=getattr(logging, level, logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    prog = f"rayfronts {args.command}"
    try:
        return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except SystemExit:
        raise
    except Exception as e:
        if level == "DEBUG" or os.environ.get("RAYFRONTS_TRACEBACK"):
            raise
        line, code = error_line(prog, e)
        print(line, file=sys.stderr)
        if entry_point:
            _exit_if_threads_linger(code)
        return code


if __name__ == "__main__":
    sys.exit(main())
