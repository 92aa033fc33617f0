"""Pure metric functions of the paper's two benchmarks (numpy / scipy, no I/O).

Label conventions used throughout:

* **search volume** (online benchmark): per-voxel ground truth of the *unobserved* volume
  is ``IGNORE`` (−1, excluded from every count), ``EMPTY`` (0, a negative for every class)
  or a class id ``c >= 1``.
* **semantic segmentation**: GT class 0 = unlabelled (not evaluated); prediction 0 = "no
  prediction" (counts as a false negative of the GT class).

All ratios are fractions in [0, 1]; an undefined ratio (0/0) is ``NaN``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import numpy.typing as npt

IGNORE = -1
EMPTY = 0


# ----------------------------------------------------------------------------- search volume
@dataclass
class Confusion:
    """Counts of "voxel in the class's search volume" vs "voxel is the class"."""

    tp: int
    fp: int
    fn: int
    tn: int

    @property
    def volume(self) -> int:
        """Non-ignored unobserved voxels (``vol_unobserved``)."""
        return self.tp + self.fp + self.fn + self.tn


def srchvol_confusion(in_volume: np.ndarray | None, gt: np.ndarray, c: int) -> Confusion:
    """TP/FP/FN/TN of class ``c`` over the unobserved voxels.

    ``in_volume`` (V,) bool: the voxel lies in class ``c``'s search volume; ``None`` means
    the class predicted nothing (every voxel outside: FN = its voxels, TN = the rest).
    ``gt`` (V,) int: ``IGNORE`` (excluded), ``EMPTY`` or a class id (other classes and empty
    voxels are negatives)."""
    gt = np.asarray(gt)
    keep = gt != IGNORE
    pos = (gt == c) & keep
    neg = keep & ~pos
    if in_volume is None:
        p = int(pos.sum())
        return Confusion(0, 0, p, int(neg.sum()))
    v = np.asarray(in_volume, dtype=bool)
    if v.shape != gt.shape:
        raise ValueError(f"search-volume mask {v.shape} and GT {gt.shape} differ in shape")
    return Confusion(int((v & pos).sum()), int((v & neg).sum()), int((~v & pos).sum()), int((~v & neg).sum()))


def scv(cf: Confusion) -> float:
    """Search cut volume ``SCV = 1 − FP / vol_unobserved`` (NaN when the volume is empty)."""
    return 1.0 - cf.fp / cf.volume if cf.volume else float("nan")


def recall(cf: Confusion) -> float:
    """``TP / (TP + FN)`` in the unobserved volume (NaN when the class has no voxel there)."""
    d = cf.tp + cf.fn
    return cf.tp / d if d else float("nan")


def scvr(cf: Confusion) -> float:
    """``SCVR = SCV · Recall`` (0 for both "cut nothing" and "cut everything")."""
    return scv(cf) * recall(cf)


def normalized_count_mask(counts: np.ndarray, thresh: float = 0.05) -> np.ndarray:
    """Search volume from per-voxel shape counts: ``counts / max(counts) > thresh``
    (paper: 0.05). All-zero counts give an empty mask."""
    c = np.asarray(counts, dtype=np.float64)
    mx = float(c.max()) if c.size else 0.0
    if mx <= 0:
        return np.zeros(c.shape, dtype=bool)
    return c / mx > thresh


def srchvol_metrics(masks: Mapping[int, np.ndarray | None], gt: np.ndarray, classes: Sequence[int],
                    default_prediction: bool = True) -> dict[int, dict[str, float]]:
    """Per class ``c`` in ``classes``: tp, fp, fn, tn, vol, scv, recall, scvr.

    ``masks[c]``: the class's search volume over the unobserved voxels (absent / ``None``
    = the class has no evidence). With ``default_prediction`` a class without evidence
    predicts the **whole** unobserved volume (SCV 0 unless the volume holds only class
    ``c``, Recall 1); otherwise it predicts nothing (Recall 0)."""
    gt = np.asarray(gt)
    out = {}
    for c in classes:
        m = masks.get(int(c))
        if m is None and default_prediction:
            m = np.ones(gt.shape, dtype=bool)
        cf = srchvol_confusion(m, gt, int(c))
        out[int(c)] = dict(tp=cf.tp, fp=cf.fp, fn=cf.fn, tn=cf.tn, vol=cf.volume,
                           scv=scv(cf), recall=recall(cf), scvr=scvr(cf))
    return out


# ----------------------------------------------------------------------------- AUC over time
def auc_stopping(steps: npt.ArrayLike, values: npt.ArrayLike, observed_frac: npt.ArrayLike,
                 stop: float = 0.5) -> float:
    """Time-average of ``values`` over the steps before the class is "mapped".

    Kept steps: those **before** the first step whose ``observed_frac`` (fraction of the
    class's occupied GT voxels inside the observed region) exceeds ``stop`` (all steps if
    it never does). ``AUC = Σ v·Δstep / Σ Δstep`` over kept steps with finite ``v``, where
    ``Δstep = diff(steps, prepend=0)`` (the first point is weighted by its step index).
    NaN when no kept step has a finite value (or all kept Δstep are 0)."""
    s = np.asarray(steps, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    f = np.asarray(observed_frac, dtype=np.float64)
    if not (s.shape == v.shape == f.shape) or s.ndim != 1:
        raise ValueError(f"steps {s.shape}, values {v.shape} and observed_frac {f.shape} must be equal 1-D shapes")
    d = np.diff(s, prepend=0.0)
    over = np.nonzero(f > stop)[0]
    n = int(over[0]) if over.size else len(s)
    v, d = v[:n], d[:n]
    ok = np.isfinite(v)
    den = d[ok].sum()
    return float((v[ok] * d[ok]).sum() / den) if den > 0 else float("nan")


def auc_table(rows: list[dict], metric: str, stop: float = 0.5) -> float:
    """Scene-level AUC of ``metric``: per class (rows with keys ``class``, ``step``,
    ``metric``, ``observed_frac`` and ``gt_count`` = the class's occupied GT voxels in the
    scene) the :func:`auc_stopping` value, then the nanmean over classes with
    ``gt_count > 0``. NaN if no class has a defined AUC."""
    by: dict[int, list[dict]] = {}
    for r in rows:
        by.setdefault(int(r["class"]), []).append(r)
    vals = []
    for _, rs in sorted(by.items()):
        rs = sorted(rs, key=lambda r: r["step"])
        if rs[-1].get("gt_count", 1) <= 0:
            continue
        vals.append(auc_stopping([r["step"] for r in rs], [r[metric] for r in rs],
                                 [r["observed_frac"] for r in rs], stop))
    arr = np.asarray(vals, dtype=np.float64)
    return float(np.nanmean(arr)) if np.isfinite(arr).any() else float("nan")


# ----------------------------------------------------------------------------- segmentation
def confusion_per_class(gt: np.ndarray, pred: np.ndarray, classes: Sequence[int]) -> dict[int, tuple[int, int, int]]:
    """``{c: (TP, FP, FN)}`` over the voxels whose GT is one of ``classes`` (GT 0 =
    unlabelled and GT classes not listed — e.g. ignored background — are not evaluated).
    A prediction 0 ("none") is a false negative of the GT class and no false positive."""
    gt = np.asarray(gt)
    pred = np.asarray(pred)
    if gt.shape != pred.shape:
        raise ValueError(f"GT {gt.shape} and prediction {pred.shape} differ in shape")
    lab = np.isin(gt, [int(c) for c in classes]) & (gt != 0)
    g, p = gt[lab], pred[lab]
    out = {}
    for c in classes:
        c = int(c)
        out[c] = (int(((g == c) & (p == c)).sum()), int(((g != c) & (p == c)).sum()), int(((g == c) & (p != c)).sum()))
    return out


def iou(tp: int, fp: int, fn: int) -> float:
    """``TP / (TP + FP + FN)``; NaN when the class has no GT voxel (TP + FN = 0)."""
    return tp / (tp + fp + fn) if tp + fn > 0 else float("nan")


def semseg_scores(gt: np.ndarray, pred: np.ndarray, classes: Sequence[int]) -> dict:
    """mIoU (nanmean of per-class IoU), f-mIoU (IoU weighted by class frequency TP+FN),
    Acc (fraction of GT-labelled voxels — GT class in ``classes`` — predicted correctly) and
    ``per_class`` {c: {iou, tp, fp, fn}} for the GT classes ``classes``."""
    classes = [int(c) for c in classes]
    conf = confusion_per_class(gt, pred, classes)
    ious = np.array([iou(*conf[c]) for c in classes], dtype=np.float64)
    freq = np.array([conf[c][0] + conf[c][2] for c in classes], dtype=np.float64)
    ok = np.isfinite(ious)
    miou = float(np.nanmean(ious)) if ok.any() else float("nan")
    fmiou = float((ious[ok] * freq[ok]).sum() / freq[ok].sum()) if freq[ok].sum() > 0 else float("nan")
    gt = np.asarray(gt)
    sel = np.isin(gt, classes) & (gt != 0)
    acc = float((np.asarray(pred)[sel] == gt[sel]).mean()) if sel.any() else float("nan")
    return dict(miou=miou, fmiou=fmiou, acc=acc,
                per_class={c: dict(iou=float(ious[i]), tp=conf[c][0], fp=conf[c][1], fn=conf[c][2])
                           for i, c in enumerate(classes)})


def observed_iou(gt_labels: np.ndarray, pred_labels: np.ndarray, classes: Sequence[int]) -> dict[int, float]:
    """Observed-region IoU per class over a shared voxel list (aligned GT and predicted
    label per voxel, 0 = empty / none): TP/(TP+FP+FN) with FP counted on every voxel
    (empty GT included); NaN when the class is neither in GT nor predicted."""
    g = np.asarray(gt_labels)
    p = np.asarray(pred_labels)
    out = {}
    for c in classes:
        tp = int(((g == c) & (p == c)).sum())
        fp = int(((g != c) & (p == c)).sum())
        fn = int(((g == c) & (p != c)).sum())
        out[int(c)] = tp / (tp + fp + fn) if tp + fp + fn else float("nan")
    return out


# ----------------------------------------------------------------------------- alignment
def mode_smallest(labels: np.ndarray) -> np.ndarray:
    """Row-wise mode of an (N, k) int array; ties → the smallest label."""
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise ValueError(f"labels must be (N, k), got {lab.shape}")
    if lab.shape[1] == 0:
        raise ValueError("need k >= 1 labels per row")
    s = np.sort(lab, axis=1)
    n, k = s.shape
    # run lengths in each sorted row
    best = s[:, 0].copy()
    best_n = np.zeros(n, dtype=np.int64)
    run = np.zeros(n, dtype=np.int64)
    for j in range(k):
        run = np.where(s[:, j] == s[:, j - 1], run + 1, 1) if j > 0 else np.ones(n, dtype=np.int64)
        better = run > best_n  # strictly greater: an earlier (smaller) label keeps a tie
        best = np.where(better, s[:, j], best)
        best_n = np.where(better, run, best_n)
    return best


def knn_align(gt_xyz: np.ndarray, pred_xyz: np.ndarray, pred_labels: np.ndarray, k: int = 5,
              vox: float | None = None) -> np.ndarray:
    """Predicted label for each GT voxel.

    ``k > 0``: majority vote of the ``k`` nearest predicted voxels (scipy ``cKDTree``;
    ties → smallest label; label 0 = "none" votes too). ``k = 0``: exact grid alignment —
    the prediction of the voxel with the same index ``floor(xyz / vox)``, 0 where there is
    none (needs ``vox``). No predicted voxels → all 0."""
    g = np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(pred_xyz, dtype=np.float64).reshape(-1, 3)
    lab = np.asarray(pred_labels).reshape(-1).astype(np.int64)
    if len(p) != len(lab):
        raise ValueError(f"{len(p)} predicted voxels but {len(lab)} labels")
    if len(g) == 0 or len(p) == 0:
        return np.zeros(len(g), dtype=np.int64)
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    if k == 0:
        if vox is None or vox <= 0:
            raise ValueError("exact grid alignment (k = 0) needs the voxel size vox > 0")
        gk = np.floor(g / vox).astype(np.int64)
        pk = np.floor(p / vox).astype(np.int64)
        keys_p = _pack(pk)
        order = np.argsort(keys_p, kind="stable")
        ks = keys_p[order]
        q = _pack(gk)
        pos = np.searchsorted(ks, q).clip(max=len(ks) - 1)
        hit = ks[pos] == q
        return np.where(hit, lab[order][pos], 0)
    from scipy.spatial import cKDTree

    kk = min(k, len(p))
    _, idx = cKDTree(p).query(g, k=kk)
    idx = np.asarray(idx).reshape(len(g), kk)
    return mode_smallest(lab[idx])


def _pack(ijk: np.ndarray) -> np.ndarray:
    off = 1 << 20
    s = ijk.astype(np.int64) + off
    if s.size and (s.min() < 0 or s.max() >= (1 << 21)):
        raise ValueError("voxel index outside the packable range ±2^20")
    return (s[:, 0] << 42) | (s[:, 1] << 21) | s[:, 2]


# ----------------------------------------------------------------------------- reference cones
def reference_cone_radius(z: npt.ArrayLike, vox: float, subsampling: float, half_angle_deg: float) -> np.ndarray:
    """Circumradius at depth ``z`` (m along the ray) of the reference's evaluation "cone"
    (docs/method.md#evaluation): a six-sided open pyramid through a hexagon of radius ``vox·s`` at
    ``z = vox`` and one of radius ``5·vox·tan(α)`` at ``z = 5·vox``; linear in between and
    beyond (``r₀ + (z − vox)(5 tan α − s)/4``); the pyramid starts at ``z = vox``."""
    z = np.asarray(z, dtype=np.float64)
    r0 = vox * subsampling
    r5 = 5 * vox * np.tan(np.radians(half_angle_deg))
    return r0 + (z - vox) * (r5 - r0) / (4 * vox)
