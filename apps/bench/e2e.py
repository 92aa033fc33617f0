"""``rayfronts bench e2e``: the whole chain over loopback Zenoh on the synthetic world.

Measures, in one run:

* ``encoder_fps`` (= ``rates.encoder_alone``): the encoder alone in this process — the one
  call per frame the edge makes, ``encode_with_global(..., global_space="features")`` — built
  as the edge builds it (``--model``: the label encoder, or NARADIO ``radio_v2.5-b`` / ``-l``
  from ``--model-dir`` or random weights of the real architecture written to
  ``<workdir>/models`` as a user's model directory; ``--output`` radio/language), with the
  edge's torch thread count (``EdgeConfig.threads``);
  ``edge_alone_fps`` (= ``rates.edge_alone``): all the per-frame work of the edge process in
  this process, no network: reading the source (rendering the synthetic world), the encoder,
  PCA and ``encode_frame``; ``ratios`` gives ``edge_alone / encoder_alone``,
  ``e2e / encoder_alone`` and ``e2e / edge_alone`` from the same run;
* ``e2e_fps``: frames integrated per second by a ``rayfronts mapper`` process fed by a
  ``rayfronts edge`` process through a ``rayfronts router`` (first to last integration),
  and ``e2e_vs_encoder`` / ``e2e_vs_edge_alone`` its ratios to the above;
* ``cpu_ms_per_frame``: CPU time (all threads) per frame of the encoder alone, the edge
  alone, and, while streaming, of the edge, mapper and router processes (edge: from the
  ``cpu_s`` its frames carry; mapper: first to last integration; router: from the edge's
  start to the end). The processes share this host's cores: ``e2e_fps_own_cores`` =
  1000 / the largest of edge and mapper CPU ms per frame estimates the rate with a core
  (or more) per process, as on a robot + base station (the mapper's map thread is serial:
  ``mapper_map_fps_cpu_bound`` = 1000 / its mean integrate CPU ms, the mapper's limit
  when the Zenoh/decode threads have another core);
* ``latency_ms``: edge hand-off to the publisher → integrated in the map (p50 / p95; both
  processes share this host's clock);
* ``bytes_per_frame``: frame message size on the wire (mean / max), seen by a subscriber,
  with the edge's ``publish.feature_codec`` / ``publish.jpeg_quality``;
  ``bytes_per_frame_local.f16_features_mean`` the same frames with float16 features, and
  ``score_change_vs_f16`` what the codec changes in the query scores per feature cell (max
  |Δ cosine| over the demo's queries; share of cells with the same top-1 class);
* ``query_rtt_ms``: query round trip from a client (embedding query: no text encoding) on
  a map of ``--query-voxels`` voxels and ``--query-rays`` ray bins, restored into a mapper
  from a snapshot written here (the first query, which copies the map and prepares its
  features, is a warm-up and not timed); ``query_server_ms`` the mapper's own time and
  ``query_server_stages_ms`` its stages for the last query.

``--only query`` runs just the query part (a random orthonormal PCA basis stands in for the
fitted one: the cost depends on the sizes only); ``--only stream`` just the streaming part.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HELP = "end-to-end edge -> mapper throughput, latency, bytes per frame, query round trip"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default="label", choices=["label", "radio_v2.5-b", "radio_v2.5-l"],
                        help="the edge's encoder: the label encoder (default) or NARADIO (random weights of the "
                             "real architecture unless --model-dir holds a checkpoint)")
    parser.add_argument("--model-dir", default="", help="NARADIO: model directory with the RADIO checkpoint")
    parser.add_argument("--output", default="radio", choices=["radio", "language"],
                        help="NARADIO output space (encoder.output, default radio)")
    parser.add_argument("--frames", type=int, default=40, help="frames streamed end to end (default 40)")
    parser.add_argument("--resolution", default="224x224", help="frame size HxW (default 224x224)")
    parser.add_argument("--pca-dim", type=int, default=100, help="PCA dimension on the wire (default 100)")
    parser.add_argument("--label-stride", type=int, default=16,
                        help="label encoder cell size in px (default 16 = the RADIO patch size, so the feature "
                             "map has the size NARADIO would send)")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="edge publish rate in Hz (0 = as fast as possible: throughput; the latency then "
                             "includes queueing at the mapper; give a rate below e2e_fps for unloaded latency)")
    parser.add_argument("--preset", default="throughput", help="mapper preset (default throughput)")
    parser.add_argument("--query-voxels", type=int, default=1_000_000, help="voxels of the query map (default 1M)")
    parser.add_argument("--query-rays", type=int, default=10_000,
                        help="semantic ray bins of the query map (default 10k; they are scored and the best "
                             "rays' cones make up the search volume)")
    parser.add_argument("--queries", type=int, default=10, help="query round trips to time (default 10)")
    parser.add_argument("--only", choices=("all", "stream", "query"), default="all",
                        help="run only the streaming part (encoder, e2e fps, latency, bytes) or only the "
                             "query-latency part (a random PCA basis stands in for the fitted one); default all")
    parser.add_argument("--layers-hz", type=float, default=0.0,
                        help="mapper layers publish rate while streaming (default 0 = off; the service's own "
                             "default is 1 Hz)")
    parser.add_argument("--mapper-set", action="append", default=[], metavar="KEY=VALUE",
                        help="extra mapper config override (repeatable), e.g. threads=2")
    parser.add_argument("--edge-set", action="append", default=[], metavar="KEY=VALUE",
                        help="extra edge config override (repeatable), e.g. threads=2")
    parser.add_argument("--shm", action="store_true", help="keep Zenoh shared memory on (default off: network path)")
    parser.add_argument("--workdir", type=Path, default=None, help="keep logs and snapshots here")


def _pct(a) -> dict:
    a = np.asarray(a, float)
    if a.size == 0:
        return {}
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)), "mean": float(a.mean()),
            "n": int(a.size)}


def encoder_items(args: argparse.Namespace, work: Path) -> list[str]:
    """The edge's encoder config overrides for ``--model`` (the same for the in-process
    measurement and the edge process)."""
    if args.model == "label":
        return ["encoder.kind=label", f"encoder.label_stride={args.label_stride}"]
    from apps.bench.encoder import random_model_dir

    mdir = Path(args.model_dir) if args.model_dir else random_model_dir(args.model, work / "models")
    return ["encoder.kind=naradio", f"encoder.model={args.model}", f"encoder.model_dir={mdir}",
            f"encoder.output={args.output}"]


def _encoder_alone(res: str, pca_dim: int, n: int, pca_path: Path, items=(), edge_set=()) -> dict:
    """The edge's per-frame work in this process, no network, as the edge does it: the
    encoder's one call per frame (``encoder_fps``), then PCA → ``encode_frame`` with the frame
    meta; ``source_ms`` (reading = rendering a frame), ``edge_alone_fps`` (all of it), CPU ms
    per frame, and the local message sizes. Runs with the edge's torch thread count and the
    edge's start-up check (``edge_set``: the edge's extra config overrides)."""
    import dataclasses

    import torch

    from apps.bench.encoder import edge_encoder
    from common.pca import OnlinePCAFitter
    from common.wire import decode_frame, encode_frame
    from edge.encoding import check_setup, compress_features
    from edge.sources import SourceConfig, open_source

    old_threads = torch.get_num_threads()
    try:
        src = open_source(SourceConfig(kind="synthetic", n_frames=n, resolution=res, depth_limit=20.0))
        t0, c0 = time.perf_counter(), time.process_time()
        frames = list(src)
        src_s, src_cpu = time.perf_counter() - t0, time.process_time() - c0
        enc, ecfg, threads = edge_encoder([*items, f"pca.out_dim={pca_dim}", *edge_set], src.class_names)
        pca = None
        if pca_dim > 0:
            fit = OnlinePCAFitter(pca_dim, max_frames=min(8, len(frames)))
            for f in frames[:8]:
                with torch.inference_mode():
                    fit.add(enc.encode_with_global(f.rgb, f.labels, global_space="features")[0])
            pca = fit.fit()
            pca.save(pca_path)
        check_setup(ecfg, enc, pca)
        codec, jq = ecfg.publish.feature_codec, ecfg.publish.jpeg_quality
        sizes, sizes_f16 = [], []
        cmp = _ScoreChange(enc, pca, src.class_names) if codec != "f16" else None
        enc_s = enc_cpu = 0.0
        t0, c0 = time.perf_counter(), time.process_time()
        for f in frames:
            t1, c1 = time.perf_counter(), time.process_time()
            with torch.inference_mode():
                # as the edge does: one pass, the image vector in the dense features' space
                x, g = enc.encode_with_global(f.rgb, f.labels, global_space="features")
            enc_s += time.perf_counter() - t1
            enc_cpu += time.process_time() - c1
            out = dataclasses.replace(f, features=compress_features(pca, x), feature_space="bench",
                                      global_feature=compress_features(pca, g.reshape(-1, 1, 1)).reshape(-1))
            out.meta = {**(out.meta or {}), "t_send": time.time(), "cpu_s": time.process_time()}
            data = encode_frame(out, feature_codec=codec, jpeg_quality=jq)
            sizes.append(len(data))
            if cmp is not None:   # outside the timed work below: subtract it
                t2, c2 = time.perf_counter(), time.process_time()
                sizes_f16.append(len(encode_frame(out, feature_codec="f16", jpeg_quality=jq)))
                back = decode_frame(data).features
                assert out.features is not None and back is not None    # both carry features
                cmp.add(out.features, back)
                t0 += time.perf_counter() - t2
                c0 += time.process_time() - c2
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        torch.set_num_threads(old_threads)
    k = len(frames)
    return {"encoder_fps": k / enc_s, "pipeline_fps": k / dt, "edge_alone_fps": k / (dt + src_s),
            "source_ms": 1e3 * src_s / k, "threads": threads, "feature_shape": list(x.shape),
            "cpu_ms": {"encoder_alone": 1e3 * enc_cpu / k, "edge_alone": 1e3 * (cpu + src_cpu) / k},
            "sizes": {"mean": float(np.mean(sizes)), "max": int(np.max(sizes)), "feature_codec": codec,
                      "jpeg_quality": jq,
                      "f16_features_mean": float(np.mean(sizes_f16)) if sizes_f16 else None},
            "score_change_vs_f16": cmp.result() if cmp is not None else None}


class _ScoreChange:
    """Per-cell query-score change of the wire's feature codec against float16: max |Δ cosine|
    over the demo's queries and the share of cells whose top-1 class is unchanged (label
    encoder: MiniLM texts; NARADIO has no text tower offline: random language-space queries,
    no classes)."""

    def __init__(self, enc, pca, class_names):
        import torch

        from apps.demo import DEFAULT_QUERIES
        from common.feature_space import FeatureSpace

        self.fs = FeatureSpace.for_encoder(enc, pca)
        if enc.name == "label":
            self.q = enc.text.encode(list(DEFAULT_QUERIES)).float()
            self.cls = enc.table.float()
            self.what = f"demo queries {list(DEFAULT_QUERIES)}"
        else:
            g = torch.Generator().manual_seed(0)
            self.q = torch.randn((len(DEFAULT_QUERIES), self.fs.lang_dim), generator=g)
            self.cls = None
            self.what = "random language-space queries"
        self.dmax, self.same, self.n = 0.0, 0, 0

    def add(self, f16: np.ndarray, decoded: np.ndarray) -> None:
        import torch

        a = torch.as_tensor(np.asarray(f16, np.float32)).reshape(f16.shape[0], -1).T
        b = torch.as_tensor(np.asarray(decoded, np.float32)).reshape(f16.shape[0], -1).T
        self.dmax = max(self.dmax, float((self.fs.similarity(a, self.q) - self.fs.similarity(b, self.q)).abs().max()))
        if self.cls is not None:
            ta, tb = self.fs.similarity(a, self.cls).argmax(0), self.fs.similarity(b, self.cls).argmax(0)
            self.same += int((ta == tb).sum())
            self.n += int(ta.numel())

    def result(self) -> dict:
        return {"queries": self.what, "max_abs_dcos_per_cell": self.dmax,
                "top1_class_same_fraction_per_cell": (self.same / self.n) if self.n else None}


def _random_pca(path: Path, in_dim: int, out_dim: int) -> None:
    """A random orthonormal PCA basis (``--only query``: no encoder run needed)."""
    from common.pca import PCA

    rng = np.random.default_rng(0)
    basis = np.linalg.qr(rng.standard_normal((in_dim, out_dim)))[0].astype(np.float32)
    PCA(rng.standard_normal(in_dim).astype(np.float32) * 0.1, basis, np.ones(out_dim)).save(path)


def _big_snapshot(root: Path, n_vox: int, pca_path: Path, preset: str, n_rays: int = 0) -> np.ndarray:
    """A mapper snapshot holding ``n_vox`` random semantic voxels (a cube of 0.5 m voxels)
    and ``n_rays`` random ray bins (one per frontier, random unit directions); returns a
    query embedding."""
    import torch

    from common.feature_space import FeatureSpace
    from common.messages import encode_feature_space
    from common.pca import PCA
    from mapper.service_config import load_mapper_config
    from mapper.service_map import create_map
    from mapper.snapshot import capture_map
    from mapper.snapshot_store import write_snapshot

    cfg = load_mapper_config(None, [f"preset={preset}", "map.vox_size=0.5"])
    pca = PCA.load(pca_path)
    fs = FeatureSpace("label", "bench", pca.in_dim, pca=pca)
    m = create_map(cfg, fs)
    g = torch.Generator().manual_seed(0)
    side = int(np.ceil(n_vox ** (1 / 3)))
    ijk = torch.stack(torch.meshgrid(*[torch.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n_vox]
    xyz = (ijk.float() + 0.5) * 0.5
    for a in range(0, n_vox, 250_000):
        b = min(n_vox, a + 250_000)
        m.fuse_samples(xyz[a:b], torch.rand((b - a, 3), generator=g), torch.randn((b - a, pca.out_dim), generator=g))
    assert m.n_voxels() == n_vox
    if n_rays > 0:
        from semantic_map import cell_keys

        fk = torch.unique(cell_keys.pack(torch.randint(-400, 400, (n_rays, 3), generator=g)))
        r = fk.numel()
        z = torch.zeros(r, dtype=torch.int64)
        m.replace_ray_bins({"fkey": fk, "tbin": z, "pbin": z.clone(),
                            "feat": torch.randn((r, pca.out_dim), generator=g), "weight": torch.ones(r),
                            "dsum": torch.nn.functional.normalize(torch.randn((r, 3), generator=g), dim=1)})
    write_snapshot(root, capture_map(m), encode_feature_space("bench", fs.to_body()),
                   {"frames_mapped": 0, "robots": {}})
    return np.random.default_rng(0).standard_normal(pca.in_dim).astype(np.float32)


def run(args: argparse.Namespace) -> dict:
    from apps.demo import zenoh_env

    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="rayfronts-bench-e2e-"))
    work.mkdir(parents=True, exist_ok=True)
    pca_path = work / "pca.npz"
    shm = "true" if args.shm else "false"
    out: dict = {"machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
                 "settings": {"model": args.model, "output": args.output if args.model != "label" else None,
                              "frames": args.frames, "resolution": args.resolution, "pca_dim": args.pca_dim,
                              "preset": args.preset, "shared_memory": args.shm, "label_stride": args.label_stride,
                              "rate_hz": args.rate, "only": args.only, "query_voxels": args.query_voxels,
                              "query_rays": args.query_rays, "layers_hz": args.layers_hz,
                              "mapper_set": list(args.mapper_set), "edge_set": list(args.edge_set)},
                 "load_avg_1_5_15_start": [round(x, 2) for x in os.getloadavg()]}
    env = zenoh_env()
    procs = []

    def start(name, *a):
        f = open(work / f"{name}.log", "wb")
        p = subprocess.Popen([sys.executable, "-m", "apps.cli", *a], stdout=f, stderr=subprocess.STDOUT, env=env)
        procs.append((p, f))
        return p

    def stop_all():
        from apps.processes import stop_process

        for p, f in reversed(procs):
            stop_process(p, timeout=60)
            f.close()
        procs.clear()

    try:
        if args.only != "query":
            _stream(args, out, work, pca_path, shm, start, stop_all)
        else:
            _random_pca(pca_path, 384, args.pca_dim)
        if args.only != "stream":
            _queries(args, out, work, pca_path, shm, start)
    finally:
        stop_all()
    out["workdir"] = str(work)
    return out


def _stream(args, out: dict, work: Path, pca_path: Path, shm: str, start, stop_all) -> None:
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client.client import Client

    items = encoder_items(args, work)
    alone = _encoder_alone(args.resolution, args.pca_dim, args.frames, pca_path, items, args.edge_set)
    enc_fps = alone["encoder_fps"]
    out["feature_shape"] = alone["feature_shape"]
    out["bytes_per_frame_local"] = alone["sizes"]
    out["score_change_vs_f16"] = alone["score_change_vs_f16"]
    out["encoder_fps"] = enc_fps
    out["edge_alone_fps"] = alone["edge_alone_fps"]
    out["source_ms_per_frame"] = alone["source_ms"]
    out["edge_torch_threads"] = alone["threads"]
    cpu_ms = dict(alone["cpu_ms"])
    zs = f"transport/shared_memory/enabled={shm}"
    # ---------------------------------------------------------------- streaming
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = start("router", "router", "--listen", ep, "--zenoh-set", zs)
    # search.warm_up=false: the text model's one-time load on map creation (seconds of CPU on
    # a background thread, search.warm_up) would overlap this short stream; streaming is measured
    start("mapper", "mapper", "--mode", "client", "--connect", ep, "--zenoh-set", zs, f"preset={args.preset}",
          "map.depth_limit=20", "queues.per_robot=100000", f"layers.rate_hz={args.layers_hz}",
          "search.warm_up=false", *args.mapper_set)
    zc = ZenohConfig(connect=[ep], connect_timeout_ms=60_000, shared_memory=args.shm)
    sizes = []
    with Client(zc, timeout=30.0) as c:
        sub = c.session.declare_subscriber(c.keys.frames_all, lambda s: sizes.append(len(s.payload.to_bytes())))
        router_cpu0 = _cpu_s(router)
        edge = start("edge", "edge", "--connect", ep, "--zenoh-set", zs, "--rate", str(args.rate), "robot=bench",
                     *items,
                     f"source.n_frames={args.frames}", f"source.resolution={args.resolution}",
                     "source.depth_limit=20", f"pca.basis={pca_path}", f"pca.out_dim={args.pca_dim}",
                     *args.edge_set)
        st = _wait_drained(c, edge, args.frames, deadline_s=600)
        if st is None:
            raise RuntimeError("the mapper answered no stats request in 600 s")
        router_cpu1 = _cpu_s(router)
        sub.undeclare()
    fr = st["frames"]
    span = (st["last_mapped_at"] or 0) - (st["first_mapped_at"] or 0)
    out["e2e_frames_mapped"] = fr["mapped"]
    out["e2e_dropped"] = fr["dropped"]
    out["e2e_fps"] = (fr["mapped"] - 1) / span if span > 0 else None
    out["e2e_vs_encoder"] = out["e2e_fps"] / enc_fps if out["e2e_fps"] else None
    out["e2e_vs_edge_alone"] = out["e2e_fps"] / alone["edge_alone_fps"] if out["e2e_fps"] else None
    out["latency_ms"] = {k: st["timings"]["latency_ms"].get(k) for k in ("p50", "p95", "max")}
    out["integrate_ms"] = {k: st["timings"]["integrate_ms"].get(k) for k in ("p50", "p95", "mean")}
    out["integrate_cpu_ms"] = {k: st["timings"].get("integrate_cpu_ms", {}).get(k) for k in ("p50", "p95", "mean")}
    out["decode_ms"] = {k: st["timings"].get("decode_ms", {}).get(k) for k in ("p50", "mean")}
    robot = st["robots"].get("bench", {})
    # frames the edge numbered but the mapper never received (replaced at the edge or lost on the wire)
    out["e2e_lost_before_mapper"] = (robot["last_seq"] + 1 - robot["received"]
                                     if robot.get("last_seq", -1) >= 0 else None)
    cpu_ms["edge"] = robot.get("edge_cpu_ms_per_frame")
    mapping = st.get("cpu_s", {}).get("mapping")
    cpu_ms["mapper"] = 1e3 * mapping / (fr["mapped"] - 1) if mapping and fr["mapped"] > 1 else None
    cpu_ms["router"] = (1e3 * (router_cpu1 - router_cpu0) / fr["mapped"]
                        if router_cpu0 is not None and router_cpu1 is not None and fr["mapped"] else None)
    out["cpu_ms_per_frame"] = cpu_ms
    worst = max((v for v in (cpu_ms["edge"], cpu_ms["mapper"]) if v), default=None)
    out["e2e_fps_own_cores"] = 1e3 / worst if worst else None
    out["e2e_own_cores_vs_encoder"] = out["e2e_fps_own_cores"] / enc_fps if worst else None
    map_cpu = out["integrate_cpu_ms"].get("mean")
    out["mapper_map_fps_cpu_bound"] = 1e3 / map_cpu if map_cpu else None
    out["rates"] = {"encoder_alone_fps": enc_fps, "edge_alone_fps": alone["edge_alone_fps"], "e2e_fps": out["e2e_fps"]}
    out["ratios"] = {"edge_alone_vs_encoder_alone": alone["edge_alone_fps"] / enc_fps,
                     "e2e_vs_encoder_alone": out["e2e_vs_encoder"], "e2e_vs_edge_alone": out["e2e_vs_edge_alone"]}
    out["load_avg_1_5_15"] = [round(x, 2) for x in os.getloadavg()]
    out["bytes_per_frame"] = {"mean": float(np.mean(sizes)) if sizes else None,
                              "max": int(np.max(sizes)) if sizes else None, "n": len(sizes),
                              "target_max": 100_000}
    stop_all()


def _wait_drained(c, edge, n_frames: int, deadline_s: float, settle_s: float = 3.0) -> dict | None:
    """Poll the mapper's stats until the edge has exited and the mapper has settled
    (``query_client.vocabulary.settled``: every frame accounted for, queues empty, the map
    flushed) on all ``n_frames`` it sent, or, short of that (frames lost on the wire), until it
    has settled on fewer and the counts have not moved for ``settle_s`` seconds (a frame still
    on the wire when the edge exits arrives after its queue read empty, so "edge gone and
    settled" alone is early)."""
    from query_client.vocabulary import settled

    end = time.monotonic() + deadline_s
    st, last, still_since = None, None, 0.0        # still_since: set whenever last is
    while time.monotonic() < end:
        time.sleep(0.5)
        try:
            st = c.stats(timeout=5.0)
        except Exception:
            continue
        if edge.poll() is None or not settled(st):
            continue
        if settled(st, received=n_frames):
            break
        seen = (st["frames"]["mapped"], st["frames"]["dropped"])
        if seen != last:
            last, still_since = seen, time.monotonic()
        elif time.monotonic() - still_since >= settle_s:
            break
    return st


def _cpu_s(p) -> float | None:
    """CPU seconds (user + system, all threads) of a running child process."""
    try:
        import psutil

        t = psutil.Process(p.pid).cpu_times()
        return float(t.user + t.system)
    except Exception:
        return None


def _queries(args, out: dict, work: Path, pca_path: Path, shm: str, start) -> None:
    from common.zenoh_session import ZenohConfig, free_tcp_port
    from query_client.client import Client

    # ---------------------------------------------------------------- queries on a big map
    zs = f"transport/shared_memory/enabled={shm}"
    snaps = work / "snaps"
    t0 = time.perf_counter()
    emb = _big_snapshot(snaps, args.query_voxels, pca_path, args.preset, args.query_rays)
    out["query_map_build_s"] = time.perf_counter() - t0
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    start("mapper_q", "mapper", "--mode", "router", "--listen", ep, "--zenoh-set", zs, f"preset={args.preset}",
          "map.vox_size=0.5", f"snapshots.dir={snaps}", "snapshots.on_exit=false", "layers.rate_hz=0",
          *args.mapper_set)  # the map config _big_snapshot built the snapshot with
    with Client(ZenohConfig(connect=[ep], connect_timeout_ms=120_000, shared_memory=args.shm), timeout=120.0) as c:
        st = None
        end = time.monotonic() + 300
        while time.monotonic() < end:
            try:
                st = c.stats(timeout=10.0)
                break
            except Exception:
                time.sleep(1.0)
        if st is None:
            raise RuntimeError("the mapper answered no stats request in 300 s")
        out["query_map_voxels"] = st["map"]["n_voxels"]
        out["query_map_rays"] = st["map"]["n_rays"]
        rtts, server = [], []
        c.query(embedding=emb, top_k=10, timeout=120.0)  # warm-up
        for _ in range(args.queries):
            t = time.perf_counter()
            r = c.query(embedding=emb, top_k=10, timeout=120.0)
            rtts.append((time.perf_counter() - t) * 1e3)
            server.append(r.timings.get("total", 0.0))
        out["query_rtt_ms"] = _pct(rtts)
        out["query_server_ms"] = _pct(server)
        out["query_server_stages_ms"] = {k: float(v) for k, v in r.timings.items()}
        out["query_mapper_rss_mb"] = c.stats(timeout=10.0).get("rss_mb")
