"""``rayfronts mapper``: the base-station process (see :mod:`mapper.service`)."""
from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.cli_options import split_trailing_options

if TYPE_CHECKING:
    from mapper.service_config import MapperConfig

HELP = "the base-station process: map, queries, layers, snapshots, rerun"
DESCRIPTION = """The base-station process. Subscribes to every robot's frames, keeps one shared
RayFronts map, answers queries (rayfronts query / query_client.Client), publishes map layers
and standing-query results, saves and restores snapshots, logs to rerun.

Configuration: --config FILE (YAML) plus trailing key=value overrides, e.g.
  rayfronts mapper preset=online map.vox_size=0.5 snapshots.dir=/var/lib/rayfronts
By default the mapper opens its Zenoh session in router mode (it is the base station's
router); give --mode client --connect ENDPOINT to use a separate router."""

log = logging.getLogger("rayfronts.mapper")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.config import describe
    from mapper.service_config import mapper_config_schema

    parser.add_argument("overrides", nargs=argparse.REMAINDER, metavar="KEY=VALUE",
                        help="config overrides (keys below); options may follow them")
    _options(parser)
    parser.epilog = "config keys:\n" + describe(mapper_config_schema())


def _options(parser, suppress: bool = False) -> None:
    from common.zenoh_session import add_zenoh_arguments

    parser.add_argument("--config", metavar="FILE", default=None, help="YAML config file (MapperConfig)")
    parser.add_argument("--rerun", metavar="FILE", default=None, help="write a rerun recording here (rerun.file)")
    parser.add_argument("--serve-grpc", action="store_true", help="serve the rerun stream over gRPC (rerun.serve_grpc)")
    parser.add_argument("--serve-web", action="store_true",
                        help="serve the rerun web viewer connected to the live stream (rerun.serve_web); "
                             "open the http://... address the mapper prints")
    parser.add_argument("--rerun-bind", metavar="ADDR", default=None,
                        help="address the rerun servers listen on (rerun.bind; default 127.0.0.1, this machine "
                             "only; 0.0.0.0 for a viewer elsewhere)")
    parser.add_argument("--grpc-port", type=int, default=None, help="rerun gRPC port (rerun.grpc_port, default 9876)")
    parser.add_argument("--web-port", type=int, default=None,
                        help="rerun web viewer port (rerun.web_port, default 9090)")
    parser.add_argument("--snapshots", metavar="DIR", default=None, help="snapshot directory (snapshots.dir)")
    parser.add_argument("--device", default=None, help="torch device (device)")
    add_zenoh_arguments(parser, mode_default_help="router")
    if suppress:
        for a in parser._actions:
            a.default = argparse.SUPPRESS


def build_config(args: argparse.Namespace) -> MapperConfig:
    import dataclasses

    from common.zenoh_session import zenoh_config_from_args
    from mapper.service_config import load_mapper_config

    ov = split_trailing_options(args, list(args.overrides or []), _options)
    cfg = load_mapper_config(args.config, ov)
    ch: dict[str, Any] = {"zenoh": zenoh_config_from_args(args, cfg.zenoh)}
    if args.device:
        ch["device"] = args.device
    cfg = dataclasses.replace(cfg, **ch)
    rr: dict[str, Any] = {}
    if args.rerun:
        rr["file"] = args.rerun
    if args.serve_grpc:
        rr["serve_grpc"] = True
    if args.serve_web:
        rr["serve_web"] = True
    if args.rerun_bind:
        rr["bind"] = args.rerun_bind
    if args.grpc_port is not None:
        rr["grpc_port"] = args.grpc_port
    if args.web_port is not None:
        rr["web_port"] = args.web_port
    if rr:
        cfg = dataclasses.replace(cfg, rerun=dataclasses.replace(cfg.rerun, **rr))
    if args.snapshots:
        cfg = dataclasses.replace(cfg, snapshots=dataclasses.replace(cfg.snapshots, dir=args.snapshots))
    return cfg


def check_listen(cfg: MapperConfig) -> None:
    """Fail at once, in one line, when a Zenoh listen endpoint of this (router-mode) mapper is
    already taken, before the map, the text encoder and rerun are loaded."""
    import json

    from common.zenoh_errors import check_listen_free
    from common.zenoh_session import config_mode, make_config

    zc = make_config(cfg.zenoh, default_mode="router")
    mode = config_mode(zc)
    if mode == "client":
        return
    eps = json.loads(zc.get_json("listen/endpoints"))
    if isinstance(eps, dict):
        eps = eps.get(mode, [])
    check_listen_free(eps)


def run(args: argparse.Namespace) -> int:
    if any(i in ("-h", "--help") for i in (args.overrides or [])):  # --help written after key=value items
        p = argparse.ArgumentParser(prog="rayfronts mapper", description=DESCRIPTION,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        add_arguments(p)
        p.print_help()
        return 0
    from common.zenoh_session import install_signal_handlers

    cfg = build_config(args)
    if cfg.text_model_dir and not Path(cfg.text_model_dir).expanduser().is_dir():
        from common.config import ConfigError

        raise ConfigError(f"text_model_dir directory not found: {cfg.text_model_dir} "
                          "(see `rayfronts models check --help`)")
    check_listen(cfg)
    if cfg.rerun.serve_grpc or cfg.rerun.serve_web:  # rerun ports too, before anything loads
        from common.zenoh_errors import check_listen_free

        ports = [cfg.rerun.grpc_port] + ([cfg.rerun.web_port] if cfg.rerun.serve_web else [])
        check_listen_free([f"tcp/{cfg.rerun.bind}:{p}" for p in ports])
    from mapper.service import MapperService

    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        return MapperService(cfg, stop).run()
    finally:
        restore()
