"""Several robots in one map — the pure parts (mapper.robot_registry): feature-space compatibility and
re-projection between PCA bases (with the measured query-score error), world_from_robot
transforms, rates, status and the bounds on per-robot state."""
from __future__ import annotations

import collections
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from common.feature_space import FeatureSpace, compatibility
from common.pca import PCA
from mapper import robot_registry as fleet


def _features(n, d=384, seed=0, decay=0.97, shift=0.0):
    """Encoder-like features: a power-law spectrum, a common mean (plus ``shift``)."""
    g = np.random.default_rng(seed)
    scales = decay ** np.arange(d)
    x = g.standard_normal((n, d)) * scales + 0.3 + shift
    return x.astype(np.float32)


def _space(x, k, name="enc", version="1"):
    return FeatureSpace(name, version, x.shape[1], pca=PCA.fit(torch.as_tensor(x), k))


def test_reprojection_is_decompress_then_compress():
    xa, xb = _features(3000, seed=1), _features(3000, seed=2, shift=0.2)
    fa, fb = _space(xa, 32), _space(xb, 24)
    assert fa.id != fb.id
    rp = fleet.Reprojection(fa, fb)                       # robot b into map a
    assert rp.A.shape == (32, 24) and rp.b.shape == (32,)
    y = np.random.default_rng(3).standard_normal((24, 5, 7)).astype(np.float32)
    got = rp.features(y)
    flat = y.reshape(24, -1).T
    ref = fa.compress(fb.decompress(flat)).T.reshape(32, 5, 7)
    np.testing.assert_allclose(got, ref, atol=2e-4)
    np.testing.assert_allclose(rp.vector(y[:, 0, 0]), ref[:, 0, 0], atol=2e-4)
    with pytest.raises(ValueError):
        rp.features(y[:3])
    # same basis: identity
    same = fleet.Reprojection(fa, fa)
    np.testing.assert_allclose(same.A, np.eye(32), atol=1e-5)
    np.testing.assert_allclose(same.b, 0, atol=1e-5)
    # a raw (no PCA) robot into a PCA map: plain compression
    raw = FeatureSpace("enc", "1", 384)
    x1 = xa[:4]
    np.testing.assert_allclose(fleet.Reprojection(fa, raw).vector(x1[0]), fa.compress(x1)[0], atol=1e-4)


def test_reprojection_score_error_is_small_and_measured():
    """Three robots with bases fitted on different data (different means and samples) against
    the map's basis, scored with 64 queries against the uncompressed features: re-projection
    adds almost nothing to what the map's own basis loses."""
    xs = [_features(4000, seed=s, shift=0.1 * s) for s in range(3)]
    spaces = [_space(x, 100) for x in xs]
    test_x = np.concatenate([_features(1000, seed=10 + s, shift=0.1 * s) for s in range(3)])
    q = torch.as_tensor(_features(64, seed=99))
    errs = [fleet.reprojection_score_error(spaces[0], fs, test_x, q) for fs in spaces[1:]]
    for e in errs:
        base = e["map_basis"]
        assert base["max_abs"] > 0.01                      # the map's basis itself loses (noise-like data)
        assert e["max_abs"] < base["max_abs"] + 0.02, e
        assert e["mean_abs"] < base["mean_abs"] + 0.003, e
        assert e["top1_agree"] >= base["top1_agree"] - 0.1, e
    # same basis: only float16 rounding differs
    e0 = fleet.reprojection_score_error(spaces[0], spaces[0], test_x, q)
    assert abs(e0["max_abs"] - e0["map_basis"]["max_abs"]) < 1e-3
    # a basis that throws away the directions the queries use gives a large, visible error
    tiny = _space(xs[1], 2)
    bad = fleet.reprojection_score_error(spaces[0], tiny, test_x, q)
    assert bad["mean_abs"] > 2 * errs[0]["mean_abs"] and bad["top1_agree"] < errs[0]["top1_agree"]


