"""Several robots on one mapper, with real processes over loopback Zenoh: robots with their
own PCA bases share one map (answers match a single-basis run), a robot with another
encoder is refused and told, per-robot world_from_robot transforms, frames never mix
across robots, eviction and the memory bound under many robot ids, drop warnings."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from common.zenoh_session import ZenohConfig, free_tcp_port
from tests.support.processes import Proc, wait_for
from tests.support.roles import client

RES = "48x64"
FRAMES = 10
MAP = ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0", "rerun.file=",
       "snapshots.on_exit=false", "queues.per_robot=1000", "queues.idle_flush_s=0.5"]
QUERIES = ["car", "tree", "building", "road", "street lamp"]


@pytest.fixture(scope="module")
def recs(tmp_path_factory):
    from apps.bench.fleet import render_recordings

    return render_recordings(tmp_path_factory.mktemp("recs"), 3, FRAMES, RES)


def _class_names(rec: Path) -> list[str]:
    import yaml

    info = yaml.safe_load((rec / "recording.yaml").read_text())
    return list(info["source"]["classes"])


@pytest.fixture(scope="module")
def bases(recs, tmp_path_factory):
    """One PCA-16 basis per robot, fitted on that robot's own frames (all different)."""
    import torch

    from common.pca import PCA
    from common.recording import RecordingReader
    from encoders import make_encoder
    from encoders.config import EncoderConfig

    out = []
    d = tmp_path_factory.mktemp("bases")
    enc = make_encoder(EncoderConfig(kind="label"), class_names=_class_names(recs[0]))
    for i, rec in enumerate(recs):
        with torch.inference_mode():
            x = torch.cat([enc.encode(f.rgb, labels=f.labels).reshape(enc.feature_dim, -1).T
                           for f in RecordingReader(rec)])
        p = d / f"b{i}.npz"
        PCA.fit(x, 16).save(p)
        out.append(p)
    return out


def _edge(ep, robot, rec, basis=None, extra=()):
    args = ["edge", "--connect", ep, f"robot={robot}", "source.kind=recording", f"source.path={rec}",
            "publish.rate_hz=20", "publish.linger_s=3", "publish.lossless=true"]
    args += [f"pca.basis={basis}", "pca.out_dim=16"] if basis else ["pca.out_dim=16", "pca.fit_frames=3"]
    return args + list(extra)


def _mapper(ep, extra=()):
    return ["mapper", "--mode", "router", "--listen", ep, *MAP, *extra]


def _voxel_scores(c, text) -> dict:
    r = c.query(text, top_k=100_000, timeout=60.0)
    return {tuple(np.round(x, 2)): float(s) for x, s in zip(r.voxel_xyz, r.voxel_score, strict=True)}


def _all_mapped(c, robots, n=FRAMES):
    """Stats once every robot's ``n`` frames are mapped. The edges run with
    ``publish.lossless=true``: a loaded host's edge would otherwise replace an unsent frame in
    its one-slot queue, and two runs compared voxel by voxel would map different frames."""
    from query_client.vocabulary import settled

    st = c.stats(timeout=5.0)
    ok = all(st["robots"].get(r, {}).get("mapped", 0) >= n for r in robots)
    return st if ok and settled(st) else None


def _same_frames(st, robots=("r0", "r1", "r2"), n=FRAMES):
    """Every robot's ``n`` frames received and mapped once each, none dropped: runs compared
    voxel by voxel must map the same frames (a missing one moves scores by up to 0.35)."""
    for r in robots:
        x = st["robots"][r]
        assert x["received"] == x["mapped"] == n and x["dropped"] == 0, (r, x)


def _run(tmp_path, procs, name, edges, mapper_extra=(), after=None, on_client=None):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs.append(Proc(f"{name}-mapper", _mapper(ep, mapper_extra), tmp_path))
    out = {}
    with client(ep) as c:
        if on_client is not None:
            on_client(c)
        for robot, args in edges:
            procs.append(Proc(f"{name}-{robot}", args(ep), tmp_path))
            if robot == edges[0][0]:   # the first robot's space becomes the map's
                wait_for(lambda: c.stats(timeout=5.0)["feature_space"], 120, what="map created")
        robots = [r for r, _ in edges if not r.startswith("odd")]
        out["stats"] = wait_for(lambda: _all_mapped(c, robots), 180, every=0.5, what="all frames mapped")
        out["scores"] = {q: _voxel_scores(c, q) for q in QUERIES}
        if after is not None:
            out.update(after(c))
    return out


