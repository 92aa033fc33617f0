"""Instance identity a planner can keep (docs/identity.md): the same object has the same id
across thresholds, backgrounds and target lists, through a brief dip and across a snapshot
restore; events new / grow / lost are sent; run-time transforms and trackers live in the
snapshot. In process, on the synthetic world (seed 0, label encoder through the edge's
chain), objects named by the true car nearest to them."""
from __future__ import annotations

import base64
import json
import threading

import numpy as np
import pytest
import torch

from common.search_messages import SearchRequest, encode_search_request
from planning.instances import InstanceTracker

VOX = 0.5
BIG = 15          # voxels: an object-sized instance (smaller ones are fragments at car edges)
STAGE_A, STAGE_B = 16, 24


class Site:
    """A map of the first frames of a ground trajectory, its query copy and trackers."""

    def __init__(self):
        from apps.closed_loop.sensing import EdgeChain, SensorConfig
        from apps.closed_loop.world_model import LocalMapper, mapper_config
        from synthetic_world import World

        self.world = World.generate(0)
        self.chain = EdgeChain(self.world, SensorConfig(resolution=96, views=1), fit_views=2)
        self.cfg = mapper_config("rayfronts", 20.0, VOX, 96)
        self.loc = LocalMapper(self.chain.space, self.cfg, (0.2, 1.5))
        self.poses = self.world.trajectory("ground", STAGE_B, seed=0)
        self.cars = self.world.instances_of(self.world.class_id("car"))
        self.version = 0
        self.integrate(0, STAGE_A)

    def integrate(self, a: int, b: int) -> None:
        self.loc.integrate([self.chain.frame(p) for p in self.poses[a:b]])
        self.sync()

    def sync(self) -> None:
        """Bring the query copy up to the map (a new map version)."""
        self.version += 1
        self.loc.snap.reserve(self.loc.map)
        self.loc.snap.sync(self.loc.map, self.version, self.loc.frames)

    def ask(self, targets=("car",), trackers=None, cfg=None, **kw):
        from mapper.search_answer import answer_search

        req = SearchRequest(targets=list(targets), max_goals=0, max_instances=200, **kw).validate()
        return answer_search(self.loc.snap, self.chain.space, req, cfg or self.cfg,
                             self.loc.trackers if trackers is None else trackers,
                             None, map_version=self.version)

    def car_of(self, inst: dict) -> str | None:
        return car_of(self.cars, inst)


def car_of(cars: list, inst: dict, map_to_world: np.ndarray | None = None) -> str | None:
    """The true car within 2 voxels of an object-sized instance's centroid (None: a fragment
    or not a car); ``map_to_world`` (4x4) takes the centroid back into the world first."""
    if inst["voxels"] < BIG:
        return None
    c = np.asarray(inst["centroid"], np.float64)
    if map_to_world is not None:
        c = (map_to_world @ np.r_[c, 1.0])[:3]
    d = [float(np.linalg.norm(np.maximum(np.maximum(t.aabb_min - c, c - t.aabb_max), 0.0))) for t in cars]
    return cars[int(np.argmin(d))].name if min(d) <= 2 * VOX else None


def ids_by_car(site: Site, found: list[dict]) -> dict[str, int]:
    """``{true car: id}`` of the object-sized instances (each car once)."""
    out: dict[str, int] = {}
    for f in found:
        name = site.car_of(f)
        if name is not None:
            assert name not in out, f"two object-sized instances on {name}: {out[name]} and {f['id']}"
            out[name] = f["id"]
    return out


@pytest.fixture(scope="module")
def site():
    from tests.support.processes import text_cache_dir

    mp = pytest.MonkeyPatch()
    mp.setenv("RAYFRONTS_TEXT_CACHE", text_cache_dir())
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield Site()
    finally:
        torch.set_num_threads(old)
        mp.undo()