def test_reprojection_loss_of_bases_on_different_classes_is_reported():
    """The map's basis fitted on ten classes, a robot's on ten others: the robot's classes become
    unqueryable in the map. Measured against the uncompressed features the loss is large (a
    comparison with the same features compressed in the map's basis would call it ~0)."""
    from encoders.text import make_text_encoder

    names = ["car", "tree", "building", "road", "water tower", "radio tower", "chimney", "bench", "lamp post",
             "fence", "bicycle", "truck", "boat", "bridge", "statue", "fountain", "tent", "sign", "bus", "crane"]
    emb = make_text_encoder("minilm-l6").encode_labels(names, templates="none").float().numpy()
    g = np.random.default_rng(0)

    def mixes(n, classes):
        w = g.dirichlet(np.full(len(classes), 0.3), size=n)
        return (w @ emb[classes]).astype(np.float32)

    first, second = list(range(10)), list(range(10, 20))
    map_fs = FeatureSpace("label", "1", 384, pca=PCA.fit(torch.as_tensor(mixes(3000, first)), 10))
    robot_fs = FeatureSpace("label", "1", 384, pca=PCA.fit(torch.as_tensor(mixes(3000, second)), 10))
    x = mixes(2000, second)                                   # what the second robot sees
    e = fleet.reprojection_score_error(map_fs, robot_fs, x, torch.as_tensor(emb[second]))
    assert e["max_abs"] > 0.3 and e["top1_agree"] < 0.8, e
    own = fleet.reprojection_score_error(robot_fs, robot_fs, x, torch.as_tensor(emb[second]))
    assert own["max_abs"] < 0.1 and own["top1_agree"] > 0.9, own     # its own basis keeps them
    # what the mapper can report without the raw features: the share of the robot's variance
    # its basis holds and the map's keeps (warned about below fleet.reproject_warn_kept)
    assert fleet.Reprojection(map_fs, robot_fs).kept_of_raw < 0.3
    assert fleet.Reprojection(robot_fs, robot_fs).kept_of_raw > 0.95


def test_label_encoder_reprojection_error_is_rounding_only():
    """With the label encoder (what the demo and tests run) every feature is a mix of the
    world's class embeddings, which any basis of >= the class count keeps: the error is
    float16 rounding only."""
    from encoders.text import make_text_encoder
    from synthetic_world.classes import CLASS_NAMES

    enc = make_text_encoder("minilm-l6")
    emb = enc.encode_labels(list(CLASS_NAMES)).float().numpy()            # (C, 384)
    g = np.random.default_rng(0)

    def mixes(n, classes):
        w = g.dirichlet(np.full(len(classes), 0.3), size=n)
        return (w @ emb[classes]).astype(np.float32)

    c = len(CLASS_NAMES)
    # robots that saw different parts of the world fit different bases
    sa = FeatureSpace("label", "1", 384, pca=PCA.fit(torch.as_tensor(mixes(3000, list(range(c)))), 32))
    sb = FeatureSpace("label", "1", 384, pca=PCA.fit(torch.as_tensor(mixes(3000, list(range(c))[::-1])), 20))
    assert sa.id != sb.id
    e = fleet.reprojection_score_error(sa, sb, mixes(2000, list(range(c))), torch.as_tensor(emb))
    assert e["max_abs"] < 5e-3 and e["top1_agree"] == 1.0, e


def test_compatibility_one_line_reasons():
    x = _features(500, seed=0)
    base = _space(x, 16)
    other_basis = _space(_features(500, seed=1), 16)
    assert compatibility(base, base) == ""
    assert compatibility(base, other_basis) == ""
    assert "fleet.reproject=false" in compatibility(base, other_basis, reproject=False)
    for fs, word in ((_space(x, 16, name="radio"), "encoder enc"), (_space(x, 16, version="2"), "version"),
                     (FeatureSpace("enc", "1", 384, text_model="siglip", pca=base.pca), "text model")):
        why = compatibility(fs, base)
        assert why.startswith("different encoder family") and word in why and "\n" not in why, why
    y = _features(500, d=200, seed=0)
    assert "dimension" in compatibility(base, _space(y, 16))


