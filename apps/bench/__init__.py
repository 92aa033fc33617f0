"""``rayfronts bench TARGET``: benchmarks that print (and optionally write) JSON.

Targets are resolved lazily like the subcommands, so a missing optional part only
disables its own target.
Each target module provides ``add_arguments(parser)`` and ``run(args) -> dict``; this
module prints the dict as JSON and writes it to ``--json FILE`` when given.
"""
from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

HELP = "throughput / latency / memory benchmarks (JSON output)"

TARGETS = {
    "world": "apps.bench.world",
    "mapper": "apps.bench.mapper",
    "encoder": "apps.bench.encoder",
    "e2e": "apps.bench.e2e",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="target", metavar="TARGET")
    for name, modname in TARGETS.items():
        try:
            mod = importlib.import_module(modname)
        except ImportError as e:
            p = sub.add_parser(name, help=f"[unavailable: {e}]")
            p.set_defaults(_bench=None, _bench_err=str(e))
            continue
        p = sub.add_parser(name, help=getattr(mod, "HELP", ""), description=getattr(mod, "HELP", None))
        mod.add_arguments(p)
        p.add_argument("--json", type=Path, default=None, help="also write the JSON result to this file")
        p.set_defaults(_bench=mod)


def run(args: argparse.Namespace) -> int:
    mod = getattr(args, "_bench", None)
    if mod is None:
        print(f"bench target unavailable: {getattr(args, '_bench_err', 'choose a target')}", file=sys.stderr)
        return 2
    result = mod.run(args)
    text = json.dumps(result, indent=2, sort_keys=True, default=float)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0