# ----------------------------------------------------------------------------- one object, one id
def test_same_objects_same_ids_across_thresholds_backgrounds_and_target_lists(site):
    base = site.ask(threshold=0.5)
    want = ids_by_car(site, base.found)
    assert len(want) >= 3, base.found                       # there is something to compare
    variants = {
        "threshold 0.9": dict(threshold=0.9),
        "background road/building/tree": dict(background=["road", "building", "tree"]),
        "no background": dict(background=[]),
        "targets car, person": dict(targets=["car", "person"]),
        "targets person, car at 0.9": dict(targets=["person", "car"], threshold=0.9),
    }
    base_ids = {f["id"] for f in base.found}
    for what, kw in variants.items():
        rep = site.ask(**kw)
        cars = [f for f in rep.found if f["target"] == "car"]
        got = ids_by_car(site, cars)
        differ = {name: (want[name], got.get(name)) for name in want if got.get(name) != want[name]}
        assert not differ, f"{what}: objects with another id (car: (base id, this id)): {differ}"
        # every car instance this request sees is one the base request saw (no id of its own)
        assert {f["id"] for f in cars} <= base_ids, (what, sorted({f["id"] for f in cars} - base_ids))


def test_an_object_below_threshold_for_an_update_comes_back_with_its_id(site):
    from mapper.search_answer import TrackerStore

    trackers = TrackerStore()
    before = site.ask(trackers=trackers)
    ids = ids_by_car(site, before.found)
    assert len(ids) >= 3
    name, oid = sorted(ids.items())[0]
    inst = next(f for f in before.found if f["id"] == oid)
    # the object's voxels leave the map for one update (no voxel above any threshold) ...
    m = site.loc.map
    xyz = m.voxel_xyz().numpy()
    lo, hi = np.asarray(inst["box_min"]) - VOX / 2, np.asarray(inst["box_max"]) + VOX / 2
    rows = np.flatnonzero(np.all((xyz >= lo) & (xyz <= hi), axis=1))
    saved = (m.voxel_xyz()[rows].clone(), m.voxels().rgb[rows].clone(), m.voxels().features[rows].clone())
    m.remove_voxels(m.voxel_ijk()[torch.as_tensor(rows)])
    site.sync()
    gone = site.ask(trackers=trackers)
    assert oid not in {f["id"] for f in gone.found}
    assert not [e for e in gone.events if e["id"] == oid], gone.events     # within the grace: not lost
    # ... and come back: the same id, no new object
    m.fuse_samples(*saved)
    site.sync()
    back = site.ask(trackers=trackers)
    assert ids_by_car(site, back.found).get(name) == oid
    assert not [e for e in back.events if e["kind"] == "new" and site.car_of(
        next(f for f in back.found if f["id"] == e["id"])) == name]
    # with no grace the same dip ends the object: event lost, and it comes back as a new one
    import dataclasses

    cfg0 = dataclasses.replace(site.cfg, search=dataclasses.replace(site.cfg.search, instance_grace=0))
    t0 = TrackerStore()
    oid0 = ids_by_car(site, site.ask(trackers=t0, cfg=cfg0).found)[name]
    m.remove_voxels(m.voxel_ijk()[torch.as_tensor(np.flatnonzero(np.all((m.voxel_xyz().numpy() >= lo) &
                                                                  (m.voxel_xyz().numpy() <= hi), axis=1)))])
    site.sync()
    lost = site.ask(trackers=t0, cfg=cfg0)
    assert {"kind": "lost", "id": oid0, "target": "car", "frame": lost.frames_mapped} in lost.events
    m.fuse_samples(*saved)
    site.sync()
    again = ids_by_car(site, site.ask(trackers=t0, cfg=cfg0).found)[name]
    assert again > oid0


def test_grace_in_the_tracker():
    """A missing instance stays matchable for ``grace`` updates, then is lost; ids never reused."""
    blob = np.array([[x, 0, 0] for x in range(5)])
    other = np.array([[x, 9, 0] for x in range(4)])
    tr = InstanceTracker(0.5, grace=2)
    tr.update("x", np.r_[blob, other], np.full(9, 0.9), 1)
    bid = next(i.id for i in tr.current() if i.voxels == 5)
    for frame in (2, 3):                                         # unseen for two updates: no event
        assert tr.update("x", other, np.full(4, 0.9), frame) == []
        assert bid not in {i.id for i in tr.current()}
    ev = tr.update("x", np.r_[blob[:3], other], np.full(7, 0.9), 4)       # back, smaller: same id
    assert ev == [] and {i.id for i in tr.current()} >= {bid}
    ev = tr.update("x", np.r_[blob, other], np.full(9, 0.9), 5)
    assert [(e.kind, e.id, e.voxels) for e in ev] == [("grow", bid, 5)]
    for frame in (6, 7):
        assert tr.update("x", other, np.full(4, 0.9), frame) == []
    assert [(e.kind, e.id) for e in tr.update("x", other, np.full(4, 0.9), 8)] == [("lost", bid)]
    ev = tr.update("x", np.r_[blob, other], np.full(9, 0.9), 9)
    assert [e.kind for e in ev] == ["new"] and ev[0].id > bid
    # the tracker's state carries missing instances too
    tr.update("x", other, np.full(4, 0.9), 10)
    rows, keys = tr.state()
    back = InstanceTracker(0.5, grace=2)
    back.load_state(rows, keys)
    assert [(r["id"], r["missed"]) for r in back.state()[0]] == [(r["id"], r["missed"]) for r in rows]
    assert back.update("x", np.r_[blob, other], np.full(9, 0.9), 11) == []     # the missing one is back


