"""The synthetic world: labelled solid primitives, their exact geometry and rendering.

World frame z up (x east, y north), metres; ground plane at z = 0. Poses are
camera-to-world with RDF camera axes (``common.conventions``). Overlapping solids of
different classes resolve to the *later* part in the list (``labels_at``); the generator
avoids such overlaps except where a later, smaller object sits on an earlier one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from common.conventions import voxel_center
from common.geometry import intrinsics_from_fov

from . import primitives
from .classes import CLASS_COLORS, CLASS_NAMES
from .parts import Layout, Part
from .render import Render, render_scene

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


@dataclass(frozen=True, eq=False)
class Instance:
    """An object of the world: ``id`` (as in ``Render.instance``), ``class_id``, ``name``,
    ``center`` (3,) of its AABB, ``aabb_min``/``aabb_max`` (3,) in metres."""

    id: int
    class_id: int
    name: str
    center: np.ndarray
    aabb_min: np.ndarray
    aabb_max: np.ndarray


class World:
    """A procedural outdoor world made of labelled primitives.

    Build with :meth:`generate` (deterministic by seed) or :meth:`from_primitives`."""

    def __init__(self, parts: Sequence[Part], classes: Sequence[str] | None = None,
                 class_colors: Sequence[tuple[int, ...]] | None = None, layout: Layout | None = None,
                 seed: int | None = None):
        self.classes: list[str] = list(classes if classes is not None else CLASS_NAMES)
        if not self.classes or self.classes[0] != "sky":
            raise ValueError(f"class 0 must be 'sky' (nothing there), got {self.classes[:1]}")
        if len(set(self.classes)) != len(self.classes):
            raise ValueError(f"duplicate class names in {self.classes}")
        if class_colors is None:
            default: dict[str, tuple[int, ...]] = dict(zip(CLASS_NAMES, CLASS_COLORS, strict=True))
            rng = np.random.default_rng(12345)
            class_colors = [default.get(n, tuple(int(x) for x in rng.integers(40, 230, 3))) for n in self.classes]
        self.class_colors: list[tuple[int, ...]] = [tuple(int(v) for v in c) for c in class_colors]
        if len(self.class_colors) != len(self.classes):
            raise ValueError("class_colors must have one colour per class")
        if not parts:
            raise ValueError("a world needs at least one part")
        self.parts: list[Part] = list(parts)
        self.layout = layout or Layout()
        self.seed = seed
        self._build()

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_primitives(cls, parts: Sequence[Part], classes: Sequence[str] | None = None,
                        class_colors: Sequence[tuple[int, ...]] | None = None) -> "World":
        """A world from an explicit list of :class:`Part` (tests, custom scenes)."""
        return cls(parts, classes, class_colors)

    @classmethod
    def generate(cls, seed: int = 0, preset: str = "default") -> "World":
        """The procedural town (see :mod:`synthetic_world.generate`), deterministic by ``seed``."""
        from .generate import generate_parts

        parts, layout = generate_parts(int(seed), preset)
        return cls(parts, CLASS_NAMES, CLASS_COLORS, layout=layout, seed=int(seed))

    def _build(self) -> None:
        names: dict[str, int] = {}
        inst_ids, cls_ids, colors, kinds = [], [], [], []
        for p in self.parts:
            if not isinstance(p, Part):
                raise TypeError(f"expected Part, got {type(p).__name__}")
            cid = self.class_id(p.class_name)
            if cid == 0:
                raise ValueError(f"part {p.instance!r}: class 0 ('sky') means empty space; give it a solid class")
            if p.instance not in names:
                names[p.instance] = len(names)
            iid = names[p.instance]
            inst_ids.append(iid)
            cls_ids.append(cid)
            colors.append(p.color if p.color is not None else self.class_colors[cid])
            kinds.append(primitives.kind_of(p.shape))
        shapes = [p.shape for p in self.parts]
        self._kind = np.asarray(kinds, dtype=np.int64)
        self._kidx = np.zeros(len(shapes), dtype=np.int64)
        for k in (primitives.KIND_BOX, primitives.KIND_FRUSTUM, primitives.KIND_SPHERE):
            sel = self._kind == k
            self._kidx[sel] = np.arange(int(sel.sum()))
        self._params = primitives.pack(shapes)
        self._cls = np.asarray(cls_ids, dtype=np.int32)
        self._inst = np.asarray(inst_ids, dtype=np.int32)
        self._color = np.asarray(colors, dtype=np.float64)
        boxes = [s.aabb() for s in shapes]
        self._amin = np.array([b[0] for b in boxes])
        self._amax = np.array([b[1] for b in boxes])
        lo, hi = self._amin[:, None, :], self._amax[:, None, :]
        sel = np.array([[(i >> a) & 1 for a in range(3)] for i in range(8)], dtype=bool)  # (8, 3)
        self._corners = np.where(sel[None], hi, lo)  # (P, 8, 3)
        # Instances.
        self.instances: list[Instance] = []
        for name, iid in names.items():
            m = self._inst == iid
            cids = np.unique(self._cls[m])
            if len(cids) != 1:
                raise ValueError(f"instance {name!r} mixes classes {[self.classes[c] for c in cids]}")
            amin, amax = self._amin[m].min(0), self._amax[m].max(0)
            self.instances.append(Instance(iid, int(cids[0]), name, (amin + amax) / 2, amin, amax))
        # x-sorted primitive order is not needed; points are sorted in labels_at.

    # ------------------------------------------------------------------ metadata

    def class_id(self, name: str) -> int:
        """Class id of ``name``; ``ValueError`` naming the valid classes if unknown."""
        try:
            return self.classes.index(name)
        except ValueError:
            raise ValueError(f"unknown class {name!r}; valid classes: {', '.join(self.classes)}") from None

    @property
    def n_primitives(self) -> int:
        return len(self.parts)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min_xyz, max_xyz) of every primitive, ground and far landmarks included."""
        return self._amin.min(0), self._amax.max(0)

    def instances_of(self, class_id: int) -> list[Instance]:
        """The instances of class ``class_id`` (index into :attr:`classes`)."""
        return [i for i in self.instances if i.class_id == class_id]

    # ------------------------------------------------------------------ rendering

    def camera(self, hw: tuple[int, int] = (480, 640), hfov_deg: float = 90.0) -> np.ndarray:
        """Intrinsics K (3×3) for an image of ``hw`` = (H, W) with horizontal FoV ``hfov_deg``."""
        return intrinsics_from_fov(hfov_deg, int(hw[0]), int(hw[1]))

    def render(self, pose: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> Render:
        """RGB, planar depth (+inf = sky), labels (0 = sky) and instance ids (−1 = none) seen
        from camera-to-world ``pose`` (RDF) with intrinsics ``K`` at ``hw`` = (H, W)."""
        return render_scene(self, pose, K, hw)

    def trajectory(self, preset: str = "ground", n_frames: int = 100, seed: int | None = None) -> np.ndarray:
        """(N, 4, 4) float64 camera-to-world RDF poses; see :mod:`synthetic_world.trajectory`."""
        from .trajectory import trajectory

        return trajectory(self, preset, n_frames, self.seed if seed is None else seed)

    # ------------------------------------------------------------------ ground truth

    def _check_points(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {p.shape}")
        return p

    def labels_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) int32 class of the solid containing each point (N, 3); 0 = empty space.
        Where solids overlap, the later part wins."""
        p = self._check_points(points)
        out = np.zeros(len(p), dtype=np.int32)
        if len(p) == 0:
            return out
        order = np.argsort(p[:, 0], kind="stable")
        xs = p[order, 0]
        for i in range(len(self.parts)):
            lo = np.searchsorted(xs, self._amin[i, 0], "left")
            hi = np.searchsorted(xs, self._amax[i, 0], "right")
            if hi <= lo:
                continue
            idx = order[lo:hi]
            q = p[idx]
            m = np.all((q[:, 1:] >= self._amin[i, 1:]) & (q[:, 1:] <= self._amax[i, 1:]), axis=1)
            if not m.any():
                continue
            idx, q = idx[m], q[m]
            k = self._kind[i]
            inside = primitives.CONTAINS[k](q, self._params[k][self._kidx[i]])
            out[idx[inside]] = self._cls[i]
        return out

    def voxel_labels(self, ijk: np.ndarray, vox: float, samples: int = 3, chunk: int = 100_000) -> np.ndarray:
        """(N,) int32 ground-truth class of voxels ``ijk`` (N, 3) int (index = floor(xyz / vox)):
        the most frequent non-empty class over a ``samples``³ grid of sub-voxel centres, 0 if
        all are empty (ties: the lower class id)."""
        ijk = np.asarray(ijk)
        if ijk.ndim != 2 or ijk.shape[1] != 3:
            raise ValueError(f"ijk must have shape (N, 3), got {ijk.shape}")
        if vox <= 0 or samples < 1:
            raise ValueError(f"need vox > 0 and samples >= 1, got vox={vox}, samples={samples}")
        s = (np.arange(samples) + 0.5) / samples - 0.5
        off = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3) * vox  # (S³, 3)
        out = np.zeros(len(ijk), dtype=np.int32)
        nc = len(self.classes)
        for a in range(0, len(ijk), chunk):
            ctr = voxel_center(ijk[a:a + chunk], vox)
            pts = (ctr[:, None, :] + off[None]).reshape(-1, 3)
            lab = self.labels_at(pts).reshape(len(ctr), -1)
            counts = np.zeros((len(ctr), nc), dtype=np.int64)
            for c in np.unique(lab):
                if c:
                    counts[:, c] = (lab == c).sum(1)
            best = counts.argmax(1)
            out[a:a + chunk] = np.where(counts.max(1) > 0, best, 0)
        return out

    def _class_prims(self, class_id: int) -> dict[int, np.ndarray]:
        if not 0 <= int(class_id) < len(self.classes):
            raise ValueError(f"class id {class_id} out of range 0..{len(self.classes) - 1}")
        m = self._cls == class_id
        kinds = (primitives.KIND_BOX, primitives.KIND_FRUSTUM, primitives.KIND_SPHERE)
        return {k: self._params[k][self._kidx[m & (self._kind == k)]] for k in kinds}

    def distance_to_class(self, points: np.ndarray, class_id: int, chunk: int = 20_000) -> np.ndarray:
        """(N,) metres from each point to the nearest solid of any instance of ``class_id``
        (0 inside; exact SDFs of the primitives; +inf if the class has no instance)."""
        p = self._check_points(points)
        prims = self._class_prims(class_id)
        out = np.full(len(p), np.inf)
        for a in range(0, len(p), chunk):
            q = p[a:a + chunk, None, :]
            for k, prm in prims.items():
                if len(prm):
                    out[a:a + chunk] = np.minimum(out[a:a + chunk], primitives.DIST[k](q, prm[None]).min(1))
        return out

    def ray_distance_to_class(self, origin: ArrayLike, direction: ArrayLike, class_id: int,
                              max_range: float | None = None, tol: float = 1e-7) -> float:
        """Minimum distance (m) between the half-line ``origin + t·direction`` (t ≥ 0, up to
        ``max_range`` if given) and any solid of ``class_id`` (0 if the ray hits one; +inf if
        the class has no instance).

        Exact up to ``tol``: the distance from ``origin + t·d`` to a convex solid is convex in
        ``t``, so a golden-section search per primitive over a bracket that provably holds
        the minimiser (from the primitive's bounding sphere) converges to the true minimum."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        if o.shape != (3,) or d.shape != (3,):
            raise ValueError(f"origin and direction must be 3-vectors, got shapes {o.shape}, {d.shape}")
        return float(self.rays_distance_to_class(o[None], d[None], class_id, max_range, tol)[0])

    def rays_distance_to_class(self, origins: ArrayLike, directions: ArrayLike, class_id: int,
                               max_range: float | None = None, tol: float = 1e-7,
                               chunk: int = 4096) -> np.ndarray:
        """Batched :meth:`ray_distance_to_class`: origins and directions (N, 3) → (N,) metres."""
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise ValueError(f"origins and directions must both have shape (N, 3), got {o.shape}, {d.shape}")
        nd = np.linalg.norm(d, axis=1)
        if not np.all(np.isfinite(nd)) or np.any(nd == 0) or not np.all(np.isfinite(o)):
            raise ValueError("need finite origins and non-zero finite directions")
        if not 0 <= int(class_id) < len(self.classes):
            raise ValueError(f"class id {class_id} out of range 0..{len(self.classes) - 1}")
        d = d / nd[:, None]
        best = np.full(len(o), np.inf)
        m = self._cls == class_id
        for k in (primitives.KIND_BOX, primitives.KIND_FRUSTUM, primitives.KIND_SPHERE):
            sel = np.nonzero(m & (self._kind == k))[0]
            if not len(sel):
                continue
            prm = self._params[k][self._kidx[sel]][None]  # (1, M, w)
            ctr = ((self._amin[sel] + self._amax[sel]) / 2)[None]  # (1, M, 3)
            rad = (np.linalg.norm(self._amax[sel] - self._amin[sel], axis=1) / 2)[None]
            step = max(1, chunk // len(sel))
            for a in range(0, len(o), step):
                oo, dd = o[a:a + step, None, :], d[a:a + step, None, :]  # (n, 1, 3)
                tp = np.sum((ctr - oo) * dd, axis=-1)  # (n, M)
                perp = np.linalg.norm(oo + tp[..., None] * dd - ctr, axis=-1)
                # f(t*) <= f(t0) <= |o + t0 d - c| + rad and f(t) >= |o + t d - c| - rad bound |t* - tp|.
                t0 = np.maximum(tp, 0.0)
                d0 = np.hypot(perp, t0 - tp)
                span = np.sqrt(np.maximum((d0 + 2 * rad) ** 2 - perp ** 2, 0.0)) + 1e-6
                lo, hi = np.maximum(tp - span, 0.0), np.maximum(tp + span, 0.0)
                if max_range is not None:
                    lo, hi = np.minimum(lo, max_range), np.minimum(hi, max_range)
                val = _golden_min(primitives.DIST[k], oo, dd, prm, lo, hi, tol)  # (n, M)
                best[a:a + step] = np.minimum(best[a:a + step], val.min(axis=1))
        return best


def _golden_min(f, o: np.ndarray, d: np.ndarray, prm: np.ndarray, a: np.ndarray, b: np.ndarray,
                tol: float) -> np.ndarray:
    """Per-primitive minimum of the convex ``t -> f(o + t d, prm[i])`` over ``[a[i], b[i]]``."""
    g = (np.sqrt(5.0) - 1.0) / 2.0

    def ev(t):
        return f(o + t[..., None] * d, prm)

    c, e = b - g * (b - a), a + g * (b - a)
    fc, fe = ev(c), ev(e)
    lowest = np.minimum(np.minimum(ev(a), ev(b)), np.minimum(fc, fe))
    while np.max(b - a) > tol:
        left = fc < fe  # the minimum lies in [a, e]
        b = np.where(left, e, b)
        a = np.where(left, a, c)
        nc = np.where(left, b - g * (b - a), e)
        ne = np.where(left, c, a + g * (b - a))
        fn = ev(np.where(left, nc, ne))
        fc, fe = np.where(left, fn, fe), np.where(left, fc, fn)
        c, e = nc, ne
        lowest = np.minimum(lowest, fn)
    return np.minimum(lowest, ev((a + b) / 2))