def _compare(a: dict, b: dict) -> dict:
    common = set(a) & set(b)
    d = np.array([abs(a[k] - b[k]) for k in common]) if common else np.array([1.0])
    return {"common": len(common) / max(len(a), len(b), 1), "max_abs": float(d.max()),
            "mean_abs": float(d.mean())}


@pytest.mark.timeout(420)
def test_three_bases_one_map_other_encoder_refused(tmp_path, procs, recs, bases):
    """3 robots with 3 different PCA bases build one map whose voxel scores match the same
    frames sent in one basis (within the re-projection error, measured in test_fleet), and
    a robot with another encoder is refused at the mapper and told at the edge.

    The two runs interleave the robots' frames differently; that changes no score beyond
    float16 rounding (4e-4 in process; test_fleet's frame-order test). What the comparison
    needs is the same frames in both runs: one frame missing changes a car score by up to
    0.35 (the one flaky failure, 0.31, was an edge replacing an unsent frame; see
    tests/test_fleet_same_frames.py), hence lossless edges and exactly FRAMES mapped per robot."""
    from common.robot_messages import decode_robot_status, robot_status_all

    seen: dict = {}

    def subscribe(c):
        def on(sample):
            st = decode_robot_status(sample.payload.to_bytes())
            seen.setdefault(st["robot"], []).append(st)
        c.session.declare_subscriber(robot_status_all(c.keys), on)

    def after(c):
        wait_for(lambda: any(s["state"] == "refused" for s in seen.get("odd", [])), 60, what="odd refused status")
        return {"final": c.stats(timeout=5.0)}

    edges = [(f"r{i}", (lambda ep, i=i: _edge(ep, f"r{i}", recs[i], bases[i]))) for i in range(3)]
    edges.append(("odd", lambda ep: _edge(ep, "odd", recs[0], extra=["encoder.kind=sim"])))
    multi = _run(tmp_path, procs, "multi", edges, after=after, on_client=subscribe)
    for p in procs:
        p.stop()
    procs.clear()
    st = multi["final"]
    assert st["robots"]["r1"]["reprojected"] and st["robots"]["r2"]["reprojected"]
    assert not st["robots"]["r0"]["reprojected"]
    odd = st["robots"]["odd"]
    assert odd["mapped"] == 0 and "different encoder family" in odd["space_error"]
    refused = [s for s in seen["odd"] if s["state"] == "refused"][0]
    assert "different encoder family" in refused["reason"] and "\n" not in refused["reason"]
    assert any(s["state"] == "accepted" and s["reprojected"] for s in seen["r1"])
    mlog = (tmp_path / "multi-mapper.log").read_text()
    assert sum("odd" in ln and "different encoder family" in ln for ln in mlog.splitlines()) == 1, mlog[-3000:]
    elog = (tmp_path / "multi-odd.log").read_text()
    assert "refused this robot's frames: different encoder family" in elog, elog[-3000:]
    # the same frames, all in robot 0's basis (the map's)
    single = _run(tmp_path, procs, "single",
                  [(f"r{i}", (lambda ep, i=i: _edge(ep, f"r{i}", recs[i], bases[0]))) for i in range(3)])
    for run in (multi, single):
        _same_frames(run["stats"])
    for q in QUERIES:
        cmp = _compare(multi["scores"][q], single["scores"][q])
        assert cmp["common"] >= 0.97, (q, cmp)
        assert cmp["max_abs"] <= 0.02, (q, cmp)


def _transformed_recording(src: Path, dst: Path, frames, robot_from_world: np.ndarray, relabel: int | None = None):
    """Frames ``frames`` of recording ``src`` with poses re-expressed in another frame
    (``pose' = robot_from_world · pose``) and, optionally, every labelled pixel set to class
    ``relabel``."""
    import yaml

    from common.recording import RecordingReader, RecordingWriter

    info = yaml.safe_load((src / "recording.yaml").read_text())
    rd = RecordingReader(src)
    with RecordingWriter(dst, robot=rd[0].robot, source=info.get("source", {}), overwrite=True) as wr:
        for j, i in enumerate(frames):
            f = rd[i]
            lab = np.array(f.labels)
            if relabel is not None:
                lab[lab != 0] = relabel
            wr.write(dataclasses.replace(f, seq=j, pose=robot_from_world @ np.asarray(f.pose), labels=lab,
                                         depth=np.array(f.depth), rgb=np.array(f.rgb)))
    return dst


def _rigid(yaw_deg, t):
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = t
    return T