def test_events_new_grow_lost_in_the_reply(site):
    """new for each object the first time, grow for the objects more frames enlarged (with
    their new size, as the tracker holds it), lost for one that left the map (grace 0)."""
    import dataclasses

    from mapper.search_answer import TrackerStore

    trackers = TrackerStore()
    first = site.ask(trackers=trackers)
    assert len(ids_by_car(site, first.found)) >= 3
    news = {e["id"] for e in first.events if e["kind"] == "new"}
    assert {f["id"] for f in first.found} <= news
    size = {f["id"]: f["voxels"] for f in first.found}
    site.integrate(STAGE_A, STAGE_B)
    later = site.ask(trackers=trackers)
    assert later.frames_mapped == STAGE_B
    grown = {e["id"]: e["voxels"] for e in later.events if e["kind"] == "grow"}
    now = {f["id"]: f["voxels"] for f in later.found}
    assert grown, later.events
    for i, n in grown.items():
        assert n == now[i] and n > size[i], (i, n, size.get(i))
    merged = {e["id"] for e in later.events if e["kind"] == "merge"}
    assert {i for i in size if i in now and now[i] > size[i] and i not in merged} == set(grown)
    # the same map version asked again: the same events (what this version changed)
    assert site.ask(trackers=trackers).events == later.events
    # lost
    cfg0 = dataclasses.replace(site.cfg, search=dataclasses.replace(site.cfg.search, instance_grace=0))
    inst = max(later.found, key=lambda f: f["voxels"])
    m = site.loc.map
    xyz = m.voxel_xyz().numpy()
    rows = np.flatnonzero(np.all((xyz >= np.asarray(inst["box_min"]) - VOX / 2)
                                 & (xyz <= np.asarray(inst["box_max"]) + VOX / 2), axis=1))
    saved = (m.voxel_xyz()[rows].clone(), m.voxels().rgb[rows].clone(), m.voxels().features[rows].clone())
    m.remove_voxels(m.voxel_ijk()[torch.as_tensor(rows)])
    site.sync()
    rep = site.ask(trackers=trackers, cfg=cfg0)
    assert [e["kind"] for e in rep.events if e["id"] == inst["id"]] == ["lost"]
    m.fuse_samples(*saved)
    site.sync()


# ----------------------------------------------------------------------------- restart = same site
def _state(cfg, root):
    import dataclasses

    from mapper.state import MapperState

    cfg = dataclasses.replace(cfg, snapshots=dataclasses.replace(cfg.snapshots, dir=str(root)))
    return MapperState(cfg, threading.Event())


