"""``rayfronts edge``: the onboard process (see :mod:`edge.runtime`), and
``rayfronts edge fit-pca`` (see :mod:`edge.fit_pca`)."""
from __future__ import annotations

import argparse
import dataclasses
import logging
import threading
from typing import TYPE_CHECKING, Any

from common.cli_options import split_trailing_options

if TYPE_CHECKING:
    from edge.config import EdgeConfig

HELP = "the onboard process: source -> encoder -> PCA -> Zenoh (and `edge fit-pca`)"
DESCRIPTION = """The onboard process: reads posed RGB-D frames from a source, encodes them,
compresses the features with PCA and publishes one frame message per frame on
<prefix>/robots/<robot>/frames. It serves its feature space and holds a liveliness token.

  rayfronts edge robot=r1 source.kind=synthetic --connect tcp/BASE:7447
  rayfronts edge fit-pca --out pca.npz source.kind=replica source.path=... [--frames 50]
  rayfronts edge --list-topics source.ros_connect=[tcp/127.0.0.1:7447]   # a ROS 2 robot's topics
  rayfronts edge robot=r1 source.kind=ros2 source.ros_connect=[tcp/127.0.0.1:7447] \\
      source.rgb_topic=/camera/color/image_raw source.depth_topic=/camera/depth/image_rect_raw \\
      source.camera_info_topic=/camera/depth/camera_info source.pose_topic=/odom --connect tcp/BASE:7447

Configuration: --config FILE (YAML) plus trailing key=value overrides (keys below)."""

FIT_PCA_DESCRIPTION = """Fit the PCA basis the edge compresses its features with, offline, over frames of
a source, so every edge and the mapper share one fixed feature space. Writes a .npz basis
that `rayfronts edge --pca FILE` (pca.basis) then uses.

  rayfronts edge fit-pca --out pca.npz source.kind=replica source.path=/data/replica/room0 --frames 50

The source, encoder and PCA size come from the same config keys as `rayfronts edge`
(source.*, encoder.*, pca.out_dim; see `rayfronts edge --help`)."""

log = logging.getLogger("rayfronts.edge")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.config import describe
    from edge.config import edge_config_schema

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
    parser.add_argument("--list-topics", action="store_true",
                        help="list the ROS 2 topics a robot publishes over Zenoh (rmw_zenoh graph tokens and data "
                             "keys seen; source.ros_keys, source.ros_domain, source.ros_connect) and exit")
    parser.add_argument("--list-seconds", type=float, default=2.0, metavar="S",
                        help="--list-topics: how long to watch the data keys (default 2 s)")
    add_zenoh_arguments(parser, mode_default_help="client")
    if suppress:
        for a in parser._actions:
            a.default = argparse.SUPPRESS


def _fit_pca_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rayfronts edge fit-pca", description=FIT_PCA_DESCRIPTION,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides (source.*, encoder.*, pca.*)")
    p.add_argument("--out", metavar="FILE", required=True, help="where to write the basis (.npz)")
    p.add_argument("--frames", type=int, default=50, help="frames to sample (default 50)")
    p.add_argument("--samples-per-frame", type=int, default=4096,
                   help="feature vectors sampled per frame (default 4096)")
    p.add_argument("--config", metavar="FILE", default=None, help="YAML config file (EdgeConfig)")
    return p


def _wants_help(items: list[str]) -> bool:
    return any(i in ("-h", "--help") for i in items)


def check_inputs(cfg: EdgeConfig) -> None:
    """Check the files and directories the config names before anything connects, so a wrong
    path is one error line and the robot never appears on the network. Raises
    ConfigError / SourceError / ModelFileError naming the key and the path."""
    from pathlib import Path

    from common.config import ConfigError

    src = cfg.source
    if src.kind == "ros2":  # live topics, no path: the source checks its options without connecting
        from edge.sources import open_source

        open_source(src)
    if src.kind not in ("synthetic", "ros2", "sim_camera"):
        if not src.path:
            raise ConfigError(f"source.kind={src.kind} needs source.path (the dataset / recording / bag location)")
        if not Path(src.path).expanduser().exists():
            raise ConfigError(f"source.path not found: {src.path} (source.kind={src.kind})")
        if src.kind != "rosbag":  # directory-based sources check their layout cheaply when opened
            from edge.sources import open_source

            close = getattr(open_source(src), "close", None)
            if callable(close):
                close()
    if cfg.pca.basis not in ("", "map") and not Path(cfg.pca.basis).expanduser().is_file():
        raise ConfigError(f"pca.basis file not found: {cfg.pca.basis} (fit one with `rayfronts edge fit-pca`)")
    enc = cfg.encoder
    for key, d in (("encoder.model_dir", enc.model_dir), ("encoder.text_model_dir", enc.text_model_dir)):
        if d and not Path(d).expanduser().is_dir():
            raise ConfigError(f"{key} directory not found: {d} (see `rayfronts models check --help`)")
    if enc.kind == "naradio":
        from encoders.files import find_radio_checkpoint

        find_radio_checkpoint(enc.model, enc.model_dir or None, enc.checkpoint)


def build_config(args: argparse.Namespace, overrides: list[str]) -> EdgeConfig:
    """The edge's config: schema defaults, ``--config`` YAML, ``key=value`` ``overrides``, then the options."""
    from common.config import load_config
    from common.zenoh_session import zenoh_config_from_args
    from edge.config import edge_config_schema

    cfg = load_config(edge_config_schema(), args.config, overrides)
    ch: dict[str, Any] = {"zenoh": zenoh_config_from_args(args, cfg.zenoh)}
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

    raw = list(args.items or [])
    if raw and raw[0] == "fit-pca" and _wants_help(raw):
        _fit_pca_parser().print_help()
        return 0
    if _wants_help(raw):  # --help written after key=value items
        p = argparse.ArgumentParser(prog="rayfronts edge", description=DESCRIPTION,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        add_arguments(p)
        p.print_help()
        return 0
    items = split_trailing_options(args, raw, _options)
    action = None
    if items and "=" not in items[0]:
        action = items.pop(0)
        if action != "fit-pca":
            raise ConfigError(f"unknown edge action {action!r} (the only action is 'fit-pca')")
    cfg = build_config(args, items)
    if getattr(args, "list_topics", False):
        from edge.sources.ros2 import format_topics, list_topics

        print(format_topics(list_topics(cfg.source, cfg.zenoh, seconds=args.list_seconds)))
        return 0
    check_inputs(cfg)
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
        rc = EdgeRuntime(cfg, stop).run()
    finally:
        restore()
    # Leave without interpreter finalisation, whatever the exit code. The runtime has closed its
    # recording and Zenoh session; a worker thread still inside torch or a Zenoh callback when
    # Python finalises is killed with a forced unwind, and the process aborts with SIGABRT
    # ("FATAL: exception not rethrown") instead of returning its code (seen: CI, rc -6 after a
    # clean "done").
    import os
    import sys

    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)