@pytest.mark.timeout(300)
def test_world_from_robot_two_frames_equal_one_frame(tmp_path, procs, recs, bases):
    """Robot a maps the first half of a lap in the world frame, robot b the second half in
    its own odometry frame (a known rigid transform away; set at run time through Zenoh for
    b): the map is the one of one robot mapping the whole lap in one frame."""
    from query_client.client import QueryError

    T = _rigid(90.0, [250.0, -40.0, 0.0])             # world_from_robot of b
    half = FRAMES // 2
    ra = _transformed_recording(recs[0], tmp_path / "ra", range(half), np.eye(4))
    rb = _transformed_recording(recs[0], tmp_path / "rb", range(half, FRAMES), np.linalg.inv(T))
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs.append(Proc("tf-mapper", _mapper(ep, ["fleet.world_from_robot={a: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}"]),
                      tmp_path))
    with client(ep) as c:
        wait_for(lambda: c.stats(timeout=5.0), 60, what="mapper up")
        np.testing.assert_allclose(c.world_from_robot("b", T), T)          # set at run time
        np.testing.assert_allclose(c.world_from_robot("b"), T)             # read back
        np.testing.assert_allclose(c.world_from_robot("a"), np.eye(4))     # from the config
        assert c.world_from_robot("nobody") is None
        with pytest.raises(QueryError, match="rigid"):
            c.world_from_robot("b", np.diag([2.0, 1, 1, 1]))
        np.testing.assert_allclose(c.world_from_robot("b"), T)             # a refused value changes nothing
        procs.append(Proc("tf-a", _edge(ep, "a", ra, bases[0]), tmp_path))
        wait_for(lambda: c.stats(timeout=5.0)["feature_space"], 120, what="map created")
        procs.append(Proc("tf-b", _edge(ep, "b", rb, bases[0]), tmp_path))
        wait_for(lambda: _all_mapped(c, ["a"], half) and _all_mapped(c, ["b"], FRAMES - half), 180, every=0.5,
                 what="both mapped")
        two = {q: _voxel_scores(c, q) for q in QUERIES}
    for p in procs:
        p.stop()
    procs.clear()
    one = _run(tmp_path, procs, "one", [("solo", lambda ep: _edge(ep, "solo", recs[0], bases[0]))])
    for q in QUERIES:
        cmp = _compare(two[q], one["scores"][q])
        assert cmp["common"] >= 0.97 and cmp["max_abs"] <= 0.02, (q, cmp)


@pytest.mark.timeout(300)
def test_frames_of_two_robots_never_mix(tmp_path, procs, recs, bases):
    """Robot a sees only cars, robot b only trees, 1 km apart (world_from_robot): every car
    voxel is where a drove and every tree voxel where b drove, and each robot's frames are
    mapped in its own order (seq) and all of them."""
    from synthetic_world.scene import World

    names = _class_names(recs[0])
    car, tree = names.index("car"), names.index("tree")
    ra = _transformed_recording(recs[0], tmp_path / "cars", range(FRAMES), np.eye(4), relabel=car)
    rb = _transformed_recording(recs[1], tmp_path / "trees", range(FRAMES), np.eye(4), relabel=tree)
    shift = "fleet.world_from_robot={b: {xyz: [1000, 0, 0]}}"
    res = _run(tmp_path, procs, "mix", [("a", lambda ep: _edge(ep, "a", ra, bases[0])),
                                        ("b", lambda ep: _edge(ep, "b", rb, bases[0]))], [shift])
    st = res["stats"]
    for r in ("a", "b"):
        x = st["robots"][r]
        assert x["mapped"] == x["received"] >= FRAMES - 2 and x["last_seq"] == FRAMES - 1, x
        assert st["robots"][r]["seq_regressions"] == 0
    world = World.generate(0, "default")
    span = np.abs(np.array(world.bounds())).max() + 30.0 if callable(getattr(world, "bounds", None)) else 200.0
    for q, own_x in (("car", 0.0), ("tree", 1000.0)):
        sc = res["scores"][q]
        xyz = np.array(list(sc))
        s = np.array(list(sc.values()))
        best = xyz[s >= s.max() - 0.05]
        assert len(best) > 5
        assert np.all(np.abs(best[:, 0] - own_x) < span), (q, best[:, 0].min(), best[:, 0].max())


