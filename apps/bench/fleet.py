"""``rayfronts bench fleet``: several robots on one mapper, replayed from recordings.

For each robot count N in ``--robots`` (e.g. ``1,2,4``): a ``rayfronts router``, a
``rayfronts mapper`` and N ``rayfronts edge`` processes, each replaying its own recording
(rendered here once, before any timing: a different lap start and direction of the
synthetic town per robot, so no rendering cost while measuring) with the label encoder
and, by default, its own online-fitted PCA basis (the mapper re-projects). Edges loop their
recording; after ``--warmup`` s the bench samples the mapper's stats twice, ``--seconds``
apart, and reports for that window:

* ``total_fused_hz`` (frames integrated per second, all robots) and ``per_robot_hz``;
  ``fairness`` = min / max of the per-robot rates (1 = equal shares);
* ``latency_ms`` p50 / p95 (edge hand-off → integrated; both on this host's clock) over
  the mapper's last 1000 frames, ``dropped_hz`` per robot;
* ``mapper_rss_mb`` and the edges' rate (``publish.rate_hz``, default ``auto``: they follow
  the mapper's advised rate);
* ``total_vs_single``: total fused rate with N robots / with one.

The mappers run with ``search.warm_up=false``: the text model's one-time load when a map is
created (seconds of CPU on a background thread) would otherwise fall in the measured
window on a 2-core machine.

The ``shards`` row (skip with ``--no-shards``): the README's first shard example, two shard
mappers split at x = 0 by ``shard.region`` alone (the edge learns their regions and sends each
frame to its owner, docs/key_space.md#shards; ``--shard-tile-m M`` routes by M-metre tiles
instead, ``publish.tile_m`` = ``shard.tile_m`` = M) and one robot lapping across the border;
over the window, ``deliveries_per_frame`` = the shards' own ``frames.received`` summed / the
frames the edge sent (counted by a passive subscriber of this bench on every frame key), goal
<= 1.3 (without routing every shard receives every frame: 2.0), and each shard's received /
mapped rates.

``--fake-ids K`` adds the memory probe: K robot ids that send frames but never serve a
feature space (one Zenoh session publishing on K keys), mapper RSS before, after and once
the eviction timeout has passed, and how many robots the mapper still tracks.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

import numpy as np

from apps.processes import stop_process

HELP = "several robots on one mapper from recordings: total / per-robot fused rate, latency, mapper RSS"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", default="1,2,4", help="robot counts to run, comma-separated (default 1,2,4)")
    parser.add_argument("--frames", type=int, default=60, help="frames per robot recording (looped; default 60)")
    parser.add_argument("--resolution", default="120x160", help="frame size HxW (default 120x160)")
    parser.add_argument("--pca-dim", type=int, default=32, help="PCA dimension (default 32)")
    parser.add_argument("--shared-basis", action="store_true",
                        help="all edges use one PCA basis file (default: each fits its own; the mapper re-projects)")
    parser.add_argument("--rate", default="auto", help="edge publish.rate_hz: auto (default), 0 = flood, or Hz")
    parser.add_argument("--preset", default="throughput", help="mapper preset (default throughput)")
    parser.add_argument("--warmup", type=float, default=8.0, help="seconds after every robot is mapping (default 8)")
    parser.add_argument("--seconds", type=float, default=20.0, help="measurement window in s (default 20)")
    parser.add_argument("--no-shards", action="store_true", help="skip the two-shard routing row")
    parser.add_argument("--only-shards", action="store_true", help="run only the two-shard routing row")
    parser.add_argument("--shard-tile-m", type=float, default=0.0,
                        help="shards row: route by tiles of this size (m) instead of the shards' announced regions")
    parser.add_argument("--fake-ids", type=int, default=0, help="memory probe: this many ids without a feature space")
    parser.add_argument("--mapper-set", action="append", default=[], metavar="KEY=VALUE",
                        help="extra mapper config override (repeatable)")
    parser.add_argument("--edge-set", action="append", default=[], metavar="KEY=VALUE",
                        help="extra edge config override (repeatable)")
    parser.add_argument("--workdir", type=Path, default=None, help="keep recordings and logs here")


def render_recordings(root: Path, n: int, frames: int, resolution: str, depth_limit: float = 20.0,
                      seed: int = 0) -> list[Path]:
    """One recording per robot of the synthetic town ``seed``: trajectory seed = robot index
    (another start and direction on the loop street). Existing ones are reused."""
    from common.conventions import sanitize_depth
    from common.frame import Frame
    from common.recording import RecordingWriter
    from synthetic_world.scene import World

    h, w = (int(v) for v in resolution.lower().split("x"))
    out = []
    world = None
    for i in range(n):
        d = Path(root) / f"rec{i}-{frames}-{h}x{w}"
        out.append(d)
        if (d / "recording.yaml").is_file() and len(list((d / "frames").glob("*.rff"))) >= frames:
            continue
        world = world or World.generate(seed, "default")
        K = world.camera((h, w), 90.0)
        poses = world.trajectory("ground", frames, seed=100 + i)
        src = {"type": "synthetic_world", "seed": seed, "classes": world.classes, "trajectory_seed": 100 + i}
        with RecordingWriter(d, robot=f"r{i}", source=src, overwrite=True) as wr:
            for j, pose in enumerate(poses):
                r = world.render(pose, K, (h, w))
                wr.write(Frame(robot=f"r{i}", seq=j, stamp=j * 0.1, pose=pose, intrinsics=K,
                               depth=sanitize_depth(r.depth, depth_limit), rgb=r.rgb, labels=r.labels,
                               meta={"frame": j}))
    return out


class _Procs:
    def __init__(self, work: Path):
        from apps.demo import zenoh_env

        self.items: list[tuple[subprocess.Popen, IO[bytes]]]     # (process, its log file)
        self.work, self.env, self.items = work, zenoh_env(), []

    def start(self, name: str, *args: str) -> subprocess.Popen:
        f = open(self.work / f"{name}.log", "wb")
        p = subprocess.Popen([sys.executable, "-m", "apps.cli", *args], stdout=f, stderr=subprocess.STDOUT,
                             env=self.env)
        self.items.append((p, f))
        return p

    def stop_all(self) -> None:
        for p, f in reversed(self.items):
            stop_process(p, timeout=30)
            f.close()
        self.items.clear()


def _pca_file(work: Path, rec: Path, dim: int) -> Path:
    out = work / f"pca{dim}.npz"
    if not out.is_file():
        from apps.demo import zenoh_env

        r = subprocess.run([sys.executable, "-m", "apps.cli", "edge", "fit-pca", "--out", str(out), "--frames", "8",
                            "source.kind=recording", f"source.path={rec}", f"pca.out_dim={dim}"],
                           env=zenoh_env(), capture_output=True, timeout=300)
        if r.returncode != 0:
            raise RuntimeError(f"fit-pca failed: {r.stderr.decode()[-800:]}")
    return out


def run_fleet(n: int, recs: list[Path], args: argparse.Namespace, work: Path) -> dict:
    """One measurement with ``n`` robots (see module doc)."""
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client.client import Client

    procs = _Procs(work)
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    zs = "transport/shared_memory/enabled=false"
    robots = [f"r{i}" for i in range(n)]
    try:
        procs.start(f"router{n}", "router", "--listen", ep, "--zenoh-set", zs)
        mapper = procs.start(f"mapper{n}", "mapper", "--mode", "client", "--connect", ep, "--zenoh-set", zs,
                             f"preset={args.preset}", "map.depth_limit=20", "layers.rate_hz=0",
                             "snapshots.on_exit=false", "search.warm_up=false", *args.mapper_set)
        basis = [f"pca.basis={_pca_file(work, recs[0], args.pca_dim)}"] if args.shared_basis else []
        for i, rb in enumerate(robots):
            procs.start(f"edge{n}-{rb}", "edge", "--connect", ep, "--zenoh-set", zs, f"robot={rb}",
                        "source.kind=recording", f"source.path={recs[i]}", "publish.loop=true",
                        f"publish.rate_hz={args.rate}", f"pca.out_dim={args.pca_dim}", "pca.fit_frames=4",
                        *basis, *args.edge_set)
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=20.0) as c:
            end = time.monotonic() + 180
            while time.monotonic() < end:
                try:
                    st = c.stats(timeout=5.0)
                    if all(st["robots"].get(rb, {}).get("mapped", 0) > 0 for rb in robots):
                        break
                except Exception:
                    pass
                if mapper.poll() is not None:
                    raise RuntimeError(f"mapper exited ({mapper.returncode}); see {work}/mapper{n}.log")
                time.sleep(0.5)
            else:
                raise RuntimeError(f"not every robot mapped within 180 s; see logs in {work}")
            time.sleep(args.warmup)
            s0, t0 = c.stats(timeout=10.0), time.monotonic()
            time.sleep(args.seconds)
            s1, t1 = c.stats(timeout=10.0), time.monotonic()
    finally:
        procs.stop_all()
    dt = t1 - t0
    per = {rb: (s1["robots"][rb]["mapped"] - s0["robots"][rb]["mapped"]) / dt for rb in robots}
    drop = {rb: (s1["robots"][rb]["dropped"] - s0["robots"][rb]["dropped"]) / dt for rb in robots}
    recv = {rb: (s1["robots"][rb]["received"] - s0["robots"][rb]["received"]) / dt for rb in robots}
    lat = s1["timings"].get("latency_ms", {})
    rates = list(per.values())
    return {"robots": n, "window_s": round(dt, 2), "total_fused_hz": sum(rates), "per_robot_hz": per,
            "received_hz": recv, "dropped_hz": drop,
            "fairness_min_over_max": (min(rates) / max(rates)) if max(rates) > 0 else None,
            "latency_ms": {k: lat.get(k) for k in ("p50", "p95", "max")},
            "integrate_ms": {k: s1["timings"].get("integrate_ms", {}).get(k) for k in ("p50", "mean")},
            "mapper_rss_mb": s1.get("rss_mb"),
            "reprojected": {rb: s1["robots"][rb].get("reprojected") for rb in robots},
            "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()]}


#: the shards row: the README's first example, two shards split at x = 0 (the synthetic lap
#: spans x in +-41 m)
SHARD_REGIONS = {"west": "[-1000, -1000, 0, 1000]", "east": "[0, -1000, 1000, 1000]"}


def tile_set(tile_m: float, section: str) -> list[str]:
    """``<section>.tile_m=M`` for explicit tile routing (M > 0), else nothing (routing by regions)."""
    return [f"{section}.tile_m={tile_m:g}"] if tile_m > 0 else []


def run_shards(rec: Path, args: argparse.Namespace, work: Path) -> dict:
    """Two shards and one robot lapping across their border (see module doc)."""
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client.client import Client

    procs = _Procs(work)
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    zs = "transport/shared_memory/enabled=false"
    sent = [0]
    try:
        procs.start("router-shards", "router", "--listen", ep, "--zenoh-set", zs)
        for name, region in SHARD_REGIONS.items():
            procs.start(f"mapper-{name}", "mapper", "--mode", "client", "--connect", ep, "--zenoh-set", zs,
                        f"preset={args.preset}", "map.depth_limit=20", "layers.rate_hz=0", "snapshots.on_exit=false",
                        f"shard.name={name}", f"shard.region={region}", *tile_set(args.shard_tile_m, "shard"),
                        "search.warm_up=false", *args.mapper_set)
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=20.0) as c:
            def count(_sample) -> None:
                sent[0] += 1
            subs = [c.session.declare_subscriber(k, count) for k in (c.keys.frames_all, c.keys.frames_tiled_all)]
            procs.start("edge-shards", "edge", "--connect", ep, "--zenoh-set", zs, "robot=r0", "source.kind=recording",
                        f"source.path={rec}", "publish.loop=true", f"publish.rate_hz={args.rate}",
                        f"pca.out_dim={args.pca_dim}", "pca.fit_frames=4", *tile_set(args.shard_tile_m, "publish"),
                        *args.edge_set)
            end = time.monotonic() + 180
            while True:
                try:
                    every = c.stats_all(timeout=5.0)
                    if set(every) == set(SHARD_REGIONS) and all(s["frames"]["mapped"] > 0 for s in every.values()):
                        break
                except Exception:
                    pass
                if time.monotonic() > end:
                    raise RuntimeError(f"the two shards did not both map within 180 s; see logs in {work}")
                time.sleep(0.5)
            time.sleep(args.warmup)
            s0, n0, t0 = c.stats_all(timeout=10.0), sent[0], time.monotonic()
            time.sleep(args.seconds)
            s1, n1, t1 = c.stats_all(timeout=10.0), sent[0], time.monotonic()
            for sub in subs:
                sub.undeclare()
    finally:
        procs.stop_all()
    dt, frames = t1 - t0, n1 - n0
    got = {k: s1[k]["frames"]["received"] - s0[k]["frames"]["received"] for k in SHARD_REGIONS}
    mapped = {k: s1[k]["frames"]["mapped"] - s0[k]["frames"]["mapped"] for k in SHARD_REGIONS}
    return {"shards": len(SHARD_REGIONS), "robots": 1, "routing": "tiles" if args.shard_tile_m > 0 else "regions",
            "tile_m": args.shard_tile_m, "window_s": round(dt, 2),
            "frames_sent": frames, "received": got,
            "deliveries_per_frame": (sum(got.values()) / frames) if frames else None, "goal_max": 1.3,
            "received_hz": {k: v / dt for k, v in got.items()}, "mapped_hz": {k: v / dt for k, v in mapped.items()},
            "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()]}


def fake_ids_probe(k: int, args: argparse.Namespace, work: Path, evict_s: float = 8.0, legacy: bool = False,
                   reps: int = 3) -> dict:
    """Mapper RSS with ``k`` robot ids that send frames but never serve a feature space."""
    import dataclasses

    from common.conventions import sanitize_depth
    from common.frame import Frame
    from common.wire import encode_frame
    from common.zenoh_session import ZenohConfig, free_tcp_port, open_session
    from query_client.client import Client
    from synthetic_world.scene import World

    procs = _Procs(work)
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    h, w = (int(v) for v in args.resolution.lower().split("x"))
    world = World.generate(0, "default")
    K = world.camera((h, w), 90.0)
    pose = world.trajectory("ground", 2, seed=0)[0]
    r = world.render(pose, K, (h, w))
    g = np.random.default_rng(0)
    base = Frame(robot="x", seq=0, stamp=0.0, pose=pose, intrinsics=K, depth=sanitize_depth(r.depth, 20.0),
                 rgb=r.rgb, labels=r.labels, features=g.standard_normal((args.pca_dim, h // 16, w // 16)).astype(
                     np.float16), feature_space="fake-1-000000000000-%d" % args.pca_dim)
    out: dict = {"ids": k, "frames_per_id": reps, "resolution": args.resolution}
    try:
        procs.start("mapper_fake", "mapper", "--mode", "router", "--listen", ep, f"preset={args.preset}",
                    "layers.rate_hz=0", "snapshots.on_exit=false",
                    *([] if legacy else [f"fleet.no_space_evict_s={evict_s}"]), *args.mapper_set)
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=20.0) as c:
            end = time.monotonic() + 60
            while True:
                try:
                    rss0 = c.stats(timeout=5.0)["rss_mb"]
                    break
                except Exception:
                    if time.monotonic() > end:
                        raise
                    time.sleep(0.5)
            s = open_session(ZenohConfig(connect=[ep], mode="client"), default_mode="client")
            try:
                for rep in range(reps):                   # frames per id
                    for i in range(k):
                        rb = f"fake{i:05d}"
                        s.put(c.keys.frames(rb), encode_frame(dataclasses.replace(base, robot=rb, seq=rep)))
                    time.sleep(0.5)
            finally:
                s.close()
            time.sleep(2.0)
            st1 = c.stats(timeout=20.0)
            time.sleep(evict_s + 3.0)
            st2 = c.stats(timeout=20.0)
        out.update(rss_mb_before=rss0, rss_mb_after_ids=st1.get("rss_mb"), rss_mb_after_evict=st2.get("rss_mb"),
                   robots_tracked_after_ids=len(st1["robots"]), robots_tracked_after_evict=len(st2["robots"]),
                   frames_received=st1["frames"]["received"], rejected=st1["frames"].get("rejected", {}),
                   fleet=st2.get("fleet", {}))
        out["mb_per_id"] = (out["rss_mb_after_ids"] - rss0) / k if k else None
    finally:
        procs.stop_all()
    out["load_avg_1_5_15"] = [round(x, 2) for x in os.getloadavg()]
    return out


def run(args: argparse.Namespace) -> dict:
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="rayfronts-bench-fleet-"))
    work.mkdir(parents=True, exist_ok=True)
    counts = [int(v) for v in str(args.robots).split(",") if v.strip()]
    if not counts or min(counts) < 1:
        raise SystemExit("--robots needs positive robot counts, e.g. 1,2,4")
    out: dict = {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                              if not k.startswith("_") and k != "json"},
                 "load_avg_1_5_15_start": [round(x, 2) for x in os.getloadavg()]}
    t = time.perf_counter()
    recs = render_recordings(work / "recordings", 1 if args.only_shards else max(counts), args.frames,
                             args.resolution)
    out["render_s"] = round(time.perf_counter() - t, 2)
    if args.only_shards:
        out["shards"] = run_shards(recs[0], args, work)
        out["workdir"] = str(work)
        return out
    runs = {}
    for n in counts:
        runs[str(n)] = run_fleet(n, recs, args, work)
    out["runs"] = runs
    if not args.no_shards:
        out["shards"] = run_shards(recs[0], args, work)
    if "1" in runs and runs["1"]["total_fused_hz"] > 0:
        single = runs["1"]["total_fused_hz"]
        out["total_vs_single"] = {n: r["total_fused_hz"] / single for n, r in runs.items()}
    if args.fake_ids > 0:
        out["fake_ids"] = fake_ids_probe(args.fake_ids, args, work)
    out["workdir"] = str(work)
    return out