def test_save_and_restore_keeps_every_objects_id_and_the_transforms(site, tmp_path):
    from common.messages import encode_feature_space
    from mapper.robots_job import RobotsJob
    from mapper.search_answer import answer_search
    from mapper.snapshot_store import SnapshotStore
    from semantic_map.query_copy import QueryCopy

    before = site.ask(threshold=0.6)
    assert len(ids_by_car(site, before.found)) >= 3
    st = _state(site.cfg, tmp_path)
    st.map, st.space = site.loc.map, site.chain.space
    st.space_reply = encode_feature_space("sim", site.chain.space.to_body())
    st.version = st.flushed_version = site.version
    st.trackers = site.loc.trackers
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [12.5, -3.0, 0.25]
    RobotsJob(st).transforms.set("r7", T.reshape(-1).tolist())
    st.standing_searches["s1"] = SearchRequest(targets=["car"], standing=True, id="s1").validate()
    SnapshotStore(st).save()
    issued = st.trackers.next_id

    again = _state(site.cfg, tmp_path)
    fleet = RobotsJob(again)
    SnapshotStore(again).restore()
    assert np.array_equal(fleet.transforms.get("r7"), T)
    assert fleet.transforms.runtime() == {"r7": T.reshape(-1).tolist()}
    assert list(again.standing_searches) == ["s1"]
    snap = QueryCopy()
    snap.reserve(again.map)
    snap.sync(again.map, again.version, again.version)
    req = SearchRequest(targets=["car"], threshold=0.6, max_goals=0, max_instances=200).validate()
    after = answer_search(snap, again.space, req, site.cfg, again.trackers, None, map_version=again.version)
    # every object, matched by position, keeps its id
    by_pos = {tuple(np.round(f["centroid"], 4)): f["id"] for f in after.found}
    differ = [(f["id"], by_pos.get(tuple(np.round(f["centroid"], 4))), f["centroid"]) for f in before.found
              if by_pos.get(tuple(np.round(f["centroid"], 4))) != f["id"]]
    assert not differ, f"(id before, id after, centroid): {differ}"
    assert len(after.found) == len(before.found)
    assert not [e for e in after.events if e["kind"] in ("new", "lost", "split")], after.events
    assert again.trackers.new_id() >= issued                  # ids continue, never reused


def test_old_format_is_read_and_a_newer_one_refused(site, tmp_path, caplog):
    """meta.json format 1 (no format_version; standing searches as bare base64, no trackers,
    no transforms) restores; format_version 3 is refused naming it."""
    from common.messages import encode_feature_space
    from mapper.snapshot import capture_map
    from mapper.snapshot_store import SnapshotStore, write_snapshot

    req = SearchRequest(targets=["car"], standing=True, id="old").validate()
    body = encode_feature_space("sim", site.chain.space.to_body())
    meta = {"frames_mapped": 3, "robots": {}, "version": 2, "flushed_version": 2,
            "standing_searches": [base64.b64encode(encode_search_request(req)).decode()], "instance_next_id": 40}
    write_snapshot(tmp_path / "v1", capture_map(site.loc.map), body, meta)
    st = _state(site.cfg, tmp_path / "v1")
    SnapshotStore(st).restore()
    assert st.map is not None and list(st.standing_searches) == ["old"] and len(st.trackers) == 0
    assert st.trackers.new_id() == 40
    write_snapshot(tmp_path / "v3", capture_map(site.loc.map), body, dict(meta, format_version=3))
    st3 = _state(site.cfg, tmp_path / "v3")
    SnapshotStore(st3).restore()
    assert st3.map is None and "format_version 3; this build reads 1..2" in caplog.text
    gen = next((tmp_path / "v1").glob("snap-*"))
    assert "format_version" not in json.loads((gen / "meta.json").read_text())


# ----------------------------------------------------------------------------- a real mapper, SIGKILLed
def _search_json(ep: str) -> dict:
    import subprocess

    from tests.support.processes import ROOT, cli_cmd, proc_env

    r = subprocess.run(cli_cmd("search", "car", "--json", "--max-instances", "200", "--max-goals", "0",
                               "--connect", ep, "--timeout", "60"),
                       env=proc_env(), cwd=str(ROOT), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout)


