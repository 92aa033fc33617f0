"""Faults and hostile input with real processes over loopback Zenoh.

Process faults: a mapper SIGKILLed and restarted from its snapshot answers as before; a
corrupt latest snapshot falls back to the older intact one; a SIGSTOPped edge and an edge
cut off by a network partition (network namespaces) are marked gone within 3 s with the
CLI defaults; an edge replaying a recording with a corrupt frame skips it and goes on; a
query during a 3-edge flood is answered (from the last consistent copy when the map lock is
busy) with bounded queues and memory.

Helpers (processes, the PCA basis, waits, the shared text-embedding cache) are
:mod:`tests.support`'s, shared with the robustness suite. Speed is not asserted here: the
query latency under flood against the unloaded one (the p95 bound) and the measured
gone-after-kill / -freeze times are ``rayfronts bench faults`` figures. What stays are
functional contracts, and the only time bound is one the configuration sets: a robot whose
link goes silent is marked gone when the link lease expires, so "within the lease + slack"
is the lease doing its job, not a speed figure (see :data:`GONE_S`). Processes that do not
interfere share one run: the restore and the snapshot-fallback tests start their mappers
from copies of one module-scoped run's snapshots.
"""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import uuid

import pytest

from apps.bench.faults import hostile_frame_headers, reject_costs
from apps.bench.faults import sample_frame_bytes as _frame_bytes
from common.zenoh_session import DEFAULT_LEASE_MS, free_tcp_port
from tests.support.netns import ip, network_namespaces
from tests.support.processes import ROOT, Proc, proc_env, stop_all, wait_for
from tests.support.roles import client, edge_args, mapped, mapper_args, zenoh_client_config

#: a frozen / partitioned edge is marked gone within 3 s with the CLI defaults.
#: The link lease (``DEFAULT_LEASE_MS`` = 2 s, keep-alives every 0.5 s) closes a silent link
#: one lease after the last message; 1 s of slack covers the keep-alive phase and a loaded
#: machine. A contract derived from the configured lease, not a speed figure.
GONE_S = DEFAULT_LEASE_MS / 1000 + 1.0


def _gone_state(c, robot="r1"):
    st = c.stats(timeout=5.0)
    r = st["robots"].get(robot, {})
    return st if r and not r["present"] else None


@pytest.fixture(scope="module")
def shared_mapper(tmp_path_factory):
    """One mapper (CLI defaults, idle flush 0.5 s) for the tests that only need a mapper to
    talk to: each uses its own robot id and compares the mapper's global counters before and
    after (the tests run one at a time), so they do not interfere. Yields its endpoint."""
    logdir = tmp_path_factory.mktemp("shared_mapper")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    m = Proc("mapper", mapper_args(ep, ["queues.idle_flush_s=0.5"]), logdir)
    try:
        yield ep
        assert m.p.poll() is None, "the shared mapper died"
        assert m.stop() == 0
    finally:
        stop_all([m], signal.SIGKILL)


def _counters(c) -> dict:
    fr = c.stats()["frames"]
    return {"rejected": dict(fr["rejected"]), "rejected_total": fr["rejected_total"]}


def _delta(now: dict, before: dict) -> dict:
    out = {k: v - before["rejected"].get(k, 0) for k, v in now["rejected"].items()}
    return {k: v for k, v in out.items() if v}


# --------------------------------------------------------------------- freeze
@pytest.mark.slow
@pytest.mark.timeout(180)
def test_sigstop_edge_marked_gone_within_3s(tmp_path, procs, pca_file, shared_mapper):
    """A frozen edge (its sockets stay open: no FIN) is gone when the lease expires: within
    :data:`GONE_S` of the SIGSTOP; thawed, it comes back by itself."""
    ep = shared_mapper
    edge = Proc("edge", edge_args(ep, pca_file, robot="frozen", frames=400, rate=8.0,
                                  extra=["publish.loop=true"]), tmp_path)
    procs.append(edge)
    with client(ep) as c:
        wait_for(lambda: mapped(c, "frozen") >= 2, 120, what="2 frames mapped")
        edge.p.send_signal(signal.SIGSTOP)
        t_stop = time.time()
        try:
            st = wait_for(lambda: _gone_state(c, "frozen"), 15, every=0.05, what="frozen robot gone")
        finally:
            edge.p.send_signal(signal.SIGCONT)
        gone_after = st["robots"]["frozen"]["gone_at"] - t_stop
        print(f"gone after SIGSTOP: {gone_after:.2f} s")
        assert 0 < gone_after <= GONE_S, f"frozen edge marked gone {gone_after:.2f} s after SIGSTOP"
        # thawed, the same edge process comes back by itself
        wait_for(lambda: c.stats()["robots"]["frozen"]["present"], 60, what="robot back after SIGCONT")
    edge.p.kill()
    edge.p.wait()


