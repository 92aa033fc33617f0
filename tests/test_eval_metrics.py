"""Metric code of the benchmarks against hand-computed cases and brute force."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from apps.evaluation import metrics, shapes


# ----------------------------------------------------------------------------- search volume
def test_srchvol_confusion_hand_case():
    gt = np.array([-1, 0, 0, 1, 1, 2, 2, 2])
    mask = np.array([1, 1, 0, 1, 0, 1, 0, 0], bool)
    cf = metrics.srchvol_confusion(mask, gt, 1)
    assert (cf.tp, cf.fp, cf.fn, cf.tn, cf.volume) == (1, 2, 1, 3, 7)   # the ignored voxel is excluded
    assert metrics.scv(cf) == pytest.approx(5 / 7)
    assert metrics.recall(cf) == pytest.approx(1 / 2)
    assert metrics.scvr(cf) == pytest.approx(5 / 14)


def test_srchvol_default_prediction_and_none():
    gt = np.array([0, 0, 0, 1, 2, 2, -1])
    out = metrics.srchvol_metrics({}, gt, [1, 2], default_prediction=True)
    # whole unobserved volume predicted: FP = every non-c voxel -> SCV = n_c / vol, Recall 1
    assert out[1]["scv"] == pytest.approx(1 / 6) and out[1]["recall"] == 1.0
    assert out[2]["scvr"] == pytest.approx(2 / 6)
    out = metrics.srchvol_metrics({}, gt, [1], default_prediction=False)
    assert out[1]["scv"] == 1.0 and out[1]["recall"] == 0.0 and out[1]["scvr"] == 0.0
    # a perfect search volume
    out = metrics.srchvol_metrics({1: gt == 1}, gt, [1])
    assert out[1]["scvr"] == 1.0
    # cutting everything -> recall 0 -> SCVR 0
    out = metrics.srchvol_metrics({1: np.zeros(7, bool)}, gt, [1])
    assert out[1]["scv"] == 1.0 and out[1]["scvr"] == 0.0


def test_normalized_count_mask_threshold_is_strict():
    c = np.array([0, 1, 5, 20, 100])
    np.testing.assert_array_equal(metrics.normalized_count_mask(c, 0.05), [False, False, False, True, True])
    assert not metrics.normalized_count_mask(np.zeros(3)).any()


# ----------------------------------------------------------------------------- AUC
def test_auc_stopping_rule():
    steps = [10, 20, 30, 40]
    vals = [0.2, 0.4, np.nan, 0.8]
    # step 40 is the first with > 50 % observed: kept 10, 20, 30; NaN ignored; Δ = 10 each
    assert metrics.auc_stopping(steps, vals, [0.1, 0.3, 0.4, 0.6]) == pytest.approx((0.2 * 10 + 0.4 * 10) / 20)
    # never stops; exactly 0.5 does not stop
    assert metrics.auc_stopping(steps, vals, [0.1, 0.5, 0.5, 0.5]) == pytest.approx((2 + 4 + 8) / 30)
    # Δ uses prepend=0: the first point weighs its step index
    assert metrics.auc_stopping([5, 10], [1.0, 0.0], [0, 0]) == pytest.approx(5 / 10)
    assert math.isnan(metrics.auc_stopping(steps, vals, [0.9, 0, 0, 0]))


def test_auc_table_classes_then_mean():
    rows = []
    for s, a, b in [(10, 0.2, 0.5), (20, 0.4, 0.7)]:
        rows.append({"class": 1, "step": s, "scvr": a, "observed_frac": 0.0, "gt_count": 5})
        rows.append({"class": 2, "step": s, "scvr": b, "observed_frac": 0.0 if s == 10 else 0.9, "gt_count": 3})
        rows.append({"class": 3, "step": s, "scvr": 1.0, "observed_frac": 0.0, "gt_count": 0})  # not in GT
    # class 1: (0.2+0.4)/2 = 0.3; class 2 stops at step 20: 0.5; mean 0.4
    assert metrics.auc_table(rows, "scvr") == pytest.approx(0.4)


# ----------------------------------------------------------------------------- segmentation
def test_semseg_scores_hand_case():
    gt = np.array([1, 1, 1, 2, 2, 3, 0, 0, 3])
    pred = np.array([1, 1, 2, 2, 0, 3, 1, 3, 1])
    s = metrics.semseg_scores(gt, pred, [1, 2, 3])
    # c1: TP2 FP1 (the GT-3 voxel) FN1 -> 1/2; c2: TP1 FP1 FN1 -> 1/3; c3: TP1 FP0 FN1 -> 1/2
    assert s["per_class"][1]["iou"] == pytest.approx(1 / 2)
    assert s["per_class"][2]["iou"] == pytest.approx(1 / 3)
    assert s["per_class"][3]["iou"] == pytest.approx(1 / 2)
    assert s["miou"] == pytest.approx((1 / 2 + 1 / 3 + 1 / 2) / 3)
    assert s["fmiou"] == pytest.approx((3 * 1 / 2 + 2 * 1 / 3 + 2 * 1 / 2) / 7)
    assert s["acc"] == pytest.approx(4 / 7)
    # class 3 as ignored background: its voxels are not evaluated (no FP for class 1 there)
    s = metrics.semseg_scores(gt, pred, [1, 2])
    assert s["per_class"][1]["iou"] == pytest.approx(2 / 3)
    assert s["miou"] == pytest.approx((2 / 3 + 1 / 3) / 2)
    assert s["fmiou"] == pytest.approx((3 * 2 / 3 + 2 * 1 / 3) / 5)
    assert s["acc"] == pytest.approx(3 / 5)


def test_semseg_background_split():
    from apps.evaluation.semseg import scores_with_without_bg
    names = ["sky", "car", "road", "tree"]
    gt = np.array([1, 1, 2, 2, 3])
    pred = np.array([1, 2, 2, 2, 3])
    s = scores_with_without_bg(gt, pred, names, ["road"])
    assert s["miou"] == pytest.approx((1 / 2 + 1) / 2)        # car, tree; road voxels ignored
    assert s["miou_bg"] == pytest.approx((1 / 2 + 2 / 3 + 1) / 3)
    assert s["acc"] == pytest.approx(2 / 3) and s["acc_bg"] == pytest.approx(4 / 5)
    assert s["per_class"]["road"]["background"] and not s["per_class"]["car"]["background"]


def test_observed_iou_nan_when_absent():
    out = metrics.observed_iou(np.array([0, 1, 1, 2]), np.array([1, 1, 0, 2]), [1, 2, 3])
    assert out[1] == pytest.approx(1 / 3) and out[2] == 1.0 and math.isnan(out[3])


# ----------------------------------------------------------------------------- alignment
def test_mode_smallest_ties():
    modes = metrics.mode_smallest(np.array([[2, 1, 2, 1], [0, 5, 5, 5], [3, 0, 3, 0], [4, 4, 9, 9]]))
    np.testing.assert_array_equal(modes, [1, 5, 0, 4])


def test_knn_align_votes_and_ties():
    p = np.stack([np.arange(6.0), np.zeros(6), np.zeros(6)], 1)
    lab = np.array([1, 1, 2, 2, 3, 3])
    q = np.array([[0.1, 0, 0], [1.6, 0, 0], [4.6, 0, 0]])
    np.testing.assert_array_equal(metrics.knn_align(q, p, lab, k=3), [1, 2, 3])
    # k = 4 at x = 1.6: neighbours 2, 1, 3, 0 -> labels 1,2,1,2 -> tie -> 1
    assert metrics.knn_align(q[1:2], p, lab, k=4)[0] == 1
    # k larger than the predicted set
    assert metrics.knn_align(q[:1], p[:2], lab[:2], k=5)[0] == 1
    assert metrics.knn_align(q, np.empty((0, 3)), np.empty(0), k=5).tolist() == [0, 0, 0]


def test_exact_grid_alignment():
    p = np.array([[0.25, 0.25, 0.25], [1.2, 0.1, 0.1]])
    g = np.array([[0.4, 0.4, 0.4], [1.9, 0.9, 0.9], [2.5, 0, 0], [-0.1, 0.2, 0.2]])
    np.testing.assert_array_equal(metrics.knn_align(g, p, [7, 8], k=0, vox=0.5), [7, 0, 0, 0])
    np.testing.assert_array_equal(metrics.knn_align(g, p, [7, 8], k=0, vox=1.0), [7, 8, 0, 0])
    with pytest.raises(ValueError):
        metrics.knn_align(g, p, [7, 8], k=0)


# ----------------------------------------------------------------------------- shapes
def test_reference_cone_radius_hand():
    r = metrics.reference_cone_radius([1, 5, 9, 100], 1.0, 4, 45.0)
    np.testing.assert_allclose(r, [4, 5, 6, 28.75])      # 4 m + 0.25 m per metre
    np.testing.assert_allclose(metrics.reference_cone_radius([1, 5, 50], 1.0, 5, 45.0), [5, 5, 5])   # cylinder
    r = metrics.reference_cone_radius([2, 10], 0.5, 4, 30.0)   # r0 = 2 at 0.5 m, 5*0.5*tan30 = 1.443 at 2.5 m
    np.testing.assert_allclose(r, [2 + 1.5 * (2.5 * math.tan(math.radians(30)) - 2) / 2,
                                   2 + 9.5 * (2.5 * math.tan(math.radians(30)) - 2) / 2])


@pytest.mark.parametrize("s,alpha", [(4, 45.0), (5, 45.0), (4, 30.0), (2, 60.0)])
def test_reference_pyramid_vs_half_spaces(s, alpha):
    rng = np.random.default_rng(s)
    pts = rng.uniform(-25, 25, (20000, 3))
    o = np.array([1.0, 2.0, 3.0])
    for d in ([0.3, -0.5, 0.8], [0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]):
        d = np.asarray(d) / np.linalg.norm(d)
        bf = shapes.brute_force_reference_inside(pts, o, d, 1.0, s, alpha)
        cnt = shapes.reference_cone_counts(pts, o[None], d[None], 1.0, s, alpha).numpy()
        np.testing.assert_array_equal(cnt > 0, bf)
        assert bf.sum() > 0


def test_reference_pyramid_radius_on_axis():
    # on the axis and just inside / outside the inscribed circle at several depths
    d = np.array([0.0, 1.0, 0.0])
    R = shapes.rotation_z_to(torch.tensor(d[None]))[0].numpy()
    for z in (1.5, 3.0, 10.0, 40.0):
        r = metrics.reference_cone_radius(z, 1.0, 4, 45.0)
        apo = r * math.cos(math.pi / 6)
        pts = np.array([R @ [0, 0, z], R @ [0, 0.99 * apo, z], R @ [0, 1.01 * r, z], R @ [0, 0, 0.9]])
        c = shapes.reference_cone_counts(pts, np.zeros((1, 3)), d[None], 1.0, 4, 45.0).numpy()
        np.testing.assert_array_equal(c, [1, 1, 0, 0])


def test_true_cones_vs_brute_force():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (5000, 3))
    o = rng.uniform(-5, 5, (7, 3))
    d = rng.normal(size=(7, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cnt = shapes.cone_counts(pts, o, d, 30.0).numpy()
    v = pts[:, None, :] - o[None]
    cosang = (v * d[None]).sum(2) / np.linalg.norm(v, axis=2)
    np.testing.assert_array_equal(cnt, (cosang >= math.cos(math.radians(30))).sum(1))


def test_ball_counts_vs_brute_force():
    rng = np.random.default_rng(2)
    pts = rng.uniform(-10, 10, (4000, 3))
    c = rng.uniform(-5, 5, (5, 3))
    r = rng.uniform(1, 4, 5)
    cnt = shapes.ball_counts(pts, c, r).numpy()
    np.testing.assert_array_equal(cnt, (np.linalg.norm(pts[:, None] - c[None], axis=2) <= r).sum(1))
