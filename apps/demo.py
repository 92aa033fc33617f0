"""``rayfronts demo``: router, mapper and edge as separate processes on loopback Zenoh, plus an
in-process query client, on the built-in synthetic world.

The edge plays a ground-robot trajectory with a 20 m depth limit (so distant landmarks
are only reachable by semantic rays), encodes frames with the label encoder (real MiniLM
text embeddings of the ground-truth classes) and PCA. When the mapper has mapped every
frame, the client asks a few open-vocabulary queries and the answers are scored against
the world's exact geometry:

* ``class``: the world class the query means (nearest class-name embedding);
* ``in_range``: an instance of it lies within the depth limit of the trajectory;
* ``best_voxel.error_m``: distance from the best voxel centre to the nearest instance;
* ``best_ray.miss_m``: distance from the best ray (a half-line) to the nearest instance.

Writes ``DIR/results.json`` (its fields are explained in ``docs/commands.md#demo``)
and ``DIR/demo.rrd`` (the mapper's rerun recording, with the operator blueprint).

The progress line is rewritten in place (``\r``) only on a terminal; into a log or a pipe it
prints one line at most every 5 s and when the edge finishes, so a log stays readable.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Iterable

import numpy as np

if TYPE_CHECKING:
    from common.messages import QueryResult
    from query_client.client import Client
    from synthetic_world import World

HELP = "run router, mapper, edge and a query client on the built-in synthetic world"
DESCRIPTION = __doc__

log = logging.getLogger("rayfronts.demo")

DEFAULT_QUERIES = ("water tower", "vehicle", "chimney", "radio tower", "tree")


@dataclass
class DemoConfig:
    out: Path = Path("out/demo")
    frames: int = 80
    resolution: str = "240x320"
    depth_limit: float = 20.0
    seed: int = 0
    vox_size: float = 0.5
    preset: str = "throughput"
    pca_dim: int = 64
    queries: tuple = DEFAULT_QUERIES
    timeout_s: float = 170.0
    map_overrides: list = field(default_factory=list)
    shared_memory: bool | None = None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory (default out/demo)")
    parser.add_argument("--frames", type=int, default=80, help="trajectory frames (default 80)")
    parser.add_argument("--resolution", default="240x320", help="frame size HxW (default 240x320)")
    parser.add_argument("--depth-limit", type=float, default=20.0, help="simulated depth range in m (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="synthetic world seed (default 0)")
    parser.add_argument("--vox-size", type=float, default=0.5, help="voxel size in m (default 0.5)")
    parser.add_argument("--pca-dim", type=int, default=64,
                        help="PCA dimension of the features on the wire (default 64)")
    parser.add_argument("--query", action="append", default=None, metavar="TEXT",
                        help="query to run (repeatable; default: " + ", ".join(DEFAULT_QUERIES) + ")")
    parser.add_argument("--timeout", type=float, default=170.0,
                        help="give up when mapping has not progressed for this many seconds (default 170)")
    parser.add_argument("--no-shm", action="store_true", help="turn Zenoh shared memory off (network path)")


# ----------------------------------------------------------------------- processes
def _py(*args: str) -> list[str]:
    return [sys.executable, "-m", "apps.cli", *args]


class Procs:
    """Child processes started by the demo; stopped in reverse order with SIGINT, then killed."""

    def __init__(self, logdir: Path):
        self.logdir = logdir
        self.procs: list[tuple[str, subprocess.Popen, IO[bytes]]] = []

    def start(self, name: str, cmd: list[str], env: dict | None = None) -> subprocess.Popen:
        f = open(self.logdir / f"{name}.log", "wb")
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env,
                             cwd=str(Path(__file__).resolve().parents[1]))
        self.procs.append((name, p, f))
        return p

    def stop(self, name: str, timeout: float = 60.0) -> int | None:
        for n, p, f in self.procs:
            if n == name:
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
                    try:
                        p.wait(timeout)
                    except subprocess.TimeoutExpired:
                        log.error("%s did not exit in %.0f s; killing it", name, timeout)
                        p.kill()
                        p.wait()
                f.close()
                return p.returncode
        return None

    def stop_all(self) -> dict[str, int | None]:
        return {n: self.stop(n) for n, _, _ in reversed(self.procs)}


def zenoh_env() -> dict:
    env = dict(os.environ)
    env.setdefault("RUST_LOG", "error")
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


# ------------------------------------------------------------------------- scoring
def query_classes(world: World, texts: Iterable[str]) -> list[int]:
    """Nearest world class (by MiniLM embedding of the class names) for each query text."""
    import torch

    from encoders.text import MiniLMText

    enc = MiniLMText()
    names = list(world.classes)
    c = torch.nn.functional.normalize(enc.encode(names[1:]).float(), dim=1)
    q = torch.nn.functional.normalize(enc.encode(list(texts)).float(), dim=1)
    return [int(i) + 1 for i in (q @ c.T).argmax(1).tolist()]


def class_in_range(world: World, class_id: int, positions: np.ndarray, depth_limit: float) -> bool:
    d = world.distance_to_class(np.asarray(positions, np.float64), class_id)
    return bool(np.isfinite(d).any() and d.min() <= depth_limit)


def score_result(world: World, res: QueryResult, class_id: int) -> dict:
    out: dict = {"best_voxel": None, "best_ray": None}
    if len(res.voxel_xyz):
        x = np.asarray(res.voxel_xyz[0], np.float64)
        out["best_voxel"] = {"xyz": [float(v) for v in x], "score": float(res.voxel_score[0]),
                             "error_m": float(world.distance_to_class(x[None], class_id)[0])}
    if len(res.ray_origin):
        o, d = np.asarray(res.ray_origin[0], np.float64), np.asarray(res.ray_direction[0], np.float64)
        out["best_ray"] = {"origin": [float(v) for v in o], "direction": [float(v) for v in d],
                           "score": float(res.ray_score[0]),
                           "miss_m": float(world.ray_distance_to_class(o, d, class_id))}
    return out


def done_criteria(results: dict, vox_size: float, ray_miss_m: float = 10.0) -> list[str]:
    """Failures of the demo's done criteria (empty = all met)."""
    bad = []
    for q in results["queries"]:
        if q["in_range"]:
            bv = q["best_voxel"]
            if bv is None or not bv["error_m"] <= vox_size:
                bad.append(f"{q['query']}: best voxel {bv and round(bv['error_m'], 2)} m from a {q['class']} "
                           f"(> {vox_size} m)")
        else:
            br = q["best_ray"]
            if br is None or not br["miss_m"] <= ray_miss_m:
                bad.append(f"{q['query']}: best ray misses a {q['class']} by {br and round(br['miss_m'], 2)} m "
                           f"(> {ray_miss_m} m)")
    return bad