# -------------------------------------------------------------------- partition
@pytest.fixture
def two_namespaces():
    """Edge namespace A and base-station namespace B joined by one veth pair (10.79.0.0/24)."""
    tag = uuid.uuid4().hex[:6]
    a, b = f"rfpA{tag}", f"rfpB{tag}"
    va, vb = f"pa{tag}", f"pb{tag}"
    with network_namespaces([a, b], [(a, b, va, vb, "10.79.0.1/24", "10.79.0.2/24")]):
        yield a, b, va


WATCHER = textwrap.dedent("""
    import json, sys, time
    from common.zenoh_session import ZenohConfig
    from query_client import Client
    with Client(ZenohConfig(connect=[sys.argv[1]], connect_timeout_ms=60000), timeout=10) as c:
        end = time.time() + 150
        while time.time() < end:
            try:
                st = c.stats(timeout=5.0)
                if st["robots"].get("r1", {}).get("mapped", 0) >= 2:
                    break
            except Exception:
                pass
            time.sleep(0.2)
        print("ready", flush=True)
        end = time.time() + 20
        while time.time() < end:
            r = c.stats(timeout=5.0)["robots"]["r1"]
            if not r["present"]:
                print(json.dumps({"gone_at": r["gone_at"]}), flush=True)
                break
            time.sleep(0.05)
""")