@pytest.mark.timeout(240)
def test_many_robot_ids_bounded_and_evicted(tmp_path, procs):
    """1,000 robot ids that never serve a feature space: the mapper tracks at most
    fleet.max_robots, holds at most fleet.pending_max_frames frames, evicts them after
    fleet.no_space_evict_s (status 'evicted'), and its memory stays bounded."""
    from common.frame import Frame
    from common.robot_messages import decode_robot_status, robot_status_key
    from common.wire import encode_frame
    from common.zenoh_session import open_session

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs.append(Proc("ids-mapper", _mapper(ep, ["fleet.max_robots=200", "fleet.no_space_evict_s=15",
                                                 "fleet.pending_max_frames=16", "fleet.pending_ttl_s=30",
                                                 "queues.per_robot=4"]),
                      tmp_path))
    g = np.random.default_rng(0)
    h, w = 120, 160
    K = np.array([[80.0, 0, 80], [0, 80, 60], [0, 0, 1]])
    base = Frame(robot="x", seq=0, stamp=0.0, pose=np.eye(4), intrinsics=K,
                 depth=np.full((h, w), 5.0, np.float32), rgb=np.zeros((h, w, 3), np.uint8),
                 features=g.standard_normal((16, h // 8, w // 8)).astype(np.float16),
                 feature_space="ghost-1-000000000000-16")
    statuses = []
    with client(ep) as c:
        rss0 = wait_for(lambda: c.stats(timeout=5.0)["rss_mb"], 60, what="mapper up")
        sub = c.session.declare_subscriber(robot_status_key(c.keys, "g00000"),
                                           lambda s: statuses.append(decode_robot_status(s.payload.to_bytes())))
        s = open_session(ZenohConfig(connect=[ep], mode="client"), default_mode="client")
        try:
            import zenoh

            for rep in range(2):
                for i in range(1000):
                    rb = f"g{i:05d}"
                    s.put(c.keys.frames(rb), encode_frame(dataclasses.replace(base, robot=rb, seq=rep)),
                          congestion_control=zenoh.CongestionControl.BLOCK)
                    time.sleep(0.003)        # about the decode rate: the mapper's raw queue is bounded too
        finally:
            s.close()
        last = {}

        def all_received():
            x = c.stats(timeout=5.0)
            done = x["frames"]["received"] >= 2000 and x["frames"]["received"] == last.get("n")
            last["n"] = x["frames"]["received"]
            return x if done else None
        st = wait_for(all_received, 120, every=2.0, what="all frames received")
        fl = st["fleet"]
        print("fleet ids:", {k: fl[k] for k in ("robots_tracked", "refused_robot_cap", "pending_frames")},
              "rss", rss0, "->", st["rss_mb"], "dropped before decode", st["frames"]["dropped"])
        assert fl["robots_tracked"] == 200                  # the cap was reached, not passed
        assert fl["refused_robot_cap"] >= 500 and st["frames"]["rejected"]["robot_cap"] == fl["refused_robot_cap"]
        assert fl["pending_frames"] <= 16 and st["frames"]["dropped"] == 0   # capped frames are rejects, not drops
        assert st["rss_mb"] - rss0 < 150, (rss0, st["rss_mb"])
        st2 = wait_for(lambda: (lambda x: x if x["fleet"]["robots_tracked"] == 0 else None)(c.stats(timeout=5.0)),
                       40, what="evicted")
        assert st2["fleet"]["evicted"] >= 200
        wait_for(lambda: any(x["state"] == "evicted" for x in statuses), 10, what="evicted status")
        sub.undeclare()


@pytest.mark.timeout(300)
def test_edges_adopt_the_maps_basis(tmp_path, procs, recs, bases):
    """One basis for a fleet by default: r0 brings a basis file and makes the map; r1 gives no
    basis and adopts the map's (no online fit, no re-projection), r2 asks for it explicitly
    (``pca.basis=map``); an edge of another encoder asking for it is refused in one line."""
    edges = [("r0", lambda ep: _edge(ep, "r0", recs[0], bases[0])),
             ("r1", lambda ep: _edge(ep, "r1", recs[1])),
             ("r2", lambda ep: _edge(ep, "r2", recs[2], "map")),
             ("odd", lambda ep: _edge(ep, "odd", recs[0], "map", extra=["encoder.kind=sim"]))]
    out = _run(tmp_path, procs, "adopt", edges)
    st = out["stats"]
    space = st["robots"]["r0"]["feature_space"]
    for r in ("r1", "r2"):
        assert st["robots"][r]["feature_space"] == space and not st["robots"][r]["reprojected"], st["robots"][r]
        log = (tmp_path / f"adopt-{r}.log").read_text()
        assert "adopting the map's PCA basis" in log and "fitting PCA" not in log, log[-2000:]
    odd = procs[-1]
    assert odd.p.wait(timeout=60) != 0
    err = [ln for ln in (tmp_path / "adopt-odd.log").read_text().splitlines() if "pca.basis=map" in ln]
    assert err and "different encoder family" in err[0], err
