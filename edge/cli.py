"""``rayfronts edge``: the onboard process (see :mod:`edge.runtime`), and
``rayfronts edge fit-pca`` (see :mod:`edge.fit_pca`)."""
from __future__ import annotations

import argparse
import dataclasses
import logging
import threading

from common.cli_options import split_trailing_options

HELP = "the onboard process: source -> encoder -> PCA -> Zenoh (and `edge fit-pca`)"
DESCRIPTION = """The onboard process: reads posed RGB-D frames from a source, encodes them,
compresses the features with PCA and publishes one frame message per frame on
<prefix>/robots/<robot>/frames. It serves its feature space and holds a liveliness token.

  rayfronts edge robot=r1 source.kind=synthetic --connect tcp/BASE:7447
  rayfronts edge fit-pca --out pca.npz source.kind=replica source.path=... [--frames 50]

Configuration: --config FILE (YAML) plus trailing key=value overrides (keys below)."""

log = logging.getLogger("rayfronts.edge")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.config import describe
    from edge.runtime import edge_config_schema

    parser.add_argument("items", nargs=argparse.REMAINDER, metavar="[fit-pca] KEY=VALUE",
                        help="optional action 'fit-pca', then config overrides (keys below); "
                             "options may follow them")
    _options(parser)
    parser.epilog = "config keys:\n" + describe(edge_config_schema())


def _options(parser, suppress: bool = False) -> None:
    from common.zenoh_session import add_zenoh_arguments

    if suppress:
        parser.argument_default = argparse.SUPPRESS
    parser.add_argument("--config", metavar="FILE", default=None, help="YAML config file (EdgeConfig)")
    parser.add_argument("--robot", default=None, help="robot id (robot)")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="pace the source at HZ frames/s; 0 = as fast as possible (publish.rate_hz)")
    parser.add_argument("--loop", action="store_true", help="replay the source in a loop (publish.loop)")
    parser.add_argument("--record", metavar="DIR", default=None, help="record what is sent (recording.dir)")
    parser.add_argument("--pca", metavar="FILE", default=None, help="PCA basis file (pca.basis)")
    parser.add_argument("--out", metavar="FILE", default=None, help="fit-pca: where to write the basis (.npz)")
    parser.add_argument("--frames", type=int, default=50, help="fit-pca: frames to sample (default 50)")
    parser.add_argument("--samples-per-frame", type=int, default=4096,
                        help="fit-pca: feature vectors sampled per frame (default 4096)")
    add_zenoh_arguments(parser, mode_default_help="client")
    if suppress:
        for a in parser._actions:
            a.default = argparse.SUPPRESS


def build_config(args, overrides):
    from common.config import load_config
    from common.zenoh_session import zenoh_config_from_args
    from edge.runtime import edge_config_schema

    cfg = load_config(edge_config_schema(), args.config, overrides)
    ch = {"zenoh": zenoh_config_from_args(args, cfg.zenoh)}
    if args.robot:
        ch["robot"] = args.robot
    pub = cfg.publish
    if args.rate is not None:
        pub = dataclasses.replace(pub, rate_hz=args.rate)
    if args.loop:
        pub = dataclasses.replace(pub, loop=True)
    ch["publish"] = pub
    if args.record:
        ch["recording"] = dataclasses.replace(cfg.recording, dir=args.record)
    if args.pca:
        ch["pca"] = dataclasses.replace(cfg.pca, basis=args.pca)
    cfg = dataclasses.replace(cfg, **ch)
    from common.keys import check_id

    check_id(cfg.robot or cfg.source.robot)
    return cfg


def run(args: argparse.Namespace) -> int:
    from common.config import ConfigError

    items = split_trailing_options(args, list(args.items or []), _options)
    action = None
    if items and "=" not in items[0]:
        action = items.pop(0)
        if action != "fit-pca":
            raise ConfigError(f"unknown edge action {action!r} (the only action is 'fit-pca')")
    cfg = build_config(args, items)
    if action == "fit-pca":
        from edge.fit_pca import fit_pca

        if not args.out:
            raise ConfigError("fit-pca needs --out FILE")
        fit_pca(cfg, args.out, frames=args.frames, samples_per_frame=args.samples_per_frame)
        return 0
    from common.zenoh_session import install_signal_handlers
    from edge.runtime import EdgeRuntime

    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        return EdgeRuntime(cfg, stop).run()
    finally:
        restore()