@pytest.mark.netns
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_partitioned_edge_marked_gone_within_3s(tmp_path, two_namespaces, pca_file):
    a, b, va = two_namespaces
    env = proc_env()
    ps = []

    def spawn(ns, name, args):
        p = Proc(name, args, tmp_path, prefix=("ip", "netns", "exec", ns))
        ps.append(p)
        return p.p

    shm = ["--zenoh-set", "transport/shared_memory/enabled=false"]
    try:
        mapper = spawn(b, "mapper", mapper_args("tcp/0.0.0.0:7447", shm))
        spawn(a, "edge", edge_args("tcp/10.79.0.2:7447", pca_file, frames=400, rate=8.0,
                                   extra=["publish.loop=true", *shm]))
        w = subprocess.Popen(["ip", "netns", "exec", b, sys.executable, "-c", WATCHER, "tcp/127.0.0.1:7447"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=str(ROOT))
        ps.append(w)
        assert w.stdout.readline().strip() == "ready", w.stderr.read()[-2000:]
        t_cut = time.time()
        ip("-n", a, "link", "set", va, "down")         # the radio link drops: no FIN, no RST
        out, err = w.communicate(timeout=60)
        assert out.strip(), f"robot never marked gone after the partition: {err[-2000:]}"
        gone_after = json.loads(out.strip().splitlines()[-1])["gone_at"] - t_cut
        print(f"gone after partition: {gone_after:.2f} s")
        assert 0 < gone_after <= GONE_S, f"partitioned edge marked gone {gone_after:.2f} s after the cut"
        assert mapper.poll() is None, "mapper died"
    finally:
        stop_all(reversed(ps), signal.SIGINT, 20)


# ----------------------------------------------------------- corrupt recording
@pytest.mark.slow
@pytest.mark.timeout(180)
def test_edge_skips_corrupt_recording_frame(tmp_path, procs, pca_file, shared_mapper):
    from common.recording import RecordingWriter, frame_file_name
    from edge.sources import SourceConfig, open_source

    rec = tmp_path / "rec"
    src = open_source(SourceConfig(kind="synthetic", robot="r1", resolution="96x128", n_frames=6, depth_limit=20.0))
    with RecordingWriter(rec, robot="r1", source={"kind": "synthetic", "class_names": list(src.class_names)}
                         ) as w:
        for f in src:
            w.write(f)
    bad = rec / "frames" / frame_file_name(2)
    data = bytearray(bad.read_bytes())
    data[len(data) // 2:] = b"\0" * (len(data) - len(data) // 2)     # the second half zeroed: corrupt
    bad.write_bytes(bytes(data))

    ep = shared_mapper
    with client(ep) as c:
        wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
        before = _counters(c)
        edge = Proc("edge", ["edge", "--connect", ep, "--rate", "5", "robot=rec1", "source.kind=recording",
                             f"source.path={rec}", f"pca.basis={pca_file}", "pca.out_dim=16",
                             "zenoh.connect_retry_s=0.2"], tmp_path)
        procs.append(edge)
        assert edge.p.wait(150) == 0, (tmp_path / "edge.log").read_text()[-3000:]
        st = wait_for(lambda: (lambda s: s if s["robots"]["rec1"]["mapped"] >= 5 else None)(c.stats()), 60,
                      what="the 5 good frames mapped")
        r = st["robots"]["rec1"]
        assert r["mapped"] == 5 and r["received"] == 5 and _delta(_counters(c), before) == {}, (r, st["frames"])
    log = (tmp_path / "edge.log").read_text()
    assert "Traceback" not in log
    assert sum("skipping frame 2" in ln for ln in log.splitlines()) == 1, log[-3000:]
    assert "'frames_skipped': 1" in log and "'frames_sent': 5" in log


# ------------------------------------------------- codec (unit level)
def test_rejected_header_costs_bounded_cpu():
    """Whatever the header, rejecting it costs little CPU (``rayfronts bench faults``'
    measurement: best of 5 per header; a hostile header that is accepted or raises anything
    but ``WireError`` fails it; the worst is printed). The bound here is 2.5x the required
    10 ms so a loaded CI machine cannot flake, while the old decoder took 680 ms - 3.4 s on the
    first two."""
    rc = reject_costs(repeats=5)
    for name, row in rc["headers"].items():
        assert row["reason"] in ("header", "frame.robot", "frame.pose"), (name, row)
    print(f"worst rejected header: {rc['worst_cpu_ms']:.2f} ms CPU ({rc['worst']}); "
          f"a real frame: {rc['real_frame_cpu_ms']:.2f} ms")
    assert rc["worst_cpu_ms"] <= 25.0, rc


def test_codec_rejects_trailing_bytes():
    from common.wire import WireError, decode_frame, decode_message, encode_message

    ok = _frame_bytes()
    decode_frame(ok)
    for tail in (b"\0", b"x", b"\0" * 8, bytes(range(200))):
        with pytest.raises(WireError, match="bytes after the end") as ei:
            decode_frame(ok + tail)
        assert ei.value.reason == "message"
    ctl = encode_message("rayfronts.test", 1, {"a": 1})          # no buffers: ends at the header
    assert decode_message(ctl)[2] == {"a": 1}
    with pytest.raises(WireError, match="bytes after the end"):
        decode_message(ctl + b"\0")


def test_frame_header_over_limit_refused_on_encode():
    from common.wire import WireError, decode_frame

    meta = {f"k{i}": "x" * 4000 for i in range(20)}              # 80 kB of meta: over the 64 KiB header
    with pytest.raises(WireError, match="frame header is .* over the wire limit"):
        _frame_bytes(meta=meta)
    small = _frame_bytes(meta={f"k{i}": "x" * 1000 for i in range(20)})
    assert len(decode_frame(small).meta) == 20


def test_reject_reasons_specific_and_bounded():
    """The reason names the field (``frame.depth``, ``frame.pose``...) from a fixed
    vocabulary, whatever text the error carries."""
    import struct

    import msgpack

    from common.wire import WireError, decode_frame, decode_message
    from common.wire.envelope import FRAME_FIELDS, reject_reason

    ok = _frame_bytes()
    _, _, body = decode_message(ok)
    hl = struct.unpack_from("<I", ok)[0]

    def with_header(fn):
        hdr = msgpack.unpackb(ok[4:4 + hl])
        fn(hdr)
        h = msgpack.packb(hdr, use_bin_type=True)
        pad = (-(4 + len(h))) % 8
        return struct.pack("<I", len(h)) + h + b"\0" * pad + ok[4 + hl + ((-(4 + hl)) % 8):]

    cases = {
        "frame.depth": lambda h: h["depth"].update(shape=[48, 65]),
        "frame.rgb": lambda h: h["rgb"].update(codec="webp"),
        "frame.robot": lambda h: h.update(robot="bad robot!"),
        "frame.seq": lambda h: h.update(seq=-1),
        "frame.stamp": lambda h: h.update(stamp="now"),
        "frame.meta": lambda h: h.update(meta=[1]),
        "frame.feature_space": lambda h: h.update(feature_space=7),
        "frame.intrinsics": lambda h: h.pop("intrinsics"),
        "frame.pose": lambda h: h.pop("pose"),
        "version": lambda h: h.update(v=9),
        "schema": lambda h: h.update(schema="other"),
    }
    for want, fn in cases.items():
        with pytest.raises(WireError) as ei:
            decode_frame(with_header(fn))
        assert ei.value.reason == want, (want, str(ei.value))
    # attacker-chosen text never becomes a reason
    rng = __import__("random").Random(0)
    seen = {reject_reason(f"frame.{''.join(rng.choices('abcdefgh.[] :', k=12))}: x") for _ in range(2000)}
    seen |= {reject_reason(''.join(rng.choices('abcdefgh.[] :', k=12))) for _ in range(2000)}
    allowed = {f"frame.{f}" for f in FRAME_FIELDS} | {"frame.malformed", "header", "schema", "version",
                                                       "message", "array", "encode"}
    assert seen <= allowed, seen - allowed


# ----------------------------------------------- incremental copy (unit level)
def test_semantic_change_journal_keeps_a_copy_exact():
    """A copy maintained from ``take_changes`` (changed rows only) equals the store after any
    mix of fuses and prunes; a second owner, a reload or an overflow asks for everything."""
    import torch

    from semantic_map.semantic_voxels import SemanticVoxels

    g = torch.Generator().manual_seed(0)
    sem = SemanticVoxels(0.5, 8)
    owner = object()
    copy_f = torch.zeros((0, 8))
    copy_k = torch.zeros(0, dtype=torch.int64)

    def sync():
        nonlocal copy_f, copy_k
        rows = sem.take_changes(owner)
        n = len(sem)
        if rows is None:
            copy_f, copy_k = sem.feat.clone(), sem.keys.clone()
            return "all"
        f = torch.zeros((n, 8))
        k = torch.zeros(n, dtype=torch.int64)
        m = min(n, copy_f.shape[0])
        f[:m], k[:m] = copy_f[:m], copy_k[:m]
        f[rows], k[rows] = sem.feat[rows], sem.keys[rows]
        copy_f, copy_k = f, k
        return int(rows.numel())

    assert sync() == "all"
    sizes = []
    for step in range(30):
        xyz = torch.rand((200, 3), generator=g) * 20
        sem.fuse(xyz, torch.rand((200, 3), generator=g), torch.randn((200, 8), generator=g))
        if step % 3 == 2 and len(sem) > 50:
            pick = torch.randperm(len(sem), generator=g)[:40]
            sem.remove(sem.keys[pick].clone())
        if step % 2:
            sizes.append(sync())
            torch.testing.assert_close(copy_f, sem.feat, rtol=0, atol=0)
            assert torch.equal(copy_k, sem.keys)
    assert all(isinstance(x, int) for x in sizes[1:])            # incremental after the first
    assert max(sizes[1:]) < len(sem)                               # ... and smaller than a full copy
    assert sem.take_changes(object()) is None                      # another owner: everything
    assert sem.take_changes(owner) is None                         # and then this one again
    # unconsumed, the journal stays bounded
    for _ in range(40):
        sem.fuse(torch.rand((300, 3), generator=g) * 20, torch.rand((300, 3), generator=g),
                 torch.randn((300, 8), generator=g))
    assert sem._journal_rows <= max(4096, len(sem) // 4)


# ------------------------------------------------------------ restore answers
QUERIES = ("car", "tree", "building")


def _answers(c) -> dict:
    out = {}
    for q in QUERIES:
        r = c.query(q, top_k=5)
        out[q] = {k: getattr(r, k) for k in ("voxel_xyz", "voxel_score", "ray_origin", "ray_direction", "ray_score",
                                            "cluster_xyz", "cluster_size", "cluster_score")}
        out[q]["frames_mapped"] = r.frames_mapped
    return out


@pytest.fixture(scope="module")
def snapshot_run(tmp_path_factory, pca_file):
    """One mapper with periodic snapshots, SIGKILLed (no clean shutdown: only the periodic
    snapshots survive) after its edge's 8 frames were mapped, flushed and snapshotted: the
    snapshot directory (several generations; the 8-frame one taken while the map still
    buffered frames: the idle flush comes 3 s after the last frame, the snapshot within
    0.5 s), and the stats and answers before the kill. The restore and the fallback tests
    each start a mapper from their own copy of it."""
    logdir = tmp_path_factory.mktemp("snapshot_run")
    snaps = logdir / "snaps"
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    started: list[Proc] = []
    try:
        m1 = Proc("mapper1", mapper_args(ep, [f"snapshots.dir={snaps}", "snapshots.period_s=0.5", "snapshots.keep=4",
                                              "queues.idle_flush_s=3"]), logdir)
        started.append(m1)
        with client(ep) as c:
            wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
            edge = Proc("edge", edge_args(ep, pca_file, frames=8, rate=4.0), logdir)
            started.append(edge)
            before_st = c.wait_settled(mapped=8, timeout=150)           # the 8 frames mapped and flushed
            assert before_st["frames"]["mapped"] == 8, before_st["frames"]
            wait_for(lambda: c.snapshot().get("frames_mapped") == 8, 30, what="a snapshot of the 8 frames")
            before = _answers(c)
            assert edge.p.wait(60) == 0
        m1.p.kill()
        m1.p.wait()
        yield {"snaps": snaps, "before": before, "before_st": before_st}
    finally:
        stop_all(reversed(started), signal.SIGKILL)


def _snap_copy(run, tmp_path):
    dst = tmp_path / "snaps"
    shutil.copytree(run["snaps"], dst)
    return dst


def _mapper_from(snaps, tmp_path, procs) -> tuple[str, Proc]:
    """(endpoint, process) of a mapper ``mapper2`` restoring the snapshot directory ``snaps``."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    m2 = Proc("mapper2", mapper_args(ep, [f"snapshots.dir={snaps}", "snapshots.period_s=0",
                                          "queues.idle_flush_s=0.5"]), tmp_path)
    procs.append(m2)
    return ep, m2


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_sigkilled_mapper_restored_answers_the_same(tmp_path, procs, snapshot_run):
    import numpy as np

    before, before_st = snapshot_run["before"], snapshot_run["before_st"]
    assert any(len(a["voxel_xyz"]) for a in before.values())
    snaps = _snap_copy(snapshot_run, tmp_path)
    ep, m2 = _mapper_from(snaps, tmp_path, procs)
    with client(ep) as c:
        st = c.wait_settled(timeout=60)                                # restored and flushed
        assert st["snapshot"].get("restored") is True and st["frames"]["mapped"] == 8
        assert st["map"]["n_voxels"] == before_st["map"]["n_voxels"] > 0
        assert st["map"]["n_rays"] == before_st["map"]["n_rays"]
        after = _answers(c)
    for q in QUERIES:
        for k, v in before[q].items():
            if k == "frames_mapped":
                assert after[q][k] == v == 8
            elif "score" in k:
                np.testing.assert_allclose(after[q][k], v, rtol=1e-6, atol=1e-7, err_msg=f"{q}.{k}")
            else:
                np.testing.assert_array_equal(after[q][k], v, err_msg=f"{q}.{k}")
    assert m2.stop() == 0


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_corrupt_latest_snapshot_falls_back_to_older(tmp_path, procs, snapshot_run):
    from mapper.snapshot import snapshot_generations

    snaps = _snap_copy(snapshot_run, tmp_path)
    gens = []
    for g in snapshot_generations(snaps):
        try:
            gens.append((g, json.loads((g / "meta.json").read_text())["frames_mapped"]))
        except (OSError, ValueError, KeyError):
            pass
    assert len(gens) >= 2 and gens[0][1] > gens[1][1] > 0, gens
    (newest, _), (older, older_frames) = gens[:2]
    arrays = newest / "map" / "arrays.npz"
    data = arrays.read_bytes()
    arrays.write_bytes(data[: len(data) // 2])            # the newest generation is corrupt
    ep, m2 = _mapper_from(snaps, tmp_path, procs)
    with client(ep) as c:
        st = c.wait_settled(timeout=60)                                # restarted and flushed
        snap = st["snapshot"]
        assert snap.get("restored") is True, snap
        assert snap["path"] == str(older) and st["frames"]["mapped"] == older_frames, (snap, older)
        assert snap.get("fallback_from") == [str(newest)], snap
        assert st["map"]["n_voxels"] > 0
    assert m2.stop() == 0
    log = (tmp_path / "mapper2.log").read_text()
    assert f"snapshot {newest} is broken" in log and f"restored snapshot {older}" in log, log[-3000:]


# ------------------------------------------------ frames in a wrong feature space
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_wrong_feature_space_frames_cost_no_real_frames(tmp_path, procs, pca_file, shared_mapper):
    import zenoh

    from common.wire import decode_frame, encode_frame

    ep = shared_mapper
    rec = tmp_path / "rec"
    with client(ep) as c:
        wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
        before = _counters(c)
        edge = Proc("edge", edge_args(ep, pca_file, robot="rw", frames=20, rate=8.0, extra=[f"recording.dir={rec}"]),
                    tmp_path)
        procs.append(edge)
        wait_for(lambda: mapped(c, "rw") >= 1, 120, every=0.05, what="first real frame mapped")
        from common.recording import RecordingReader

        real = decode_frame(RecordingReader(rec).read_bytes(0))
        real.feature_space = "label:bogus:pca-0000:16"
        bad = encode_frame(real)
        s = zenoh.open(zenoh_client_config(ep))
        try:
            pub = s.declare_publisher("rayfronts/robots/rw/frames", congestion_control=zenoh.CongestionControl.BLOCK)
            n_bad = 0
            while edge.p.poll() is None and n_bad < 400:
                pub.put(bad)
                n_bad += 1
                time.sleep(0.01)
            pub.undeclare()
        finally:
            s.close()
        assert edge.p.wait(120) == 0
        st = wait_for(lambda: (lambda s: s if s["robots"]["rw"]["mapped"] == 20 else None)(c.stats()), 60,
                      what="all 20 real frames mapped")
        r1 = st["robots"]["rw"]
        assert r1["dropped"] == 0 and r1["space_ok"] and r1["queue"] == 0, r1
        rej = wait_for(lambda: (lambda d: d if sum(d.values()) >= n_bad else None)(_delta(_counters(c), before)), 30,
                       what="every bad frame counted")
        assert rej == {"feature_space_mismatch": n_bad}, rej


# ----------------------------------------------------------- flood query bound
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_queries_answered_during_three_edge_flood(tmp_path, procs, pca_file, shared_mapper):
    """The flood query bound, functional part: while 3 edges flood the mapper at full rate, every query
    is answered with the mapped voxels (from the last consistent copy when the map lock is
    busy for longer than ``query.lock_timeout_s``, flagged ``stale``), queues stay within
    ``queues.per_robot`` (defaults: 0.25 s, 8), every frame a robot sent is mapped or
    dropped (counted), and the mapper's memory stays bounded. How long the
    queries take against the unloaded ones (the bound: p95 <= lock_timeout + 3 x unloaded)
    is ``rayfronts bench faults``' figure; the per-query times are printed here only."""
    import numpy as np

    from apps.bench.faults import timed_queries

    ep = shared_mapper
    per_robot = 8                     # the default queues.per_robot of the shared mapper
    robots = ["f1", "f2", "f3"]
    with client(ep) as c:
        wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
        for i in (1, 2, 3):   # the edges stand for robots' own computers: niced, so they load the
            # mapper with frames without starving its process of CPU on this one machine
            procs.append(Proc(f"flood{i}", edge_args(ep, pca_file, robot=f"f{i}", frames=400, rate=0.0,
                                                     extra=["publish.loop=true"]), tmp_path, nice=10))
        wait_for(lambda: all(mapped(c, f"f{i}") >= 2 for i in (1, 2, 3)), 150, what="three floods mapping")
        qs = timed_queries(c, 12)
        st = c.stats()
        for p in procs:                                                # the floods end
            p.p.kill()
            p.p.wait()

        # nothing lost: once the floods stop, every frame received is mapped or dropped (counted)
        rs = c.wait_settled(timeout=60)["robots"]
        assert all(rs[r]["received"] == rs[r]["mapped"] + rs[r]["dropped"] for r in robots), rs
        assert all(not rs[r]["rejected"] for r in robots), {r: rs[r]["rejected"] for r in robots}
        assert all(rs[r]["mapped"] >= 2 for r in robots)
    times = [q["s"] for q in qs]
    stale = sum(q["stale"] for q in qs)
    print(f"under flood (not asserted): query p50 {np.median(times) * 1e3:.0f} ms, max {max(times) * 1e3:.0f} ms, "
          f"stale answers {stale}/{len(qs)}, mapper RSS max {max(q['rss_mb'] for q in qs):.0f} MB, "
          f"mapped {st['frames']['mapped']}, dropped {st['frames']['dropped']}")
    # answered, with the map: the frames mapped so far, never fewer than an earlier answer saw
    assert all(q["voxels"] > 0 for q in qs), [q["voxels"] for q in qs]
    seen = [q["frames_mapped"] for q in qs]
    assert seen == sorted(seen) and seen[0] >= 6, seen
    assert all(q["stats"]["frames"]["mapped"] >= q["frames_mapped"] for q in qs)
    # bounded: every robot's queue within queues.per_robot, memory within a fixed ceiling
    for q in qs:
        assert max(q["stats"]["queues"].values()) <= per_robot, q["stats"]["queues"]
    assert max(q["rss_mb"] for q in qs) < 4000


def test_incremental_query_copy_answers_as_a_full_copy():
    """The query copy synced with the changed rows only answers exactly like a fresh
    full copy, through fuses, new voxels and prunes; after the first sync it copies only the
    changed rows (what the map lock is held for)."""
    import numpy as np
    import torch

    from apps.bench.query import _change, _space, build_map
    from common.messages import QueryRequest
    from mapper.query_answer import answer_snapshot
    from semantic_map.query_copy import QueryCopy

    fs = _space(16)
    cfg, m = build_map(8_000, 16, 300, fs)
    inc = QueryCopy()
    g = torch.Generator().manual_seed(3)
    for step in range(4):
        inc.reserve(m)
        inc.sync(m, step)
        if step:
            assert 0 <= inc.changed_rows < m.n_voxels() // 2, inc.changed_rows
        full = QueryCopy().take(m, step)
        for text in ("car", "tree"):
            a = answer_snapshot(inc, fs, QueryRequest(text=text, top_k=8), cfg.query)
            b = answer_snapshot(full, fs, QueryRequest(text=text, top_k=8), cfg.query)
            for k in ("voxel_xyz", "cluster_xyz", "cluster_size", "ray_origin"):
                np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"{step} {text} {k}")
            np.testing.assert_allclose(a.voxel_score, b.voxel_score, rtol=1e-6, atol=1e-7)
        _change(m, 16, g, 20)
        if step == 1:
            m.remove_voxels(m.voxel_ijk()[:500])         # a prune moves rows


def test_frame_callback_only_enqueues_and_the_queue_is_bounded(monkeypatch):
    """The Zenoh frame callback does not decode (a hostile payload costs it a copy);
    the decode thread validates and counts; a full queue waits, then drops the oldest, counted."""
    import threading

    import mapper.ingest as ingest_mod
    from common.keys import KeySpace
    from mapper.ingest import RAW_QUEUE_MAX, Ingest
    from mapper.service_config import MapperConfig
    from mapper.state import MapperState

    class Payload:
        def __init__(self, b):
            self.b = b

        def to_bytes(self):
            return self.b

    class Sample:
        def __init__(self, key, b):
            self.key_expr, self.payload = key, Payload(b)

    s = MapperState(MapperConfig(), threading.Event())
    s.keys = KeySpace("rayfronts")
    ing = Ingest(s)
    key = s.keys.frames("r1")
    hostile = next(d for name, d in hostile_frame_headers() if name == "8.9 MB map")
    t = time.process_time()
    ing.on_frame(Sample(key, hostile))
    cb_ms = (time.process_time() - t) * 1e3
    assert s.received == 1 and sum(s.rejected.values()) == 0      # not decoded in the callback
    print(f"callback with an 8.9 MB hostile payload: {cb_ms:.2f} ms CPU")
    monkeypatch.setattr(ingest_mod, "RAW_WAIT_S", 0.05)
    for _ in range(RAW_QUEUE_MAX + 9):                            # nobody decodes: the queue fills
        ing.on_frame(Sample(key, b"\x00" * 16))
    assert len(ing._raw) == RAW_QUEUE_MAX and ing.raw_dropped == 10 and s.dropped == 10
    th = threading.Thread(target=ing.decode_loop, daemon=True)
    th.start()
    try:
        end = time.monotonic() + 30
        while sum(s.rejected.values()) < RAW_QUEUE_MAX and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        s.stop.set()
        th.join(5)
    assert sum(s.rejected.values()) == RAW_QUEUE_MAX and s.received == RAW_QUEUE_MAX + 10
    assert s.received == sum(s.rejected.values()) + s.dropped
    assert set(s.rejected) <= {"header", "message"}, s.rejected


def test_rejected_query_request_costs_bounded_cpu():
    """Cheap rejects for the query queryable: hostile request headers are rejected cheaply too."""
    import struct

    import msgpack

    from common.messages import MessageError, QueryRequest, decode_query_request, encode_query_request

    assert decode_query_request(encode_query_request(QueryRequest(text="car"))).text == "car"
    H = {"schema": "rayfronts.query_request", "v": 1}

    def m(hdr: bytes) -> bytes:
        return struct.pack("<I", len(hdr)) + hdr

    worst = 0.0
    for data in (m(msgpack.packb({**H, **{f"k{i}": i for i in range(700_000)}})),
                 m(msgpack.packb({**H, "text": [[[{}] * 60] * 60] * 60})),
                 m(b"\x91" * 2_000_000 + b"\xc0"),
                 m(msgpack.packb({**H, "text": "a" * 5_000_000}))):
        best = 1e9
        for _ in range(3):
            t = time.process_time()
            with pytest.raises(MessageError):
                decode_query_request(data)
            best = min(best, time.process_time() - t)
        worst = max(worst, best * 1e3)
    print(f"worst rejected query request: {worst:.2f} ms CPU")
    assert worst <= 25.0


def test_bench_query_smoke(tmp_path):
    """``rayfronts bench query`` runs (tiny map, no figures asserted: speed belongs to the bench)."""
    from apps.cli import main

    out = tmp_path / "q.json"
    assert main(["bench", "query", "--voxels", "3k", "--queries", "2", "--changes", "2", "--rays", "50",
                 "--dim", "8", "--no-client", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    ip = d["sizes"]["3k"]["in_process"]
    assert ip["voxels"] >= 3000 and ip["steady_ms"]["n"] == 2 and ip["after_change_ms"]["n"] == 2
    assert ip["after_change_lock_held_ms"]["n"] == 2 and "similarity" in ip["steady_stage_p50_ms"]
    assert "machine" in d["meta"]
