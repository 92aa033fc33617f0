"""The search's instance fast paths (issue 46) against the full computation: the request's view
of each tracked instance (one sorted search for all of them, :func:`planning.instances.request_views`)
against a per-instance brute force over Python sets; the reply's found list (area, z band,
order, only the kept rows built) against every row built and sorted; and on a search, the
tracker's own instances (the request sees the identity's voxels) against the general path."""
from __future__ import annotations

import zlib

import numpy as np
import pytest

import planning.instances as inst
from common.conventions import voxel_center
from common.search_messages import SearchRequest
from mapper import search_answer as sa


def _tracked(rng, frames: int = 3) -> inst.InstanceTracker:
    """A tracker fed a few updates of random voxel sets (several instances, some split / grown)."""
    tr = inst.InstanceTracker(0.25, 3)
    base = np.unique(rng.integers(0, 14, (900, 3)), axis=0)
    for f in range(frames):
        keep = rng.random(len(base)) < 0.35
        tr.update("t", base[keep], rng.random(int(keep.sum())), f)
    return tr


def _unpack(keys: np.ndarray) -> np.ndarray:
    """Packed keys back to (N, 3) voxel indices (21 bits per axis, offset 2^20)."""
    return np.stack([((keys >> s) & 0x1FFFFF) - (1 << 20) for s in (42, 21, 0)], 1)


def _brute_view(i: inst.Instance, ijk: np.ndarray, conf: np.ndarray, vox: float, min_voxels: int) -> dict | None:
    """One instance seen through the request's voxels ``ijk`` / ``conf``, by Python sets."""
    where = {tuple(map(int, p)): n for n, p in enumerate(ijk)}
    mine = [where[k] for k in map(tuple, _unpack(i.keys).tolist()) if k in where]
    if len(mine) < max(1, min_voxels):
        return None
    p = ijk[mine]
    d = i.as_dict()
    d.update(centroid=[float(v) for v in (p.mean(0) + 0.5) * vox],
             box_min=[float(v) for v in voxel_center(p.min(0), vox)],
             box_max=[float(v) for v in voxel_center(p.max(0), vox)],
             confidence=float(conf[mine].max()), voxels=len(mine))
    return d


@pytest.mark.parametrize("seed", range(5))
def test_request_views_equal_a_per_instance_brute_force(seed: int):
    rng = np.random.default_rng(seed)
    tr = _tracked(rng)
    cur = tr.current("t")
    assert len(cur) >= 5                                      # something to compare
    have = np.concatenate([c.keys for c in cur])
    for share in (0.3, 0.8, 1.0):
        # the request's voxels: a share of the tracked ones plus others nearby, random order
        pick = rng.random(len(have)) < share
        mine = _unpack(have[pick])
        other = np.unique(rng.integers(-2, 16, (300, 3)), axis=0)
        ijk = np.unique(np.concatenate([mine, other]), axis=0)
        ijk = ijk[rng.permutation(len(ijk))]
        conf = rng.random(len(ijk)).astype(np.float32)
        rk = inst.pack_ijk(ijk)
        o = np.argsort(rk)
        for min_voxels in (1, 3, 6):
            got = inst.request_views(cur, rk[o], ijk[o], conf[o], tr.vox, min_voxels)
            want = [d for d in (_brute_view(c, ijk, conf, tr.vox, min_voxels) for c in cur) if d is not None]
            assert [got.as_dict(k) for k in range(len(got))] == want
            assert len(want) >= 1 or share < 1.0


def test_tracked_views_are_the_instances_own_figures():
    tr = _tracked(np.random.default_rng(9))
    cur = tr.current("t")
    v = inst.tracked_views(cur)
    assert len(cur) >= 5 and [v.as_dict(k) for k in range(len(v))] == [c.as_dict() for c in cur]
    assert len(inst.tracked_views([])) == 0


def _all_rows_sorted(views, req: SearchRequest) -> list[dict]:
    """Every row built, then filtered and sorted as the reply's found list is defined."""
    from planning.look_next import points_in_polygon

    rows = []
    for v, name in views:
        for k in range(len(v)):
            d = v.as_dict(k)
            d["target"] = name
            rows.append(d)
    poly, zb = req.polygon(), req.z_band
    rows = [d for d in rows if (poly is None or points_in_polygon(np.asarray([d["centroid"][:2]]), poly)[0])
            and (zb is None or not (d["box_max"][2] < zb[0] or d["box_min"][2] > zb[1]))]
    rows.sort(key=lambda d: (-round(d["confidence"], 3), -d["voxels"], d["id"]))
    return rows[:req.max_instances]