def test_head_difference_is_refused():
    from common.language_head import MLP2, MLP2Config

    cfg = MLP2Config(in_dim=32, hidden_dim=16, out_dim=8, num_inner=0)
    torch.manual_seed(0)
    h1 = {k: v.numpy().copy() for k, v in MLP2(cfg).state_dict().items()}
    torch.manual_seed(1)
    h2 = {k: v.numpy().copy() for k, v in MLP2(cfg).state_dict().items()}
    a = FeatureSpace("radio", "1", 32, head_config=cfg, head_state=h1)
    b = FeatureSpace("radio", "1", 32, head_config=cfg, head_state=h2)
    assert "language head" in compatibility(a, b)
    assert compatibility(a, FeatureSpace("radio", "1", 32, head_config=cfg, head_state=dict(h1))) == ""


def test_transforms_parse_apply_and_refuse():
    T = fleet.parse_transform({"xyz": [10, -5, 1], "rpy_deg": [0, 0, 90]})
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(fleet.parse_transform(T.reshape(-1).tolist()), T)
    np.testing.assert_allclose(fleet.parse_transform(T.tolist()), T)
    for bad in ([1, 2, 3], np.diag([2, 1, 1, 1]).tolist(), {"xyz": [0, 0, 0], "yaw": 3}, "x",
                [float("nan")] * 16):
        with pytest.raises(fleet.TransformError):
            fleet.parse_transform(bad)
    tr = fleet.RobotTransforms({"r2": T.reshape(-1).tolist()})
    pose = np.eye(4)
    pose[:3, 3] = [1, 0, 0]
    np.testing.assert_allclose(tr.apply("r2", pose)[:3, 3], [10, -4, 1], atol=1e-12)
    assert tr.apply("r1", pose) is pose
    tr.set("r1", {"xyz": [0, 0, 2]})
    assert tr.apply("r1", pose)[2, 3] == 2 and set(tr.as_dict()) == {"r1", "r2"}
    with pytest.raises(fleet.TransformError):
        fleet.RobotTransforms({"r3": [0] * 16})


def test_rate_meter_and_bounded():
    m = fleet.RateMeter(window=2.0, cap=50)
    for i in range(20):
        m.add(now=100 + i * 0.1)               # 10 Hz for 2 s
    assert m.rate(now=102.0) == pytest.approx(10.0, rel=0.1)
    assert m.rate(now=110.0) == 0.0
    for i in range(1000):
        m.add(now=200 + i * 0.001)             # 1 kHz burst, capped storage
    assert len(m._t) == 50 and m.rate(now=201.0) > 40


def test_drop_warner_rate_limited_with_rate(caplog):
    import logging

    w = fleet.DropWarner(period=10.0, logger=logging.getLogger("t.fleet"))
    with caplog.at_level(logging.WARNING, "t.fleet"):
        assert w.dropped("r1", 1, {"dropped_hz": 3.2, "received_hz": 4.0, "mapped_hz": 0.8}, 8, now=0.0)
        assert not any(w.dropped("r1", 1, {}, 8, now=0.1 * i) for i in range(1, 50))
        assert w.dropped("r1", 1, {"dropped_hz": 3.0}, 8, now=10.5)
        assert w.dropped("r2", 2, {}, 8, now=10.6)
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 3 and "3.2/s" in msgs[0] and "r1: 50 frame(s)" in msgs[1], msgs


def test_status_and_publish_cadence():
    st = SimpleNamespace(received=10, mapped=7, dropped=2, rejected=collections.Counter(bad=1),
                         queue=collections.deque([1]), feature_space="s1", reprojection=object())
    s = fleet.robot_status("r1", "accepted", "", st, {"mapped_hz": 2.0}, "s0", advised_hz=3.33333)
    assert s["rejected_total"] == 1 and s["reprojected"] and s["advised_hz"] == 3.333 and s["queue"] == 1
    with pytest.raises(ValueError):
        fleet.robot_status("r1", "happy", "", st, {}, "s0")
    p = fleet.StatusPublisher(period=1.0)
    assert p.due("r1", s, now=0.0)
    assert not p.due("r1", s, now=0.5)                       # nothing changed
    s2 = dict(s, mapped=8)
    assert not p.due("r1", s2, now=0.6)                      # changed counts: at most once a period
    assert p.due("r1", s2, now=1.7)
    assert p.due("r1", dict(s2, state="refused", reason="x"), now=1.8)   # state change: at once


