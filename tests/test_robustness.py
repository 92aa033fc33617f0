"""Robustness of the distributed runtime with real processes over loopback Zenoh.

Each test starts ``rayfronts mapper`` (router mode, the base station) and ``rayfronts edge``
processes (client mode) and talks to them with ``query_client.Client``.

Speed (the helpers are :mod:`tests.support`'s, shared by the process-level test files): every
process started through :class:`Proc` (and the PCA fit) gets ``RAYFRONTS_TEXT_CACHE`` pointing
at one directory per pytest session, so only the first edge of a session loads the MiniLM text
model to embed its class names, and a mapper loads it only for a query text no earlier
process embedded (``encoders.text.base``; the embeddings read back are the exact float32
rows). The PCA basis is fitted once per session. Clients retry their connection every
0.2 s (the mapper is usually still starting when a test opens one). Tests wait for
conditions, never for fixed times; the only time bounds asserted are functional contracts
derived from a configured setting (the liveliness lease), never speed figures, which
belong to ``rayfronts bench`` (``bench faults``).
"""
from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np
import pytest

from apps.demo import zenoh_env
from common.zenoh_session import DEFAULT_LEASE_MS, free_tcp_port
from tests.support.instances import describe, match_by_position
from tests.support.processes import ROOT, Proc, cli_cmd, stop_all, wait_for
from tests.support.roles import FAST_MAP, client, edge_args, mapped, mapper_args, zenoh_client_config

#: a robot whose edge died is marked gone within the link lease (the CLI default, when the
#: FIN/RST of a killed process is lost) plus 1 s of slack for a loaded machine: a functional
#: contract derived from the configured lease, not a speed figure (those are in bench faults)
GONE_BOUND_S = DEFAULT_LEASE_MS / 1000 + 1.0
#: a car found again after a restart when an instance's centroid is this near its centroid of
#: before (m): 3 voxels of the 0.5 m map (tests.support.roles.FAST_MAP)
MATCH_M = 1.5

@pytest.fixture(scope="module")
def queue2_mapper(tmp_path_factory):
    """One mapper with ``queues.per_robot=2`` shared by the SIGKILL and the bounded-queue
    tests (different robot ids, per-robot counters; they run one after the other).
    Yields its endpoint."""
    logdir = tmp_path_factory.mktemp("queue2_mapper")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    m = Proc("mapper", mapper_args(ep, ["queues.per_robot=2", "queues.idle_flush_s=0.5"]), logdir)
    try:
        yield ep
        assert m.p.poll() is None, "the shared mapper died"
        assert m.stop() == 0, "the shared mapper exited uncleanly"
    finally:
        stop_all([m], signal.SIGKILL)


# --------------------------------------------------------------------------- tests
@pytest.mark.timeout(180)
def test_edge_sigkill_robot_gone_and_restart(tmp_path, procs, pca_file, queue2_mapper):
    """A SIGKILLed edge's robot is marked gone within :data:`GONE_BOUND_S` (the lease plus
    slack: the bound the lease guarantees even if the killed socket's FIN were lost; the
    measured time is ``rayfronts bench faults``' figure), the mapper keeps answering, and a
    restarted edge of the same robot is taken back and its map grows again."""
    ep = queue2_mapper
    edge = Proc("edge", edge_args(ep, pca_file, frames=200, rate=8.0, extra=["publish.loop=true"]), tmp_path)
    procs.append(edge)
    with client(ep) as c:
        wait_for(lambda: mapped(c, "r1") >= 3, 120, what="3 frames mapped")
        assert c.robots() == ["r1"]
        # a standing query refreshes as the map grows
        seen = []
        h = c.watch("car", lambda r: seen.append(r.frames_mapped), top_k=3)
        wait_for(lambda: len(seen) >= 2 and seen[-1] > seen[0], 60, what="standing query refreshes")
        h.cancel()
        assert h.id not in c.stats()["standing_queries"]
        # the command line client
        q = subprocess.run(cli_cmd("query", "car", "--json", "--top-k", "2", "--connect", ep), env=zenoh_env(),
                           cwd=str(ROOT), capture_output=True, text=True, timeout=60)
        assert q.returncode == 0, q.stderr[-1500:]
        assert json.loads(q.stdout)["query"] == "car"
        edge.p.kill()
        t_kill = time.time()
        st = wait_for(lambda: (lambda s: s if not s["robots"]["r1"]["present"] else None)(c.stats()), 10,
                      every=0.05, what="robot gone")
        gone_after = st["robots"]["r1"]["gone_at"] - t_kill
        assert gone_after <= GONE_BOUND_S, f"robot reported gone {gone_after:.2f} s after SIGKILL"
        # the mapper keeps serving queries (once it flushed what it buffered)
        c.wait_settled(timeout=30)
        r = c.query("car", top_k=3)
        assert len(r.voxel_xyz) > 0
        n_before = mapped(c, "r1")
        procs.append(Proc("edge2", edge_args(ep, pca_file, frames=200, rate=8.0), tmp_path))
        wait_for(lambda: c.stats()["robots"]["r1"]["present"], 60, what="robot back")
        wait_for(lambda: mapped(c, "r1") >= n_before + 3, 120, what="map growing again")
        st = c.stats()
        assert not st["robots"]["r1"]["rejected"], st["robots"]["r1"]
    for p in reversed(procs):
        if p.p.poll() is None:
            assert p.stop() == 0, f"{p.name} exited uncleanly"


