"""``rayfronts bench TARGET``: benchmarks that print (and optionally write) JSON.

Targets are resolved lazily like the subcommands, so a missing optional part only
disables its own target.
Each target module provides ``add_arguments(parser)`` and ``run(args) -> dict``; this
module prints the dict as JSON and writes it to ``--json FILE`` when given. Every result
gets a ``meta`` block (:mod:`apps.bench.meta`: machine, threads, load before / after,
process wall and CPU time, the target's timed sections) and, where it counts frames, CPU
ms per frame beside frames/s, so no target repeats that code.

Two commands sit beside the targets:

* ``rayfronts bench all --json DIR`` runs every benchmark the README quotes (:data:`ALL`),
  each in its own process (so one target's torch thread setting cannot leak into the
  next), writes ``DIR/<name>.json`` per run plus ``DIR/table.md``, and prints the table;
  ``--quick`` runs tiny versions (a smoke test), ``--only a,b`` a subset.
* ``rayfronts bench table DIR [--readme README.md]`` renders the table from those JSONs
  (:mod:`apps.bench.report`) and optionally replaces the README's generated block.
"""
from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path

HELP = "throughput / latency / memory benchmarks (JSON output)"

TARGETS = {
    "world": "apps.bench.world",
    "mapper": "apps.bench.mapper",
    "encoder": "apps.bench.encoder",
    "e2e": "apps.bench.e2e",
    "gpu": "apps.bench.gpu",
    "fleet": "apps.bench.fleet",
    "query": "apps.bench.query",
    "search": "apps.bench.search",
    "faults": "apps.bench.faults",
    "mission": "apps.bench.mission",
}

#: (name, argv, quick argv) of every figure the README quotes, in table order. A name's
#: JSON is ``DIR/<name>.json``; entries whose target is not in :data:`TARGETS` are skipped.
ALL: list[tuple[str, list[str], list[str]]] = [
    ("mapper_throughput", ["mapper", "--preset", "throughput", "--frames", "300"],
     ["mapper", "--preset", "throughput", "--frames", "16"]),
    ("mapper_online", ["mapper", "--preset", "online", "--frames", "100"],
     ["mapper", "--preset", "online", "--frames", "4"]),
    ("mapper_kernels_vs_torch", ["mapper", "--preset", "throughput", "--frames", "150", "--compare", "kernels"],
     ["mapper", "--preset", "throughput", "--frames", "10", "--compare", "kernels"]),
    ("mapper_pipeline_vs_sequential", ["mapper", "--preset", "throughput", "--frames", "300", "--compare", "pipeline"],
     ["mapper", "--preset", "throughput", "--frames", "10", "--compare", "pipeline"]),
    ("mapper_growth", ["mapper", "--preset", "throughput", "--frames", "2400", "--growing"],
     ["mapper", "--preset", "throughput", "--frames", "24", "--growing", "--window", "8"]),
    ("world", ["world"], ["world", "--frames", "2"]),
    ("encoder_radio_b", ["encoder", "--model", "radio_v2.5-b", "--frames", "5"],
     ["encoder", "--model", "radio_v2.5-b", "--frames", "1", "--warmup", "0", "--resolution", "64x64"]),
    ("e2e", ["e2e"], ["e2e", "--frames", "6", "--only", "stream", "--resolution", "64x64"]),
    ("query", ["query", "--voxels", "100k,1M,5M"], ["query", "--voxels", "20k", "--queries", "3", "--changes", "2",
                                                    "--rays", "200"]),
    ("search", ["search", "--voxels", "100k,1M,5M"], ["search", "--voxels", "20k", "--queries", "2", "--rays", "200",
                                                      "--frames", "2", "--standing-rounds", "1"]),
    ("e2e_radio_b", ["e2e", "--model", "radio_v2.5-b", "--only", "stream", "--frames", "12"],
     ["e2e", "--model", "radio_v2.5-b", "--only", "stream", "--frames", "3", "--resolution", "64x64"]),
    ("e2e_480x640", ["e2e", "--resolution", "480x640", "--only", "stream"],
     ["e2e", "--resolution", "96x128", "--only", "stream", "--frames", "4"]),
    ("fleet", ["fleet", "--robots", "1,2,4", "--fake-ids", "1000"],
     ["fleet", "--robots", "1,2", "--frames", "8", "--warmup", "1", "--seconds", "3"]),
    ("faults", ["faults"], ["faults", "--only", "decode"]),
    ("mission", ["mission", "--frames", "12000"],
     ["mission", "--frames", "60", "--resolution", "64x64", "--queries", "1", "--query-source", "random"]),
]