# ----------------------------------------------------------------------------- run
class Progress:
    """One status line: rewritten in place on a TTY; on a pipe/log a new line at most every
    ``every_s`` seconds (and whenever ``force``), never a ``\r``."""

    def __init__(self, stream=None, every_s: float = 5.0):
        self.stream = stream if stream is not None else sys.stdout
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._last_t: float | None = None
        self._last_text: str | None = None
        self._open = False

    def update(self, text: str, force: bool = False) -> None:
        if self.tty:
            print(f"\r{text}   ", end="", flush=True, file=self.stream)
            self._open = True
            return
        now = time.monotonic()
        due = self._last_t is None or now - self._last_t >= self.every_s
        if text != self._last_text and (due or force):
            print(text, flush=True, file=self.stream)
            self._last_t, self._last_text = now, text

    def end(self) -> None:
        if self._open:
            print(file=self.stream, flush=True)
            self._open = False


def wait_mapped(client: Client, edge: subprocess.Popen, deadline: float, progress: bool = True,
                others: Iterable[tuple[str, subprocess.Popen]] = (), stall_s: float | None = None) -> dict:
    """Poll the mapper's stats until the edge has exited and every frame it sent is mapped,
    dropped or rejected, and the map is flushed. With ``stall_s`` the deadline moves on
    whenever the counts change (a slow, loaded machine gets time; a stuck one does not)."""
    from query_client.vocabulary import settled

    last = None
    stable_since = None
    line = Progress() if progress else None
    was_done = False
    while time.monotonic() < deadline:
        for name, p in others:
            if p.poll() is not None:
                raise RuntimeError(f"the {name} process exited early (code {p.returncode}); see its log")
        if edge.poll() not in (None, 0):
            raise RuntimeError(f"the edge process failed (code {edge.returncode}); see its log")
        try:
            st = client.stats(timeout=5.0)
        except Exception:
            time.sleep(0.5)
            continue
        fr = st["frames"]
        done_edge = edge.poll() is not None
        key = (fr["received"], fr["mapped"], st.get("map_version"), st.get("flushed_version"))
        if stall_s is not None and key != last:
            deadline = max(deadline, time.monotonic() + stall_s)
        if line is not None:
            line.update(f"  frames received {fr['received']:4d}  mapped {fr['mapped']:4d}  dropped {fr['dropped']}"
                        f"  rejected {fr['rejected_total']}  edge {'done' if done_edge else 'running'}",
                        force=done_edge and not was_done)
        was_done = done_edge
        if done_edge and settled(st, mapped=0):
            if key == last:
                if stable_since is None:  # the final state may be reached before the edge exits
                    stable_since = time.monotonic()
                if time.monotonic() - stable_since > 1.0:
                    if line is not None:
                        line.update(f"  frames received {fr['received']:4d}  mapped {fr['mapped']:4d}  dropped "
                                    f"{fr['dropped']}  rejected {fr['rejected_total']}  edge done", force=True)
                        line.end()
                    return st
            else:
                stable_since = time.monotonic()
        last = key
        time.sleep(0.5)
    if line is not None:
        line.end()
    raise TimeoutError("the mapper made no progress for too long (see mapper.log / edge.log in the output "
                       "directory; --timeout S gives a loaded machine more time)")


