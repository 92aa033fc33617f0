"""The ``rayfronts`` command: one entry point, one subcommand per job (DESIGN §5).

This is an application (``apps``), above the roles: each subcommand lives in the part
that owns it and is resolved lazily by module name, so a robot with only the edge installed
can still run ``rayfronts edge`` and a laptop with only the client ``rayfronts query``. A subcommand module provides::

    HELP = "one line for the overview"
    def add_arguments(parser: argparse.ArgumentParser) -> None: ...
    def run(args: argparse.Namespace) -> int: ...

Config-driven subcommands take ``--config FILE`` and trailing ``key=value`` overrides
(see :mod:`common.config`); unknown keys are errors naming the closest valid key.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

#: subcommand -> module implementing it (imported only when that subcommand runs).
SUBCOMMANDS: dict[str, str] = {
    "demo": "apps.demo",
    "edge": "edge.cli",
    "mapper": "mapper.cli",
    "query": "query_client.cli",
    "router": "common.router",
    "world": "common.world.cli",
    "bench": "apps.bench",
    "eval": "apps.evaluation.cli",
    "models": "edge.models_cli",
}

_FALLBACK_HELP = {
    "demo": "run router, mapper, edge and a query client on the built-in synthetic world",
    "edge": "the onboard process: source -> encoder -> PCA -> Zenoh",
    "mapper": "the base-station process: map, queries, layers, snapshots, rerun",
    "query": "operator queries (one-shot or --watch)",
    "router": "a Zenoh router for sites without zenohd",
    "world": "render the synthetic world to a recording directory and a rerun file",
    "bench": "throughput / latency / memory benchmarks (JSON output)",
    "eval": "the paper's benchmarks (search volume; 3D semantic segmentation)",
    "models": "prepare model directories (download/convert on a machine with internet)",
}


class _Unavailable:
    def __init__(self, name: str, err: Exception):
        self.HELP = f"{_FALLBACK_HELP.get(name, '')} [unavailable: {err}]"
        self._err = err
        self._name = name

    def add_arguments(self, parser):
        parser.add_argument("rest", nargs=argparse.REMAINDER)

    def run(self, args):
        print(f"rayfronts {self._name}: not available here: {self._err}", file=sys.stderr)
        return 2


def _load(name: str):
    try:
        return importlib.import_module(SUBCOMMANDS[name])
    except ImportError as e:
        return _Unavailable(name, e)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rayfronts",
        description="RayFronts over Zenoh: open-set semantic voxels and ray frontiers, "
        "split into edge, mapper and query client.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--log-level", default="INFO", help="logging level (DEBUG, INFO, WARNING, ERROR)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        if only is not None and name != only:
            sub.add_parser(name, help=_FALLBACK_HELP.get(name, ""))
            continue
        mod = _load(name)
        p = sub.add_parser(name, help=getattr(mod, "HELP", _FALLBACK_HELP.get(name, "")),
                           description=getattr(mod, "DESCRIPTION", None) or getattr(mod, "HELP", None),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # Load only the requested subcommand's module (fast start, and a broken optional part
    # does not break the others).
    only = next((a for a in argv if a in SUBCOMMANDS), None)
    parser = build_parser(only)
    args = parser.parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    try:
        return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # config errors etc.: one clear line, no traceback
        from common.config import ConfigError

        if isinstance(e, (ConfigError, FileNotFoundError)):
            print(f"rayfronts {args.command}: error: {e}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