@pytest.mark.timeout(240)
def test_malformed_flood_rejected_and_map_equals_good_frames(tmp_path, procs, pca_file):
    import zenoh

    from common.feature_space import FeatureSpace
    from common.frame import Frame
    from common.recording import RecordingReader
    from common.wire import decode_frame, encode_frame, encode_message
    from mapper.service_config import load_mapper_config
    from mapper.service_map import create_map, flush, integrate, layer_arrays

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs.append(Proc("mapper", mapper_args(ep, ["queues.per_robot=100000", "layers.max_voxels=100000000",
                                                  # no flush between the 4 Hz frames (0.25 s apart): the
                                                  # local reference map below is flushed once, at the end
                                                  "queues.idle_flush_s=3"]), tmp_path))
    rec = tmp_path / "rec"
    with client(ep) as c:
        wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
        procs.append(Proc("edge", edge_args(ep, pca_file, frames=12, rate=4.0, extra=[f"recording.dir={rec}"]),
                          tmp_path))
        # flood the same key while the good edge runs (once its first frame arrived)
        wait_for(lambda: c.stats()["frames"]["received"] >= 1, 120, every=0.05, what="first good frame")
        ok = encode_frame(Frame("r1", 0, 0.0, np.eye(4), np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]),
                                np.ones((48, 64), np.float32), np.zeros((48, 64, 3), np.uint8),
                                features=np.zeros((16, 6, 8), np.float16), feature_space="x"))
        rng = np.random.default_rng(0)
        kinds = [
            lambda i: rng.bytes(int(rng.integers(0, 64))),                       # garbage
            lambda i: ok[: int(rng.integers(1, len(ok) - 1))],                   # truncated
            lambda i: encode_message("rayfronts.frame", 1, {"robot": "r1"}),     # missing fields
            lambda i: encode_message("rayfronts.frame", 7, {"robot": "r1"}),     # wrong version
            lambda i: encode_message("not.a.frame", 1, {}),                      # wrong schema
            lambda i: encode_frame(Frame("r2", 0, 0.0, np.eye(4), np.eye(3) * 50 + np.diag([0, 0, -49]),
                                         np.ones((4, 4), np.float32), np.zeros((4, 4, 3), np.uint8),
                                         features=np.zeros((16, 2, 2), np.float16))),  # wrong robot for key
        ]
        s = zenoh.open(zenoh_client_config(ep))
        try:
            pub = s.declare_publisher("rayfronts/robots/r1/frames", congestion_control=zenoh.CongestionControl.BLOCK)
            for i in range(10_000):
                pub.put(bytes(kinds[i % len(kinds)](i)))
            # closing the session drops what Zenoh still queues: let the mapper take it all first
            wait_for(lambda: c.stats()["frames"]["rejected_total"] >= 10_000, 120, what="the flood received")
            pub.undeclare()
        finally:
            s.close()
        edge = procs[-1]
        edge.p.wait(180)
        assert edge.p.returncode == 0
        # the same good frames (the edge's recording), mapped in-process while the mapper
        # waits for its idle flush
        reader = RecordingReader(rec)
        assert len(reader) == 12
        from common.pca import PCA

        cfg = load_mapper_config(None, FAST_MAP)
        pca = PCA.load(pca_file)
        frames = [decode_frame(reader.read_bytes(i)) for i in range(len(reader))]
        fs = FeatureSpace("label", "x", pca.in_dim, pca=pca)
        m = create_map(cfg, fs)
        for f in frames:
            integrate(m, f)
        flush(m)
        vox_local, _ = layer_arrays(m, "voxels", type(cfg.layers)(max_voxels=10 ** 9, max_rays=10 ** 9))
        o_local, _ = layer_arrays(m, "rays", type(cfg.layers)(max_voxels=10 ** 9, max_rays=10 ** 9))
        st = c.wait_settled(mapped=12, timeout=120)           # the 12 good frames mapped and flushed
        assert st["frames"]["mapped"] == 12 and st["frames"]["rejected_total"] == 10_000, st["frames"]
        assert len(st["frames"]["rejected"]) >= 4   # counted by reason
        assert st["robots"]["r1"]["mapped"] == 12
        vox_remote, _ = c.layer("voxels")
        rays_remote, _ = c.layer("rays")
        stats_remote = st["map"]
    assert stats_remote["n_voxels"] == len(vox_local["xyz"]) == len(vox_remote["xyz"])
    assert stats_remote["n_rays"] == len(o_local["origin"])
    order_r = np.lexsort(vox_remote["xyz"].T)
    order_l = np.lexsort(vox_local["xyz"].T)
    np.testing.assert_array_equal(vox_remote["xyz"][order_r], vox_local["xyz"][order_l])
    np.testing.assert_array_equal(vox_remote["rgb"][order_r], vox_local["rgb"][order_l])
    mp = procs[0]
    assert mp.p.poll() is None, "mapper died"
    assert mp.stop() == 0


