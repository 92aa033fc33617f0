"""Issue 41's site rehearsal: the site of deploy/README.md, whole, on loopback.

Certificates and ACL from the shipped scripts (deploy/certs/make_certs.sh, which runs
deploy/acl/make_acl.py); a router with mutual TLS + ACL; two mapper shards (west / east of
x = 0, TLS clients with the mapper certificate, periodic snapshots); robot r1's edge (its
certificate) driving a lap that crosses the border; two planners (an operator's Client and r1's
onboard Client(robot="r1")) running search -> occupancy -> goal; the console over HTTPS with a
token (operator certificate) driven in Chromium. Then the east shard is SIGKILLed and restarted
from its snapshots. One test: everything that can be shared is (one world, one lap of 12 frames).

Asserted: complete answers (instances from both halves, site-wide unique ids, occupancy known on
both sides of a box across the border); ``missing_shards`` naming the dead shard in search and
occupancy replies (and the console's answer) while it is down; the same objects with the same
ids after the restart (matched by position); the frames mapped per shard before / after equal to
the snapshot's counters (nothing lost: the map had not changed since the snapshot); and what the
site refused before it still refuses.
"""
from __future__ import annotations

import json
import ssl

import numpy as np
import pytest

from common.zenoh_session import free_tcp_port
from tests.support.browser import module_browser
from tests.support.console import assert_rows_equal_api, http, search_in_page, wait_page
from tests.support.processes import Proc, stop_all, wait_for, wait_log
from tests.support.roles import FAST_MAP, edge_args
from tests.support.site import (
    acl_router,
    answer_of,
    assert_still_refused,
    certs_done,
    goal_of,
    make_certs,
    planner,
    tls_args,
)

pytestmark = pytest.mark.timeout(240)
browser = module_browser()

FRAMES = 12                 # one lap (x, y in +-41 m, +-24 m): crosses x = 0 at y = +23.6 and -23.6
TARGETS = ["car", "tree", "building"]
TOKEN = "site-rehearsal-token"
#: a box across the border where the lap crosses it driving +x (y = 23.6): west's frame at x = -17
#: looks across, east's frames from x = 3 on
BOX = ([-8.0, 19.0, 0.0], [12.0, 28.0, 3.0])
REGIONS = {"west": "[-1000, -1000, 0, 1000]", "east": "[0, -1000, 1000, 1000]"}


def _positions(found: list[dict]) -> dict[tuple, str]:
    """``{(target, centroid rounded to 1 mm): id}`` of a search's instances."""
    return {(f["target"], *(float(x) for x in np.round(f["centroid"], 3))): f["id"] for f in found}


def _settled(op, frames: int):
    """Every shard's stats once the lap's frames are mapped and each shard has settled
    (``query_client.vocabulary.settled``: every frame accounted for, the map flushed), else None."""
    from query_client.vocabulary import settled

    sts = op.stats_all(5.0)
    if set(sts) != {"west", "east"} or sum(s["frames"]["mapped"] for s in sts.values()) < frames:
        return None
    return sts if all(settled(s, mapped=0) for s in sts.values()) else None


def _latest_snapshot(d) -> dict:
    """meta.json of the generation ``LATEST`` names (docs/snapshot_format.md), read from disk."""
    return json.loads((d / (d / "LATEST").read_text().strip() / "meta.json").read_text())


def _check_complete(s, world) -> None:
    """A merged search over both shards: instances from both halves, site-wide unique ids."""
    ids = [f["id"] for f in s.found]
    assert len(ids) >= 4 and len(set(ids)) == len(ids), ids
    assert all(str(i).split(":")[0] == f["shard"] for i, f in zip(ids, s.found, strict=True)), ids
    xs = np.array([f["centroid"][0] for f in s.found])
    assert {f["shard"] for f in s.found} == {"west", "east"} and xs.min() < -2 and xs.max() > 2, ids
    assert s.look_next and np.all(world.labels_at(np.array([g["position"] for g in s.look_next])) == 0), s.look_next


def _loop(c, **kw):
    """One planner step: search -> the goal -> occupancy around it and of the border box."""
    r = c.search(TARGETS, max_instances=60, max_goals=5, from_xyz=[0.0, 23.6, 1.5], **kw)
    goal = goal_of(r)
    near = c.occupancy_points([goal], radius=2.0)
    box = c.occupancy_box(*BOX)
    assert near.states.shape == (1,) and box.states.ndim == 3
    return r, near, box