@pytest.mark.parametrize("seed", range(4))
def test_found_list_equals_every_row_built_and_sorted(seed: int):
    rng = np.random.default_rng(20 + seed)
    views = []
    for name in ("car", "tree"):
        cur = _tracked(rng, 2).current("t")
        v = inst.tracked_views(cur)
        v.confidence = np.round(rng.random(len(v)), int(rng.integers(2, 5)))      # ties at 3 decimals
        v.voxels = rng.integers(3, 6, len(v))                                        # ties in size too
        views.append((v, name))
    assert sum(len(v) for v, _ in views) >= 10
    for kw in (dict(), dict(box=[0.5, 0.5, 2.5, 3.0]), dict(z_band=[1.0, 2.0], max_instances=3),
               dict(area=[[0, 0], [3.5, 0], [0, 3.5]], z_band=[0.0, 1.5])):
        req = SearchRequest(targets=["car", "tree"], **kw).validate()
        want = _all_rows_sorted(views, req)
        assert want and sa._found(views, req) == want


def test_a_search_seeing_the_identity_voxels_equals_the_general_path(monkeypatch):
    """A request with the identity's probabilities and threshold is answered from the
    tracker's own instances; the same search through the general request view (the
    probabilities handed over as a copy) gives the same found list and events, over two map
    versions (the second relabels)."""
    import torch

    from apps.bench.query import _change, _space, build_map
    from semantic_map.query_copy import QueryCopy

    fs = _space(16)
    cfg, m = build_map(20000, 16, 30, fs)
    snap = QueryCopy()
    snap.sync(m, 1, 1)

    def phrases(fs, req, background, *a):                    # a seeded vector per phrase, no text model
        return torch.as_tensor(np.stack([np.random.default_rng(zlib.crc32(p.encode())).standard_normal(fs.lang_dim)
                                         for p in [*req.targets, *background]]), dtype=torch.float32)

    monkeypatch.setattr(sa, "embed_phrases", phrases)
    real = sa._identity_probabilities
    stores = {False: sa.TrackerStore(), True: sa.TrackerStore()}

    def ask(copy: bool, version: int) -> dict:
        if copy:
            monkeypatch.setattr(sa, "_identity_probabilities", lambda *a, **k: np.array(real(*a, **k)))
        req = SearchRequest(targets=["car"], threshold=cfg.search.identity_threshold, max_instances=50).validate()
        rep = sa.answer_search(snap, fs, req, cfg, stores[copy], None, map_version=version)
        monkeypatch.setattr(sa, "_identity_probabilities", real)
        return dict(found=rep.found, events=rep.events)

    fast, full = ask(False, 1), ask(True, 1)
    assert len(fast["found"]) >= 10 and fast == full
    g = torch.Generator().manual_seed(3)
    for _ in range(3):
        _change(m, 16, g, 28)
    snap.sync(m, 2, 2)
    fast, full = ask(False, 2), ask(True, 2)
    assert len(fast["found"]) >= 10 and len(fast["events"]) >= 1 and fast == full


@pytest.mark.parametrize("seed", range(3))
def test_tracker_fed_packed_keys_equals_fed_indices(seed: int):
    """The mapper feeds its trackers the copy's packed keys (no unpacking, one sort inside):
    the same events and instances, update after update, as the same voxels given as indices
    (in another order, with small groups below ``min_voxels`` among them)."""
    rng = np.random.default_rng(seed)
    by_ijk, by_keys = inst.InstanceTracker(0.25, 3, grace=1), inst.InstanceTracker(0.25, 3, grace=1)
    base = np.unique(rng.integers(-10, 10, (1500, 3)), axis=0)
    for f in range(4):
        keep = np.flatnonzero(rng.random(len(base)) < 0.5)
        ijk, conf = base[keep], rng.random(len(keep))
        p = rng.permutation(len(keep))
        ev_a = by_ijk.update("t", ijk, conf, f)
        ev_b = by_keys.update("t", None, conf[p], f, keys=inst.pack_ijk(ijk)[p])
        assert [e.as_dict() for e in ev_a] == [e.as_dict() for e in ev_b]
        assert len(ev_a) > 0
        got_a = [(i.as_dict(), i.keys.tolist()) for i in by_ijk.current("t")]
        got_b = [(i.as_dict(), i.keys.tolist()) for i in by_keys.current("t")]
        assert got_a == got_b and len(got_a) >= 3
    with pytest.raises(ValueError, match="confidences"):
        by_keys.update("t", None, np.ones(2), 9, keys=inst.pack_ijk(base[:3]))