@pytest.mark.timeout(300)
def test_sigkilled_mapper_restarts_as_the_same_site(tmp_path, procs, pca_file):
    """A transform set at run time, objects found, a snapshot, SIGKILL, a restart from it:
    the transform is back, every object (by position) has its id, and frames sent after the
    restart land where the ones before did (on the same objects, the same ids)."""
    from common.zenoh_session import free_tcp_port
    from synthetic_world import World
    from tests.support.processes import Proc, wait_for
    from tests.support.roles import client, edge_args, mapped, mapper_args

    world = World.generate(0)
    cars = world.instances_of(world.class_id("car"))
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]          # 90° about z, then 300 m away
    T[:3, 3] = [300.0, 100.0, 0.0]
    Tinv = np.linalg.inv(T)

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    args = mapper_args(ep, [f"snapshots.dir={tmp_path / 'snaps'}", "snapshots.period_s=0", "queues.idle_flush_s=0.3"])
    m1 = Proc("mapper1", args, tmp_path)
    procs.append(m1)
    with client(ep) as c:
        wait_for(lambda: mapped(c) == 0, 120, what="mapper up")
        c.world_from_robot("r1", T)
        edge = Proc("edge1", edge_args(ep, pca_file, frames=16, rate=8.0), tmp_path)
        procs.append(edge)
        assert edge.p.wait(timeout=180) == 0
        c.wait_settled(mapped=16, timeout=120)
        first = _search_json(ep)
        assert first["frames_mapped"] == 16
        objects = {car_of(cars, f, Tinv): f["id"] for f in first["found"] if car_of(cars, f, Tinv)}
        assert len(objects) >= 3, first["found"]
        # the frames landed through the transform: no object where the untransformed cars are
        assert not [f for f in first["found"] if car_of(cars, f)]
        # events in --json: each object's "new" (this is the trackers' first update)
        new = {e["id"] for e in first["events"] if e["kind"] == "new"}
        assert {f["id"] for f in first["found"]} <= new, first["events"]
        c.snapshot(save=True)
    m1.p.kill()                                             # SIGKILL: no shutdown, only the snapshot
    m1.p.wait()
    m2 = Proc("mapper2", args, tmp_path)
    procs.append(m2)
    with client(ep) as c:
        wait_for(lambda: c.stats()["snapshot"].get("restored") is True, 120, what="restored mapper")
        assert np.allclose(c.world_from_robot("r1"), T)
        after = c.search("car", max_instances=200, max_goals=0)
        by_pos = {tuple(np.round(f["centroid"], 4)): f["id"] for f in after.found}
        differ = [(f["id"], by_pos.get(tuple(np.round(f["centroid"], 4))), f["centroid"]) for f in first["found"]
                  if by_pos.get(tuple(np.round(f["centroid"], 4))) != f["id"]]
        assert not differ, f"(id before, id after, centroid) of objects whose id changed: {differ}"
        # frames after the restart (the same robot, its transform restored) land on the same objects
        edge = Proc("edge2", edge_args(ep, pca_file, frames=16, rate=8.0), tmp_path)
        procs.append(edge)
        assert edge.p.wait(timeout=180) == 0
        c.wait_settled(mapped=32, timeout=120)           # 16 more
        later = c.search("car", max_instances=200, max_goals=0)
    assert later.frames_mapped == 32
    now = {car_of(cars, f, Tinv): f["id"] for f in later.found if car_of(cars, f, Tinv)}
    differ2 = {name: (i, now.get(name)) for name, i in objects.items() if now.get(name) != i}
    assert not differ2, f"cars whose id changed after the restart's frames (before, after): {differ2}"
    assert not [f for f in later.found if car_of(cars, f)]
    assert m2.stop() == 0



def test_a_tracker_update_makes_a_periodic_snapshot_due():
    """``TrackerStore.generation`` moves on a tracker update with a new input (the map worker
    then saves a periodic snapshot although the map did not change), not on a repeat."""
    from mapper.search_answer import TrackerStore

    ts, key = TrackerStore(), ("text", "car")
    ts.get(key, VOX, 1)
    ijk, conf = np.array([[0, 0, 0], [0, 0, 1]]), np.array([0.9, 0.8])
    g0 = ts.generation
    assert ts.update(key, ijk, conf, 1, (1, 1)) and ts.generation == g0 + 1      # "new"
    ts.update(key, ijk, conf, 1, (1, 1))                 # the same map version searched again
    assert ts.generation == g0 + 1
    ts.update(key, ijk[:1], conf[:1], 2, (2, 2))
    assert ts.generation == g0 + 2

def test_identity_settings_refused_with_one_line():
    from common.config import ConfigError
    from mapper.service_config import load_mapper_config

    cfg = load_mapper_config(None, ["search.identity_threshold=0.7", "search.instance_grace=0"])
    assert (cfg.search.identity_threshold, cfg.search.instance_grace) == (0.7, 0)
    for kv, msg in (("search.identity_threshold=1.0", r"search\.identity_threshold=1\.0: must be a probability"),
                    ("search.identity_threshold=nan", "must be a probability in"),
                    ("search.instance_grace=-1", r"search\.instance_grace=-1: must be >= 0")):
        with pytest.raises(ConfigError, match=msg) as e:
            load_mapper_config(None, [kv])
        assert "\n" not in str(e.value)