def test_advised_rate_fair_share_and_probe():
    assert fleet.advised_rate(0.0, 2, {}, 8) is None
    # congested robot: fair share of what the mapper maps, a bit under it
    r = fleet.advised_rate(10.0, 4, {"dropped_hz": 1.0, "mapped_hz": 2.5, "queue": 8}, 8)
    assert r == pytest.approx(0.9 * 2.5)
    # a robot below its share may go up
    assert fleet.advised_rate(10.0, 4, {"mapped_hz": 1.0, "queue": 0}, 8) == pytest.approx(2.5)
    assert fleet.advised_rate(10.0, 1, {"mapped_hz": 10.0, "queue": 0}, 8) == pytest.approx(12.5)
    # frames waiting in its queue (latency) count as congestion, before anything is dropped
    assert fleet.advised_rate(10.0, 1, {"mapped_hz": 10.0, "queue": 3}, 8) == pytest.approx(9.0)


def _st(name, **kw):
    d = dict(name=name, present=False, gone_at=None, seen_at=0.0, last_frame_at=0.0, space_ok=False,
             feature_space="", queue=collections.deque())
    d.update(kw)
    return SimpleNamespace(**d)


def test_evictions():
    cfg = fleet.FleetSection(no_space_evict_s=60, gone_evict_s=300)
    robots = {"ok": _st("ok", present=True, space_ok=True, feature_space="s"),
              "nospace_old": _st("nospace_old", present=True, seen_at=0.0),
              "nospace_new": _st("nospace_new", present=True, seen_at=50.0),
              "gone_old": _st("gone_old", gone_at=10.0, space_ok=True, feature_space="s", last_frame_at=9.0),
              "gone_new": _st("gone_new", gone_at=90.0, space_ok=True, feature_space="s")}
    out = dict(fleet.evictions(robots, 100.0, cfg))
    assert set(out) == {"nospace_old"}
    out = dict(fleet.evictions(robots, 350.0, cfg))
    assert set(out) == {"nospace_old", "nospace_new", "gone_old"}
    assert set(dict(fleet.evictions(robots, 400.0, cfg))) == {"nospace_old", "nospace_new", "gone_old", "gone_new"}
    assert "feature space" in out["nospace_old"] and "gone" in out["gone_old"]


def test_expire_pending_ttl_and_global_cap():
    cfg = fleet.FleetSection(pending_ttl_s=10.0, pending_max_frames=5)
    a = _st("a", queue=collections.deque([(None, t) for t in (0.0, 5.0, 12.0, 13.0)]))
    b = _st("b", queue=collections.deque([(None, t) for t in (11.0, 14.0, 15.0, 16.0)]))
    ok = _st("ok", space_ok=True, queue=collections.deque([(None, 0.0)] * 3))
    out = dict(fleet.expire_pending([a, b, ok], 20.0, cfg))
    # ttl: a's 0.0 and 5.0 (and nothing of b: 11 is 9 s old); cap 5 of the remaining 6: b's 11.0
    assert out == {"a": 2, "b": 1}
    assert [t for _, t in a.queue] == [12.0, 13.0] and [t for _, t in b.queue] == [14.0, 15.0, 16.0]
    assert len(ok.queue) == 3                                  # robots with a space are not touched
    assert math.isclose(sum(len(s.queue) for s in (a, b)), 5)
    # one robot may always fill its own queue (queues.per_robot above the global cap)
    c = _st("c", queue=collections.deque([(None, 19.0)] * 9))
    assert dict(fleet.expire_pending([c], 20.0, cfg, per_robot=8)) == {"c": 1} and len(c.queue) == 8


def test_synthetic_robots_in_one_town_take_their_own_laps():
    """source.seed is the world (and by default the lap); trajectory_seed gives a second robot
    another lap in the same town (a different source.seed would map another town)."""
    from edge.sources.config import SourceConfig
    from edge.sources.synthetic import SyntheticSource

    kw = dict(kind="synthetic", resolution="24x32", n_frames=3)
    a = SyntheticSource(SourceConfig(**kw))
    b = SyntheticSource(SourceConfig(**kw, trajectory_seed=7))
    c = SyntheticSource(SourceConfig(**kw, seed=1))
    assert not np.allclose(a.poses, b.poses)

    def lamps(src):
        return [i.center.tolist() for i in src.world.instances_of(src.world.class_id("street lamp"))]
    assert lamps(a) == lamps(b) and lamps(a) != lamps(c)