def run_demo(cfg: DemoConfig, progress: bool = True) -> dict:
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client.client import Client
    from synthetic_world import World

    t_start = time.monotonic()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    rrd = out / "demo.rrd"
    if rrd.exists():
        rrd.unlink()
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    env = zenoh_env()
    procs = Procs(out)
    shm = [] if cfg.shared_memory is None else [f"zenoh.shared_memory={str(cfg.shared_memory).lower()}"]
    shm_flag = [] if cfg.shared_memory is None else ["--zenoh-set",
                                                      f"transport/shared_memory/enabled={str(cfg.shared_memory).lower()}"]
    results: dict = {"settings": demo_settings(cfg, ep), "queries": [], "frames": 0, "seconds": 0.0}
    try:
        router = procs.start("router", _py("router", "--listen", ep, *shm_flag), env)
        mapper = procs.start("mapper", _py("mapper", "--mode", "client", "--connect", ep, "--rerun", str(rrd),
                                  f"preset={cfg.preset}", f"map.vox_size={cfg.vox_size}",
                                  f"map.depth_limit={cfg.depth_limit}",
                                  "queues.per_robot=100000", "layers.rate_hz=0.5", "snapshots.on_exit=false",
                                  *shm, *cfg.map_overrides), env)
        edge = procs.start("edge", _py("edge", "--connect", ep, "--rate", "0", "robot=demo1",
                                       "source.kind=synthetic", f"source.seed={cfg.seed}",
                                       f"source.n_frames={cfg.frames}", f"source.resolution={cfg.resolution}",
                                       f"source.depth_limit={cfg.depth_limit}", "encoder.kind=label",
                                       f"pca.out_dim={cfg.pca_dim}", "pca.fit_frames=8", "publish.linger_s=0.5",
                                       *shm), env)
        world = World.generate(cfg.seed)
        classes = query_classes(world, cfg.queries)
        traj = np.asarray(world.trajectory("ground", cfg.frames))[:, :3, 3]
        zc = ZenohConfig(connect=[ep], connect_timeout_ms=30_000,
                         shared_memory=cfg.shared_memory)
        with Client(zc, timeout=30.0) as client:
            if progress:
                print(f"rayfronts demo: router {ep}; mapper, edge started (logs in {out})")
            st = wait_mapped(client, edge, t_start + cfg.timeout_s, progress,
                             others=(("router", router), ("mapper", mapper)), stall_s=cfg.timeout_s)
            results["frames"] = int(st["frames"]["mapped"])
            for text, cid in zip(cfg.queries, classes, strict=True):
                res = client.query(text, top_k=10, timeout=cfg.timeout_s)  # the first loads the text model
                entry = {"query": text, "class": world.classes[cid],
                         "in_range": class_in_range(world, cid, traj, cfg.depth_limit)}
                entry.update(score_result(world, res, cid))
                # in range: judged by the best voxel; beyond range: by the best ray (the best voxel of
                # an unmapped object is just the most similar mapped surface, often far away)
                entry["judged_by"] = "best_voxel" if entry["in_range"] else "best_ray"
                entry["search_volume_m3"] = float(res.search_volume_m3)
                results["queries"].append(entry)
    finally:
        codes = procs.stop_all()
    results["seconds"] = round(time.monotonic() - t_start, 2)
    results["exit_codes"] = codes
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