def _meta():
    from apps.bench import meta
    return meta


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
        p.set_defaults(_bench=mod, _parser=p)
    p = sub.add_parser("all", help="run every benchmark the README quotes; one JSON per run plus table.md")
    p.add_argument("--json", type=Path, required=True, metavar="DIR", help="directory for the JSONs and table.md")
    p.add_argument("--quick", action="store_true", help="tiny runs (smoke test; figures meaningless)")
    p.add_argument("--only", default="", help=f"comma-separated subset of: {', '.join(n for n, _, _ in ALL)}")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per run before it is killed (default 3600)")
    p.set_defaults(_bench="all")
    p = sub.add_parser("table", help="render the README benchmark table from a `bench all` directory")
    p.add_argument("dir", type=Path, help="directory written by `rayfronts bench all --json DIR`")
    p.add_argument("--readme", type=Path, default=None,
                   help="replace the generated block of this README (between the bench-table markers)")
    p.set_defaults(_bench="table")


def _dump(result: dict) -> str:
    return json.dumps(result, indent=2, sort_keys=True, default=float)


def run(args: argparse.Namespace) -> int:
    mod = getattr(args, "_bench", None)
    if mod == "all":
        return run_all(args.json, quick=args.quick, only=args.only, timeout=args.timeout)
    if mod == "table":
        return run_table(args.dir, args.readme)
    if mod is None:
        print(f"bench target unavailable: {getattr(args, '_bench_err', 'choose a target')}", file=sys.stderr)
        return 2
    meta = _meta()
    with meta.run_meta(_argv_of(args)) as m:
        result = mod.run(args)
    result = meta.attach(result, m)
    text = _dump(result)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """The command line of this run: ``sys.argv`` from ``bench`` on when this process was
    started as ``rayfronts bench TARGET ...``, else the options that differ from their
    defaults (a call through ``apps.cli.main([...])``)."""
    av = list(sys.argv[1:])
    if "bench" in av and args.target in av[av.index("bench"):]:
        return ["rayfronts"] + av[av.index("bench"):]
    out = ["rayfronts", "bench", args.target]
    p = getattr(args, "_parser", None)
    for a in (p._actions if p is not None else []):
        if not a.option_strings or a.dest in ("help", "json"):
            continue
        v = getattr(args, a.dest, a.default)
        if v == a.default:
            continue
        if isinstance(a, argparse._StoreTrueAction):
            out.append(a.option_strings[-1])
        elif isinstance(v, (list, tuple)) and a.nargs not in (None, 1):
            out += [a.option_strings[-1], *map(str, v)]
        else:
            out += [a.option_strings[-1], "x".join(map(str, v)) if isinstance(v, tuple) else str(v)]
    return out


def run_all(out_dir: Path, quick: bool = False, only: str = "", timeout: float = 3600.0) -> int:
    """Run :data:`ALL` (see module docstring); returns 0 when every selected run succeeded."""
    from apps.bench import report

    want = [s.strip() for s in only.split(",") if s.strip()]
    names = [n for n, _, _ in ALL]
    bad = [w for w in want if w not in names]
    if bad:
        print(f"rayfronts bench all: error: unknown run(s) {', '.join(bad)}; choose from {', '.join(names)}",
              file=sys.stderr)
        return 2
    out_dir.mkdir(parents=True, exist_ok=True)
    status: dict[str, dict] = {}
    for name, full, small in ALL:
        if want and name not in want:
            continue
        argv = small if quick else full
        if argv[0] not in TARGETS:
            status[name] = {"skipped": f"target {argv[0]!r} not available"}
            continue
        path = out_dir / f"{name}.json"
        cmd = [sys.executable, "-m", "apps.cli", "bench", *argv, "--json", str(path)]
        print(f"[bench all] {name}: rayfronts bench {' '.join(argv)}", file=sys.stderr, flush=True)
        t = time.perf_counter()
        try:
            p = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=timeout)
            rc, err = p.returncode, p.stderr
        except subprocess.TimeoutExpired:
            rc, err = 124, f"killed after {timeout:.0f} s"
        status[name] = {"rc": rc, "wall_s": round(time.perf_counter() - t, 1), "command": ["rayfronts", "bench", *argv]}
        if rc != 0:
            status[name]["error"] = (err or "").strip().splitlines()[-1:] or [""]
            print(f"[bench all] {name} failed (rc {rc}): {status[name]['error'][0]}", file=sys.stderr, flush=True)
    if want and (out_dir / "all.json").exists():  # a subset rerun keeps the other runs' records
        try:
            prev = json.loads((out_dir / "all.json").read_text())
            status = {**prev.get("runs", {}), **status}
        except (ValueError, OSError):
            pass
    order = [n for n in names if n in status] + [n for n in status if n not in names]
    # "order": the table order (the JSON's keys are sorted)
    (out_dir / "all.json").write_text(_dump({"quick": quick, "order": order, "runs": status}) + "\n")
    table = report.render(out_dir)
    (out_dir / "table.md").write_text(table)
    print(table)
    return 0 if all(s.get("rc", 0) == 0 for s in status.values()) else 1


def run_table(src: Path, readme: Path | None) -> int:
    from apps.bench import report

    if not src.is_dir():
        print(f"rayfronts bench table: error: {src} is not a directory (run `rayfronts bench all --json {src}`)",
              file=sys.stderr)
        return 2
    table = report.render(src)
    print(table)
    if readme is not None:
        report.replace_block(readme, table)
    return 0
