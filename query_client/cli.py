"""``rayfronts query "water tower"``: operator queries (one-shot or ``--watch``)."""
from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from common.messages import QueryResult
    from query_client.client import Client

HELP = "operator queries (one-shot or --watch)"
DESCRIPTION = """Send an open-vocabulary query to the mapper and print the best answers:
voxel clusters (position, size, score) inside the mapped range, semantic rays (origin,
direction, score) beyond it, and the search volume their cones span.

  rayfronts query "water tower" --connect tcp/BASE:7447
  rayfronts query --image door.jpg --top-k 3 --json
  rayfronts query "vehicle" --watch            # standing query, prints each refresh
  rayfronts query "chimney" --rerun out.rrd    # also view the answer in rerun"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.zenoh_session import add_zenoh_arguments

    parser.add_argument("text", nargs="?", default=None, help="the query text (omit with --image / --stats)")
    parser.add_argument("--image", metavar="PATH", default=None, help="query with an image file (JPEG/PNG)")
    parser.add_argument("--top-k", type=int, default=5, help="answers per kind (clusters, rays), default 5")
    parser.add_argument("--watch", action="store_true", help="standing query: print each refresh until Ctrl-C")
    parser.add_argument("--json", action="store_true", help="print the full result as JSON")
    parser.add_argument("--softmax", action="store_true", help="scores as softmax against generic negatives")
    parser.add_argument("--stats", action="store_true", help="print the mapper's stats instead of querying")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the mapper (default 10)")
    parser.add_argument("--prefix", default=None, help="key-space prefix (default rayfronts)")
    parser.add_argument("--rerun", metavar="FILE", default=None, help="write the answer to a rerun file")
    parser.add_argument("--rerun-connect", metavar="URL", default=None,
                        help="send the answer to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy")
    add_zenoh_arguments(parser, mode_default_help="client")


def format_result(r: QueryResult, top_k: int = 5) -> str:
    """The answer as the text the CLI prints: the ``top_k`` best voxel clusters and rays (metres)."""
    lines = [f"query {r.query!r}  ({r.frames_mapped} frames mapped, {r.timings.get('total', 0.0):.0f} ms)"]
    if len(r.cluster_xyz):
        lines.append("  voxel clusters (in range):")
        lines.append("    #  score     x        y        z     voxels  size (m)")
        for i in range(min(top_k, len(r.cluster_xyz))):
            x, y, z = r.cluster_xyz[i]
            ex = r.cluster_extent[i]
            lines.append(f"   {i + 1:2d}  {r.cluster_score[i]:.4f} {x:8.2f} {y:8.2f} {z:8.2f} "
                         f"{int(r.cluster_size[i]):6d}  {ex[0]:.1f}x{ex[1]:.1f}x{ex[2]:.1f}")
    else:
        lines.append("  no voxel answers")
    if len(r.ray_origin):
        lines.append("  rays (beyond range):")
        lines.append("    #  score     origin (x, y, z)            direction (x, y, z)")
        for i in range(min(top_k, len(r.ray_origin))):
            o, d = r.ray_origin[i], r.ray_direction[i]
            lines.append(f"   {i + 1:2d}  {r.ray_score[i]:.4f}  ({o[0]:7.2f}, {o[1]:7.2f}, {o[2]:6.2f})"
                         f"   ({d[0]:+.3f}, {d[1]:+.3f}, {d[2]:+.3f})")
        lines.append(f"  search volume of the best rays' cones: {r.search_volume_m3:,.0f} m³")
    else:
        lines.append("  no ray answers")
    return "\n".join(lines)


def log_result_rerun(r: QueryResult, file: str | None = None, url: str | None = None,
                     layers: dict | None = None) -> None:
    """Log a query answer (and optionally map layers) to a rerun file or viewer."""
    import numpy as np
    import rerun as rr

    from common import rerun_paths as paths

    rec = rr.RecordingStream("rayfronts_query")
    if file:
        rec.save(file)
    if url:
        rec.connect_grpc(url)
    rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    if layers and "voxels" in layers:
        v = layers["voxels"]
        rec.log(paths.MAP_VOXELS, rr.Points3D(v["xyz"], colors=v["rgb"]))
    base = paths.QUERIES(paths.entity_name(r.query))
    if len(r.cluster_xyz):
        rec.log(f"{base}/clusters", rr.Boxes3D(centers=r.cluster_xyz, half_sizes=np.asarray(r.cluster_extent) / 2,
                                               labels=[f"{r.query} {s:.3f}" for s in r.cluster_score]))
    if len(r.ray_origin):
        rec.log(f"{base}/rays", rr.Arrows3D(origins=r.ray_origin, vectors=np.asarray(r.ray_direction) * 20.0,
                                            labels=[f"{s:.3f}" for s in r.ray_score]))
    rec.flush()
    rec.disconnect()


def check_inputs(args: argparse.Namespace) -> dict:
    """The user's mistakes that need no mapper, found before connecting (ConfigError, one line);
    returns the ``Client.query`` keywords (``query_client.vocabulary.query_fields``)."""
    from common.config import ConfigError
    from query_client.vocabulary import query_fields

    if args.text is None and args.image is None and not args.stats:
        raise ConfigError('give a query text, --image PATH or --stats, e.g. rayfronts query "water tower"')
    kw = query_fields(args.text, args.image, args.top_k)
    if args.timeout <= 0:
        raise ConfigError(f"--timeout must be > 0 seconds (got {args.timeout})")
    if args.rerun or args.rerun_connect:
        import importlib.util

        if importlib.util.find_spec("rerun") is None:  # the [client] install has no rerun
            raise ConfigError("--rerun / --rerun-connect need the rerun SDK, which this install lacks: "
                              "pip install rerun-sdk (or install the [mapper] extra)")
    if args.image is not None:
        import os

        from query_client.client import QueryError, read_query_image

        if not os.path.isfile(args.image):
            raise ConfigError(f"image file not found: {args.image}")
        try:  # size and file type here (no image library needed); the mapper decodes the pixels
            read_query_image(args.image)
        except QueryError as e:
            raise ConfigError(str(e)) from None
    return kw


def connect_client(args: argparse.Namespace, command: str) -> Client | None:
    """A :class:`Client` from the CLI's Zenoh options (``--timeout`` s bounds the connect), or
    ``None`` after printing the one-line ``rayfronts COMMAND: error: ...``."""
    from common.zenoh_session import ZenohConfig, ZenohConnectError, zenoh_config_from_args
    from query_client.client import Client

    zc = zenoh_config_from_args(args, ZenohConfig(connect_timeout_ms=int(args.timeout * 1000)))
    zlog = logging.getLogger("common.zenoh_session")
    level = zlog.level
    zlog.setLevel(logging.ERROR)  # the bounded retries need no "retrying" line: the outcome is one line
    try:
        return Client(zc, prefix=args.prefix, timeout=args.timeout)
    except ZenohConnectError as e:
        from common.zenoh_errors import explain_zenoh_error

        print(f"rayfronts {command}: error: {explain_zenoh_error(e, zc.connect)} (waited {args.timeout:g} s)",
              file=sys.stderr)
        return None
    finally:
        zlog.setLevel(level)


def watch_until_signal(start: Callable[[], Any]) -> None:
    """Start a standing query/search (``start()`` returns a handle with ``cancel()``), keep it
    until SIGINT/SIGTERM, then cancel it."""
    from common.zenoh_session import install_signal_handlers

    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        handle = start()
        while not stop.wait(0.5):
            pass
        handle.cancel()
    finally:
        restore()


def warn_missing(r, command: str = "query") -> None:
    """The warning line on stderr of an answer some shards did not contribute to."""
    if r.missing_shards:
        print(f"rayfronts {command}: warning: shards that did not answer: {', '.join(r.missing_shards)} "
              "(their regions are missing from this answer)", file=sys.stderr, flush=True)


def with_client(args: argparse.Namespace, command: str, body: Callable[[Client], int]) -> int:
    """Connect (:func:`connect_client`), return ``body(client)`` and close the client; a
    ``QueryError`` is the one-line ``rayfronts COMMAND: error: ...`` and exit code 1."""
    from query_client.client import QueryError

    client = connect_client(args, command)
    if client is None:
        return 1
    with client:
        try:
            return body(client)
        except QueryError as e:
            error = " ".join(str(e).split())
    print(f"rayfronts {command}: error: {error}", file=sys.stderr)
    return 1


def run(args: argparse.Namespace) -> int:
    kw = check_inputs(args)
    return with_client(args, "query", lambda client: _query(args, client, kw))


def _query(args: argparse.Namespace, client: Client, kw: dict) -> int:
    if args.stats:  # shards: every shard's stats by shard name
        every = client.stats_all()
        one = list(every.values())[0] if list(every) == [""] else every
        print(json.dumps(one, indent=2, default=str))
        return 0
    if args.watch:
        def show(r):
            warn_missing(r)
            print(json.dumps(r.to_dict()) if args.json else format_result(r, args.top_k) + "\n", flush=True)

        watch_until_signal(lambda: client.watch(kw["text"], show, image=kw["image"], top_k=kw["top_k"]))
        return 0
    r = client.query(**kw, softmax=args.softmax)
    warn_missing(r)
    if args.json:
        print(json.dumps(r.to_dict(), indent=2))
    else:
        print(format_result(r, args.top_k))
    if args.rerun or args.rerun_connect:
        layers = {}
        try:
            layers["voxels"] = client.layer("voxels")[0]
        except Exception:
            pass
        log_result_rerun(r, args.rerun, args.rerun_connect, layers)
    return 0