@pytest.mark.timeout(180)
def test_fast_edge_bounded_queue_counts_drops(tmp_path, procs, pca_file, queue2_mapper):
    ep = queue2_mapper
    with client(ep) as c:
        wait_for(lambda: c.mapper_alive(), 60, what="mapper alive")
        edge = Proc("edge", edge_args(ep, pca_file, robot="fast", frames=60, rate=0.0), tmp_path)
        procs.append(edge)
        edge.p.wait(150)
        assert edge.p.returncode == 0
        st = c.wait_settled(timeout=60)                        # the queue drained, the map flushed
        fr = st["robots"]["fast"]
        # every frame is accounted for and the queue stays bounded; how many are dropped
        # depends on the machine's speed (rayfronts bench e2e reports it), so no "> 0" here
        assert fr["received"] == fr["mapped"] + fr["dropped"] + sum(fr["rejected"].values()), fr
        assert fr["received"] > 0 and fr["mapped"] > 0, fr
        assert max(st["queues"].values()) <= 2
        # latency is bounded by the queue: at most (queue + 1) integrations plus transport
        lat, integ = st["timings"]["latency_ms"], st["timings"]["integrate_ms"]
        assert lat["max"] <= (2 + 2) * integ["max"] + 10_000, (lat, integ)
        assert st.get("rss_mb", 0) < 4000