def test_edge_status_watcher_logs_changes_and_auto_rate(caplog):
    """The edge logs a line per change of the mapper's status (WARNING when refused) and
    publish.rate_hz=auto follows the advised rate, smoothed, within its bounds."""
    import logging

    from common.robot_messages import encode_robot_status
    from edge.mapper_status import AutoRate, StatusWatcher

    st = SimpleNamespace(received=1, mapped=0, dropped=0, rejected={}, queue=(), feature_space="s1")
    auto = AutoRate(start_hz=10.0, min_hz=0.5, max_hz=50.0)
    w = StatusWatcher("r1", auto, logger=logging.getLogger("t.edge"))
    with caplog.at_level(logging.INFO, "t.edge"):
        for _ in range(3):
            w.on_payload(encode_robot_status(fleet.robot_status("r1", "pending", "waiting", st, {}, "s0")))
        assert auto.current() == 10.0                              # no advice while pending
        for _ in range(6):
            w.on_payload(encode_robot_status(fleet.robot_status("r1", "accepted", "", st, {}, "s0", advised_hz=2.0)))
        refused = fleet.robot_status("r1", "refused", "different encoder family: x", st, {}, "s0")
        w.on_payload(encode_robot_status(refused))
        w.on_payload(encode_robot_status(fleet.robot_status("other", "refused", "not me", st, {}, "s0")))
        assert w.on_payload(b"garbage") is None and w.bad == 1
    states = [r.getMessage() for r in caplog.records if "robot r1" in r.getMessage() or "refused" in r.getMessage()]
    assert len([m for m in states if "pending" in m]) == 1 and len([m for m in states if "accepted" in m]) == 1
    refused = [r for r in caplog.records if "refused this robot's frames" in r.getMessage()]
    assert len(refused) == 1 and refused[0].levelno == logging.WARNING and "not me" not in caplog.text
    assert 2.0 < auto.current() < 2.5                              # 10 -> 2 Hz, half way per update
    assert AutoRate(min_hz=1.0).advise(0.01) == pytest.approx(5.5)    # clamped to min_hz before smoothing


def test_frame_order_does_not_change_the_map():
    """Robots interleave in any order at the mapper: the same frames in another order give the
    same voxels and features (so a fleet run and a single-basis run differ only by the frames
    each mapped; the runtime tests make the edges lossless for that reason)."""
    import random

    import torch

    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    from synthetic_world import World

    w = World.generate(0)
    hw = (48, 64)
    K = w.camera(hw, 90.0)
    n_cls = len(w.classes)
    frames = []
    for robot in range(3):
        for p in w.trajectory("ground", 6, seed=100 + robot):
            r = w.render(p, K, hw)
            oh = torch.nn.functional.one_hot(torch.as_tensor(r.labels.astype(np.int64)), n_cls)
            frames.append((p, r.depth.astype(np.float32), r.rgb, oh.permute(2, 0, 1).float()))
    cfg = map_config("throughput", {"vox_size": 0.5, "depth_limit": 20.0})

    def run(order):
        m = RayFrontsMap(cfg, n_cls, "labels", occupancy_backend="torch")
        for p, d, rgb, f in order:
            m.integrate(p, K, d, rgb, f)
        m.flush()
        feat = m.voxels().features.float()
        feat = feat / feat.norm(dim=1, keepdim=True).clamp_min(1e-9)
        return dict(zip(map(tuple, m.voxel_ijk().tolist()), feat.numpy(), strict=True))

    a = run(frames)
    shuffled = frames[:]
    random.Random(1).shuffle(shuffled)
    b = run(shuffled)
    assert set(a) == set(b) and len(a) > 1000
    assert max(float(np.abs(a[k] - b[k]).max()) for k in a) < 1e-3