def test_site_rehearsal(tmp_path, procs, closer, pca_file, browser):
    from synthetic_world import World

    world = World.generate(0)
    # -- certificates and ACL from the shipped script; another CA for the refusals
    mk = make_certs(tmp_path / "certs", "--robot", "r1", "--robot", "r2", "--operator", "alice")
    mk_other = make_certs(tmp_path / "other", "--robot", "r1", "--no-acl")
    certs = certs_done(mk, tmp_path / "certs")
    port = free_tcp_port()
    ep = f"tls/localhost:{port}"
    router = acl_router(closer, certs, port)

    # -- two shards (TLS clients, mapper certificate), the console (operator certificate, HTTPS + token)
    snaps = {name: tmp_path / f"{name}-snaps" for name in REGIONS}

    def shard(name: str, log: str) -> Proc:
        return Proc(log, ["mapper", "--mode", "client", "--connect", ep, *tls_args(certs / "mapper"), *FAST_MAP,
                          "queues.idle_flush_s=0.3", "queues.per_robot=1000", f"shard.name={name}",
                          f"shard.region={REGIONS[name]}", f"snapshots.dir={snaps[name]}", "snapshots.period_s=0.5"],
                    tmp_path)
    procs.extend([shard("west", "west"), shard("east", "east")])
    cport = free_tcp_port()
    procs.append(Proc("console", ["console", "--connect", ep, *tls_args(certs / "operator-alice", "laptop-tls.json5"),
                                  "--http", f"0.0.0.0:{cport}", "--token", TOKEN, "--tls-cert",
                                  str(certs / "router" / "cert.pem"), "--tls-key", str(certs / "router" / "key.pem"),
                                  "--timeout", "30"], tmp_path))
    base = f"https://127.0.0.1:{cport}"
    ctx = ssl.create_default_context(cafile=str(certs / "ca" / "ca.pem"))
    bearer = {"Authorization": f"Bearer {TOKEN}"}

    with planner(certs / "operator-alice", port) as op, planner(certs / "robot-r1", port, robot="r1") as bot:
        wait_for(lambda: op.shards()[0] == ["east", "west"], 120, what="both shards announced")
        # -- robot r1's edge: one lap across the border, each frame to the shard owning it
        edge = Proc("edge", [*edge_args(ep, pca_file, robot="r1", frames=FRAMES, rate=8.0),
                             *tls_args(certs / "robot-r1")], tmp_path)
        procs.append(edge)
        assert edge.p.wait(timeout=120) == 0, (tmp_path / "edge.log").read_text()[-2000:]
        sts = wait_for(lambda: _settled(op, FRAMES), 60, every=0.3, what="the lap mapped and flushed on both shards")
        mapped = {k: s["frames"]["mapped"] for k, s in sts.items()}
        assert sum(mapped.values()) == FRAMES and min(mapped.values()) > 0, mapped

        # -- search -> occupancy -> goal, the operator's and the robot's planner, complete answers
        (r_op, near_op, box_op), (r_bot, near_bot, box_bot) = _loop(op), _loop(bot)
        _check_complete(r_op, world)
        assert answer_of(r_op) == answer_of(r_bot) and r_op.missing_shards == [] == r_bot.missing_shards
        assert np.array_equal(box_op.states, box_bot.states) and np.array_equal(near_op.states, near_bot.states)
        assert r_op.frames_mapped == FRAMES
        cx = box_op.origin[0] + (np.arange(box_op.states.shape[0]) + 0.5) * box_op.cell_m
        known = box_op.states != -1
        assert box_op.missing_shards == [] and known[cx < 0].sum() >= 100 and known[cx >= 0].sum() >= 100, (
            known[cx < 0].sum(), known[cx >= 0].sum())
        # the look-next goals (free in the true world: _check_complete) are free in the map too
        assert np.all(bot.occupancy_points([g["position"] for g in r_bot.look_next], radius=1.0).states == 0)
        # the robot's standing search: its first answer now, on its own key, from both shards
        got: list = []
        with bot.watch_search(TARGETS, got.append, max_instances=60):
            assert got and {f["shard"] for f in got[0].found} == {"west", "east"}
            assert sorted(f["id"] for f in got[0].found) == sorted(f["id"] for f in r_op.found)
            assert {k: s["search"]["standing"] for k, s in op.stats_all(5.0).items()} == {"west": 1, "east": 1}

        # -- the console over HTTPS with the token, in Chromium: its rows are the console API's answer
        wait_log(procs[2].p, tmp_path / "console.log", r"console at https://", 60)
        browser.call("Security.setIgnoreCertificateErrors", ignore=True)
        browser.navigate(f"{base}/?token={TOKEN}")
        wait_page(browser, "document.readyState === 'complete' && !!document.getElementById('q')", 30, "the page")
        rows = search_in_page(browser, "car")
        st, api = http(base + "/api/search?q=car&threshold=0.5", headers=bearer, context=ctx)
        assert st == 200 and api["missing_shards"] == [], api
        assert_rows_equal_api(browser, rows, api)
        # the console (operator identity) answers as the planners do: its instances are theirs
        by_id = {f["id"]: f for f in r_op.found}
        assert {f["shard"] for f in api["found"]} == {"west", "east"}, api["found"]
        assert all(np.allclose(by_id[f["id"]]["centroid"], f["centroid"], atol=1e-4)
                   for f in api["found"] if f["id"] in by_id)

        # -- east's last snapshot holds everything it mapped (and its trackers); then SIGKILL
        before = _positions(r_op.found)
        east_before = {k: v for k, v in before.items() if str(v).startswith("east:")}
        assert len(east_before) >= 3 and len(before) - len(east_before) >= 3, before
        wait_for(lambda: (lambda m: m["frames_mapped"] == mapped["east"] and m.get("instances", {}).get("trackers"))(
            _latest_snapshot(snaps["east"])) if (snaps["east"] / "LATEST").exists() else None, 30,
            what="east's snapshot of its whole map and trackers")
        snap_meta = _latest_snapshot(snaps["east"])
        procs[1].p.kill()
        procs[1].p.wait()

        # -- while east is down: both planners' replies (and the console's) name it
        def east_missing():
            r = op.search(TARGETS, max_instances=60, from_xyz=[0.0, 23.6, 1.5], timeout=5.0)
            return r if r.missing_shards else None
        down = wait_for(east_missing, 20, every=0.3, what="east named missing")
        assert down.missing_shards == ["east"] and {f["shard"] for f in down.found} == {"west"}
        r_bot2, near2, box2 = _loop(bot)
        assert r_bot2.missing_shards == ["east"] and near2.missing_shards == ["east"]
        assert box2.missing_shards == ["east"] and (box2.states != -1).sum() < known.sum()
        assert op.occupancy_box(*BOX).missing_shards == ["east"]
        st, api_down = http(base + "/api/search?q=car&threshold=0.5", headers=bearer, context=ctx)
        assert st == 200 and api_down["missing_shards"] == ["east"], api_down
        search_in_page(browser, "car")       # the page warns as the CLI does
        shown = browser.evaluate("document.getElementById('status').textContent")
        assert "shards that did not answer: east" in shown, shown

        # -- east restarted with the same name and snapshots: the same site
        procs.append(shard("east", "east-again"))
        wait_for(lambda: op.stats_all(5.0).get("east", {}).get("snapshot", {}).get("restored"), 120, every=0.3,
                 what="east restored from its snapshot")
        east_stats = op.stats_all(5.0)["east"]

        def east_back():
            r = op.search(TARGETS, max_instances=60, max_goals=5, from_xyz=[0.0, 23.6, 1.5], timeout=10.0)
            return r if not r.missing_shards else None
        after = wait_for(east_back, 30, every=0.3, what="east answering searches again")
        # frames: nothing lost beyond those mapped since the snapshot (none: the map was settled)
        assert snap_meta["frames_mapped"] == mapped["east"] == east_stats["frames"]["mapped"], (
            snap_meta["frames_mapped"], mapped, east_stats["frames"])
        assert op.stats_all(5.0)["west"]["frames"]["mapped"] == mapped["west"]
        assert after.frames_mapped == FRAMES
        # ids: every object found before (matched by position) has its id again
        now = _positions(after.found)
        differ = {k: (v, now.get(k)) for k, v in before.items() if now.get(k) != v}
        assert not differ, f"objects (target, x, y, z) whose id changed across the restart (before, after): {differ}"
        _check_complete(after, world)
        # the robot's planner loop gets the same answer again, whole
        r_bot3, _, box3 = _loop(bot)
        assert [f["id"] for f in r_bot3.found] == [f["id"] for f in after.found] and r_bot3.missing_shards == []
        assert box3.missing_shards == [] and np.array_equal(box3.states, box_op.states)

        # -- what the site refused before, it still refuses
        assert_still_refused(closer, router, port, certs, certs_done(mk_other, tmp_path / "other"))
        assert set(op.stats_all(5.0)["east"]["robots"]) == {"r1"}
    stop_all([procs[2]])