@pytest.mark.timeout(240)
def test_mapper_restart_restores_snapshot_and_edge_reconnects(tmp_path, procs, pca_file, request):
    snaps = tmp_path / "snaps"
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    m1 = Proc("mapper1", mapper_args(ep, [f"snapshots.dir={snaps}", "snapshots.period_s=0.5"]), tmp_path)
    procs.append(m1)
    watcher = client(ep)                 # a standing query that lives through the restart
    request.addfinalizer(watcher.close)  # closed even when an assertion fails
    seen: list[int] = []
    # registered before any frame is mapped (no edge yet): answered empty now, published once the map exists
    wait_for(lambda: watcher.stats()["frames"]["mapped"] == 0, 60, what="mapper up")
    watcher.watch("car", lambda r: seen.append(int(r.frames_mapped)), top_k=3, timeout=60.0)
    assert seen == [0], seen
    found: list = []                     # and a standing search: (frames mapped, found rows)
    watcher.watch_search("car", lambda r: found.append((int(r.frames_mapped), list(r.found))), timeout=60.0)
    # Zenoh's reconnect backoff (1 s doubling to 4 s by default) capped at 0.5 s: the
    # reconnection is what is tested, not how long Zenoh's default backoff waits
    edge = Proc("edge", edge_args(ep, pca_file, frames=400, rate=6.0,
                                  extra=["publish.loop=true", "--zenoh-set", 'connect/retry={"period_init_ms": 200, '
                                         '"period_max_ms": 500, "period_increase_factor": 2}']), tmp_path)
    procs.append(edge)
    wait_for(lambda: any(f >= 1 for f in seen), 90, what="the standing query answered once frames are mapped")
    # something to check: the standing search has found cars before the kill
    wait_for(lambda: any(rows for _, rows in found), 150, what="the standing search finding cars")
    import json as _json

    def saved_car_ids() -> set:
        """Instance ids in the newest snapshot's trackers (format 2; empty for format 1)."""
        latest = (snaps / "LATEST").read_text().strip() if (snaps / "LATEST").exists() else ""
        m = _json.loads((snaps / latest / "meta.json").read_text()) if latest else {}
        return {int(r["id"]) for t in (m.get("instances") or {}).get("trackers", []) for r in t["instances"]}

    with client(ep) as c:
        wait_for(lambda: c.snapshot().get("frames_mapped", 0) >= 4, 150, what="a periodic snapshot of >= 4 frames")
        # a snapshot that holds found cars (trackers are saved by the periodic snapshot after
        # they change): the ids the restarted mapper must keep
        wait_for(lambda: saved_car_ids() & {i["id"] for _, rows in found for i in rows}, 60,
                 what="a periodic snapshot holding the cars found")
        m1.p.kill()   # no clean shutdown: only the periodic snapshot survives
        m1.p.wait()
    latest = (snaps / "LATEST").read_text().strip()
    meta = _json.loads((snaps / latest / "meta.json").read_text())
    saved_ids = saved_car_ids()
    saved = meta["frames_mapped"]
    assert saved >= 4 and len(meta["standing"]) == 1      # the standing query is in the snapshot
    assert len(meta["standing_searches"]) == 1              # and the standing search, with the id counter
    ids_before = {i["id"] for _, rows in found for i in rows}
    assert ids_before, found                             # established above: cars found before the kill
    last_before = next(rows for _, rows in reversed(found) if rows)
    # ids sent after the newest snapshot (the search may answer between the save and the
    # kill) are covered by the durable reservation, written before any of them was sent
    ids_file = snaps / "instance_ids.json"
    assert ids_file.exists(), "ids were issued but no reservation was written"
    restored_next = max(meta["instance_next_id"], _json.loads(ids_file.read_text())["reserved_below"])
    assert restored_next > max(ids_before), (restored_next, sorted(ids_before))
    before, before_found = len(seen), len(found)
    m2 = Proc("mapper2", mapper_args(ep, [f"snapshots.dir={snaps}", "snapshots.period_s=0"]), tmp_path)
    procs.append(m2)
    # the watch keeps delivering from the restarted mapper, answers of a map that grows past the snapshot
    wait_for(lambda: any(f > saved for f in seen[before:]), 120, what="standing query answers after the restart")
    wait_for(lambda: any(f > saved and rows for f, rows in found[before_found:]), 120,
             what="the standing search finding cars after the restart")
    after = [rows for f, rows in found[before_found:] if f > saved and rows]
    pairs, _ = match_by_position(last_before, after[0], MATCH_M)
    assert pairs, (f"no car of before the kill found again at its place: {[describe(i) for i in last_before]} "
                   f"vs {[describe(i) for i in after[0]]}")
    if "instances" in meta:
        # snapshot format 2 saves the trackers: every car the snapshot holds that is found again
        # at its place keeps its id (a car first seen after the snapshot may get a new one: what
        # came after the last snapshot is lost), and an id of before the kill sent again names
        # the car it named then
        kept = [(a, b) for a, b in pairs if a["id"] in saved_ids]
        assert kept, (f"no car of the snapshot ({sorted(saved_ids)}) found again at its place: "
                      f"{[describe(a) for a, _ in pairs]}")
        renamed = [f"{describe(a)} is now #{b['id']}" for a, b in kept if a["id"] != b["id"]]
        assert not renamed, f"{len(renamed)} of {len(kept)} saved cars changed id over the restart: {renamed}"
        last_row = {i["id"]: i for _, rows in found[:before_found] for i in rows}   # each id's last row
        moved = [f"{describe(i)} was {describe(last_row[i['id']])}" for rows in after for i in rows
                 if i["id"] in last_row and match_by_position([i], [last_row[i["id"]]], MATCH_M)[1]]
        assert not moved, f"ids given to other objects after the restart: {moved}"
    else:
        # format 1: the trackers start empty; every id issued after the restart continues from
        # the restored counter, so each car found again carries a new id, never an old one
        old_ids = sorted({i["id"] for rows in after for i in rows if i["id"] < restored_next})
        assert not old_ids, f"ids issued after the restart below the restored counter {restored_next}: {old_ids}"
        reused = [f"{describe(b)} was {describe(a)}" for a, b in pairs if b["id"] in ids_before]
        assert not reused, f"ids reused after the restart: {reused}"
    with client(ep) as c:
        st = wait_for(lambda: c.stats(), 60, what="restarted mapper")
        assert st["snapshot"].get("restored") is True
        assert st["frames"]["mapped"] >= saved            # at most the frames since the snapshot are lost
        # the same edge process reconnects by itself and the map keeps growing
        wait_for(lambda: c.stats()["robots"]["r1"]["received"] >= 3, 90, what="edge reconnected")
        wait_for(lambda: c.stats()["frames"]["mapped"] >= saved + 3, 90, what="map growing after restore")
        assert edge.p.poll() is None
    # while the restarted mapper lives, the cars it found keep their ids as the map grows
    grown = wait_for(lambda: next((rows for f, rows in reversed(found) if f >= saved + 3 and rows), None), 60,
                     what="a standing search answer of the grown map")
    watcher.close()
    pairs, lost = match_by_position(after[0], grown, MATCH_M)
    renamed = [f"{describe(a)} is now #{b['id']}" for a, b in pairs if a["id"] != b["id"]]
    assert not renamed, f"{len(renamed)} of {len(after[0])} cars changed id while the map grew: {renamed}"
    assert edge.stop() == 0
    assert m2.stop() == 0