def demo_settings(cfg: DemoConfig, endpoint: str = "") -> dict:
    """What results.json records about how the run was set up (``docs/commands.md#demo``)."""
    return {
        "frames": cfg.frames, "resolution": cfg.resolution, "depth_limit_m": cfg.depth_limit, "seed": cfg.seed,
        "vox_size_m": cfg.vox_size, "map_preset": cfg.preset, "pca_dim": cfg.pca_dim, "encoder": "label",
        "world": "synthetic", "trajectory": "ground", "queries": list(cfg.queries), "top_k": 10,
        "timeout_s": cfg.timeout_s, "map_overrides": list(cfg.map_overrides),
        "shared_memory": cfg.shared_memory, "router_endpoint": endpoint,
        "done_criteria": {"best_voxel_error_m_max": cfg.vox_size, "best_ray_miss_m_max": 10.0},
    }


def summary_table(results: dict, vox_size: float) -> str:
    rows = [f"{'query':<13} {'class':<12} {'range':<6} {'best voxel err (m)':>18} {'best ray miss (m)':>18}"]
    for q in results["queries"]:
        bv = q["best_voxel"]
        br = q["best_ray"]
        ev = f"{bv['error_m']:.2f}" if bv else "-"
        mv = f"{br['miss_m']:.2f}" if br else "-"
        rng = "in" if q["in_range"] else "beyond"
        rows.append(f"{q['query']:<13} {q['class']:<12} {rng:<6} {ev:>18} {mv:>18}")
    bad = done_criteria(results, vox_size)
    rows.append(f"{results['frames']} frames mapped in {results['seconds']:.1f} s; "
                + ("all answers meet the done criteria" if not bad else "NOT MET: " + "; ".join(bad)))
    return "\n".join(rows)


def run(args: argparse.Namespace) -> int:
    cfg = DemoConfig(out=args.out, frames=args.frames, resolution=args.resolution, depth_limit=args.depth_limit,
                     seed=args.seed, vox_size=args.vox_size, pca_dim=args.pca_dim,
                     queries=tuple(args.query) if args.query else DEFAULT_QUERIES, timeout_s=args.timeout,
                     shared_memory=False if args.no_shm else None)
    results = run_demo(cfg)
    print(summary_table(results, cfg.vox_size))
    print(f"results: {Path(cfg.out) / 'results.json'}\nrerun:   {Path(cfg.out) / 'demo.rrd'} "
          f"(view with: rerun {Path(cfg.out) / 'demo.rrd'})")
    bad_exit = {k: v for k, v in results.get("exit_codes", {}).items() if v not in (0, None)}
    if bad_exit:
        print(f"processes exited with errors: {bad_exit}", file=sys.stderr)
        return 1
    return 0
