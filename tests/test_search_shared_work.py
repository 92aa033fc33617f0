"""Searches that share one map version's work (issue 46: a planner's repeated search, several
robots' standing searches): the scores kept per query-copy revision, the identity tracker not
fed the same voxels twice, the kept search volumes. Every answer is held equal to the same
request answered with nothing kept (a fresh full copy of the map, no kept scores or volumes,
an empty look-next cache), over map updates, robots, thresholds, areas and target lists."""
from __future__ import annotations

import zlib

import numpy as np
import pytest
import torch

from apps.bench.search import ROBOTS
from common.search_messages import SearchRequest
from mapper import search_answer as sa
from planning.look_next import LookNextCache
from semantic_map.query_copy import QueryCopy

DIM = 16


def _phrases(fs, req, background, *a):
    """A seeded vector per phrase (no text model): what ``embed_phrases`` returns."""
    return torch.as_tensor(np.stack([np.random.default_rng(zlib.crc32(p.encode())).standard_normal(fs.lang_dim)
                                     for p in [*req.targets, *background]]), dtype=torch.float32)


@pytest.fixture
def world(monkeypatch):
    from tests.support.search_world import search_world

    monkeypatch.setattr(sa, "embed_phrases", _phrases)
    fs, cfg, m, frames = search_world(DIM, 6000, 60)
    frames(0, 2)
    return fs, cfg, m, frames


REQUESTS = [dict(targets=["car"], from_xyz=ROBOTS[0]), dict(targets=["car"], from_xyz=ROBOTS[1]),
            dict(targets=["car"], from_xyz=ROBOTS[2], threshold=0.7, box=[-3.0, -3.0, 12.0, 12.0]),
            dict(targets=["tree"], from_xyz=ROBOTS[0]), dict(targets=["car", "tree"], z_band=[0.0, 3.0]),
            dict(targets=["car"], from_xyz=ROBOTS[0], background=["road", "wall"]),
            dict(targets=["car"], from_xyz=ROBOTS[0])]


def test_searches_sharing_a_version_equal_each_answered_with_nothing_kept(world, monkeypatch):
    fs, cfg, m, frames = world
    monkeypatch.setattr(sa, "BEYOND_AREAS", 1)           # three areas below: the kept ones are dropped
    snap = QueryCopy()
    kept, alone = sa.TrackerStore(), sa.TrackerStore()
    repeats = []
    real_repeat = sa.TrackerStore.repeat
    monkeypatch.setattr(sa.TrackerStore, "repeat", lambda self, *a: repeats.append(a) or real_repeat(self, *a))

    def answer(s, store, kw, version) -> dict:
        req = SearchRequest(max_instances=30, **kw).validate()
        rep = sa.answer_search(s, fs, req, cfg, store, lambda fn: fn(m), map_version=version)
        return dict(found=rep.found, events=rep.events, look_next=rep.look_next, beyond=rep.beyond)

    checked = dict(found=0, events=0, look_next=0)
    for version in (1, 2, 3):
        if version > 1:
            frames(version, version + 1)                     # a map update
        snap.sync(m, version, version)
        for kw in REQUESTS:
            got = answer(snap, kept, kw, version)
            with monkeypatch.context() as mp:                # nothing kept: a full recompute
                mp.setattr(sa, "SCORED_ENTRIES", 0)
                mp.setattr(sa, "VOLUME_ENTRIES", 0)
                mp.setattr(sa, "look_next_cache", lambda _m: LookNextCache())
                want = answer(QueryCopy().take(m, version, version), alone, kw, version)
            assert got == want, (version, kw)
            for k in checked:
                checked[k] += len(want[k])
    assert all(v > 0 for v in checked.values()), checked          # there was something to compare
    assert sa._SCORED[snap].hits >= 3 * 3 and len(repeats) >= 3 * 2  # and the kept work was used
    assert all(len(e.beyond) == 1 for e in sa._SCORED[snap].entries.values())


def test_kept_scores_follow_the_copy_revision(world):
    """A search after a sync sees the new rows: the kept scores of the old revision are dropped."""
    fs, cfg, m, frames = world
    snap = QueryCopy()
    snap.sync(m, 1, 1)
    req = SearchRequest(targets=["car"]).validate()
    a = sa.answer_search(snap, fs, req, cfg, sa.TrackerStore(), None, map_version=1)
    store = sa._SCORED[snap]
    before = len(store.entries)
    frames(2, 4)
    snap.sync(m, 2, 2)
    b = sa.answer_search(snap, fs, req, cfg, sa.TrackerStore(), None, map_version=2)
    assert before == 1 and store.revision == snap.revision and len(store.entries) == 1
    assert a.found != b.found and b.found == sa.answer_search(QueryCopy().take(m, 2, 2), fs, req, cfg,
                                                               sa.TrackerStore(), None, map_version=2).found
