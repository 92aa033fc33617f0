"""A world we did not write: scenes assembled with a seed from the assets that ship with
``pybullet`` (``pybullet_data``), rendered by pybullet's CPU renderer (docs/pybullet_world.md).

    from synthetic_world.pybullet_world import PybulletWorld
    w = PybulletWorld.generate(seed=0)
    K = w.camera((224, 224), 90.0)
    r = w.render(pose, K, (224, 224))   # r.rgb, r.depth (planar, +inf nothing), r.labels, r.instance

It offers what the closed loop and the edge use of :class:`synthetic_world.World`:
``classes`` (:data:`synthetic_world.pybullet_assets.CLASS_NAMES`, 0 = sky), ``instances``
(one per body: id = load order, class from its asset, AABB from ``getAABB`` over all links),
``class_id``, ``instances_of``, ``camera``, ``render`` and ``labels_at`` (what solid, if
any, holds a point).

Scene (seed): the ground plane, the samurai monastery at the origin turned by a random yaw,
``count`` objects of each object asset at random free spots of the site (``site_half_m``:
a footprint circle whose vertical rays from 40 m down all reach the ground first: open
ground, no roof), each with a random yaw; the landmarks (tall assets scaled up) at
``landmark_m`` from the origin, bearings at least 90° apart.

Rendering: ``p.getCameraImage`` with ``ER_TINY_RENDERER`` in a ``p.DIRECT`` connection (no
display, no GPU): RGB, the OpenGL depth buffer turned into metric planar depth
(``far·near / (far − (far − near)·d)``; ``d = 1``, no surface, → +inf) and the segmentation
mask (body unique id per pixel, −1 none) mapped to class ids (``labels``) and instance ids. The
tiny renderer culls back faces and the monastery's mesh is one-sided in places: a
visual-only twin with every triangle turned round makes its walls visible from both sides,
as the ray test (and the robot) meet them.
Intrinsics must have square pixels and the principal point at the image centre (what
:meth:`camera` gives). The tiny renderer samples each pixel half a pixel off its centre; the
projection is shifted by half a pixel so that pixel (u, v) looks through (u + ½, v + ½) as
docs/conventions.md says (checked against ``rayTestBatch`` in tests/test_pybullet_world.py).

Free space (``labels_at``): pybullet has no point-in-solid test for concave meshes, so the
collision shapes are voxelised lazily in cubic tiles (``tile`` voxels of ``vox_m``) with
``p.rayTestBatch``: rays along x, y and z through every row of voxel centres of a tile,
marched from hit to hit; a voxel holding a hit point is a surface voxel with the hit body's
class, and every voxel within one voxel of a surface voxel (26-neighbourhood) is solid: the
surfaces are inflated by up to one voxel (0.25 m), so a surface crossing a voxel between the
rows of rays is still solid and the robot's body points (0.32 m apart vertically) feel a thin
table top; free space is conservative by that much. It marks surfaces (a shell), not closed
interiors — a body cannot get inside one without crossing its shell. Below z = 0 is ground.
World frame z up, metres.
"""
from __future__ import annotations

import math
import os
import re
import shutil
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from common.geometry import intrinsics_from_fov
from synthetic_world.pybullet_assets import ASSETS, CLASS_NAMES, Asset
from synthetic_world.render import Render
from synthetic_world.scene import Instance

#: the renderer's clip planes (m)
NEAR_M, FAR_M = 0.1, 400.0


@contextmanager
def _quiet():
    """Silence pybullet's C-level notes (URDF inertia warnings) on stdout / stderr while loading."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:          # pragma: no cover - no standard streams
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


def _flipped_obj(path: Path) -> Path:
    """A copy of Wavefront OBJ ``path`` (with its material library) whose faces list their
    vertices in reverse order (the other side of every triangle), cached in the temp dir."""
    import tempfile

    out_dir = Path(tempfile.gettempdir()) / f"rayfronts_pybullet_{os.getuid()}"
    out = out_dir / f"{path.stem}_flipped_{path.stat().st_size}.obj"
    if out.exists():
        return out
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = []
    for line in path.read_text().splitlines():
        if line.startswith("f "):
            line = "f " + " ".join(reversed(line.split()[1:]))
        lines.append(line)
        if line.startswith("mtllib "):
            mtl = path.parent / line.split(maxsplit=1)[1].strip()
            if mtl.exists():
                shutil.copyfile(mtl, out_dir / mtl.name)
    tmp = out.with_suffix(f".tmp{os.getpid()}")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, out)
    return out


class PybulletWorld:
    """One pybullet scene in its own ``p.DIRECT`` connection (module docstring)."""

    def __init__(self, seed: int = 0, site_half_m: float = 40.0, landmark_m: tuple[float, float] = (95.0, 110.0),
                 vox_m: float = 0.25, tile: int = 32, assets: tuple[Asset, ...] = ASSETS):
        import pybullet as p
        import pybullet_data

        self.seed = int(seed)
        self.classes: list[str] = list(CLASS_NAMES)
        self.vox, self.tile = float(vox_m), int(tile)
        self._p = p
        self.cid = p.connect(p.DIRECT)
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=self.cid)
        self._body_class: dict[int, int] = {}
        self._body_inst: dict[int, int] = {}
        self.instances: list[Instance] = []
        self._tiles: dict[tuple[int, int, int], np.ndarray] = {}
        rng = np.random.default_rng(self.seed)
        with _quiet():
            self._assemble(rng, assets, float(site_half_m), landmark_m)

    @classmethod
    def generate(cls, seed: int = 0) -> "PybulletWorld":
        """The scene of ``seed`` (module docstring)."""
        return cls(seed)

    def close(self) -> None:
        """Disconnect from pybullet (the world cannot render afterwards)."""
        if self.cid >= 0:
            try:
                self._p.disconnect(physicsClientId=self.cid)
            except Exception:   # noqa: BLE001 - already gone
                pass
            self.cid = -1

    def __del__(self) -> None:
        self.close()

    # ------------------------------------------------------------------ assembly

    def _load(self, a: Asset, yaw: float) -> int:
        p = self._p
        q = p.getQuaternionFromEuler([0.0, 0.0, yaw])
        if a.file.endswith(".sdf"):
            uid = p.loadSDF(a.file, globalScaling=a.scale, physicsClientId=self.cid)[0]
            p.resetBasePositionAndOrientation(uid, [0, 0, 0], q, physicsClientId=self.cid)
        else:
            uid = p.loadURDF(a.file, [0, 0, 0], q, useFixedBase=True, globalScaling=a.scale,
                             physicsClientId=self.cid)
        return int(uid)

    def _aabb(self, uid: int) -> tuple[np.ndarray, np.ndarray]:
        p = self._p
        boxes = [p.getAABB(uid, link, physicsClientId=self.cid)
                 for link in range(-1, p.getNumJoints(uid, physicsClientId=self.cid))]
        lo = np.min([b[0] for b in boxes], 0)
        hi = np.max([b[1] for b in boxes], 0)
        return np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    def _move_to(self, uid: int, xy: np.ndarray, on_ground: bool = True) -> None:
        """Shift body ``uid`` so its AABB's xy centre is at ``xy`` and (``on_ground``) nothing
        of it below z = 0 (an asset modelled above the ground, e.g. the table whose collision
        shape is its top only, keeps its height)."""
        p = self._p
        pos, q = p.getBasePositionAndOrientation(uid, physicsClientId=self.cid)
        lo, hi = self._aabb(uid)
        d = np.r_[np.asarray(xy, np.float64) - (lo[:2] + hi[:2]) / 2, max(0.0, -lo[2]) if on_ground else 0.0]
        p.resetBasePositionAndOrientation(uid, list(np.asarray(pos) + d), q, physicsClientId=self.cid)

    def _register(self, uid: int, class_name: str, name: str) -> None:
        cid = self.class_id(class_name)
        iid = len(self.instances)
        lo, hi = self._aabb(uid)
        self._body_class[uid], self._body_inst[uid] = cid, iid
        self.instances.append(Instance(iid, cid, name, (lo + hi) / 2, lo, hi))

    def _add_back_faces(self, uid: int, a: Asset) -> None:
        """A visual-only twin of body ``uid`` whose mesh has every triangle turned round, at the
        same pose: the tiny renderer culls back faces, and the monastery's mesh is one-sided
        in places, so without it the camera would see through walls the ray test (and the
        robot) hit. The twin's pixels read as ``uid``'s class and instance."""
        import pybullet_data

        p = self._p
        root = Path(pybullet_data.getDataPath())
        src = root / a.file
        urdf = src.read_text()
        mesh = re.search(r'<visual>.*?<mesh filename="([^"]+)"', urdf, re.S)
        origin = re.search(r'<visual>\s*<origin rpy="([^"]+)"', urdf, re.S)
        if mesh is None:
            return
        obj = _flipped_obj(root / mesh.group(1))
        rpy = [float(x) for x in origin.group(1).split()] if origin else [0.0, 0.0, 0.0]
        vis = p.createVisualShape(p.GEOM_MESH, fileName=str(obj), meshScale=[a.scale] * 3,
                                  visualFrameOrientation=p.getQuaternionFromEuler(rpy), physicsClientId=self.cid)
        pos, q = p.getBasePositionAndOrientation(uid, physicsClientId=self.cid)
        twin = p.createMultiBody(0.0, -1, vis, pos, q, physicsClientId=self.cid)
        self._body_class[twin], self._body_inst[twin] = self._body_class[uid], self._body_inst[uid]

    def _open_ground(self, xy: np.ndarray, radius: float) -> bool:
        """Whether vertical rays from 40 m down over a circle of ``radius`` around ``xy`` all
        reach the ground plane first (open ground, no roof, nothing placed)."""
        ang = np.linspace(0.0, 2 * math.pi, 12, endpoint=False)
        pts = np.concatenate([[xy], xy + radius * np.c_[np.cos(ang), np.sin(ang)],
                              xy + 0.5 * radius * np.c_[np.cos(ang), np.sin(ang)]])
        hits = self._p.rayTestBatch(np.c_[pts, np.full(len(pts), 40.0)].tolist(),
                                    np.c_[pts, np.full(len(pts), -0.5)].tolist(), physicsClientId=self.cid)
        return all(h[0] == self.ground_uid for h in hits)

    def _assemble(self, rng: np.random.Generator, assets: tuple[Asset, ...], half: float,
                  landmark_m: tuple[float, float]) -> None:
        site: tuple[int, Asset] | None = None
        for a in assets:
            if a.role == "ground":
                self.ground_uid = self._load(a, 0.0)
                self._register(self.ground_uid, a.class_name, a.class_name)
        for a in assets:
            if a.role == "site":
                uid = self._load(a, float(rng.uniform(0, 2 * math.pi)))
                self._move_to(uid, np.zeros(2), on_ground=False)
                self._register(uid, a.class_name, a.class_name)
                site = (uid, a)
        for a in assets:
            for k in range(a.count if a.role == "object" else 0):
                uid = self._load(a, float(rng.uniform(0, 2 * math.pi)))
                lo, hi = self._aabb(uid)
                radius = 0.5 * float(np.hypot(*(hi[:2] - lo[:2]))) + 0.5
                for _ in range(200):
                    xy = rng.uniform(-half, half, 2)
                    if self._open_ground(xy, radius):
                        break
                else:
                    raise ValueError(f"seed {self.seed}: no open ground found for a {a.class_name!r}")
                self._move_to(uid, xy)
                self._register(uid, a.class_name, f"{a.class_name} {k}")
        bearings: list[float] = []
        for a in assets:
            if a.role != "landmark":
                continue
            for _ in range(100):
                b = float(rng.uniform(0, 2 * math.pi))
                if all(abs(math.remainder(b - c, 2 * math.pi)) >= math.pi / 2 for c in bearings):
                    break
            bearings.append(b)
            uid = self._load(a, float(rng.uniform(0, 2 * math.pi)))
            self._move_to(uid, float(rng.uniform(*landmark_m)) * np.array([math.cos(b), math.sin(b)]))
            self._register(uid, a.class_name, a.class_name)
        if site is not None:        # last, so that body i is instance i
            self._add_back_faces(*site)

    # ------------------------------------------------------------------ metadata

    def class_id(self, name: str) -> int:
        """Class id of ``name``; ``ValueError`` naming the valid classes if unknown."""
        try:
            return self.classes.index(name)
        except ValueError:
            raise ValueError(f"unknown class {name!r}; valid classes: {', '.join(self.classes)}") from None

    def instances_of(self, class_id: int) -> list[Instance]:
        """The instances of class ``class_id`` (index into :attr:`classes`)."""
        return [i for i in self.instances if i.class_id == class_id]

    # ------------------------------------------------------------------ rendering

    def camera(self, hw: tuple[int, int] = (224, 224), hfov_deg: float = 90.0) -> np.ndarray:
        """Intrinsics K (3×3) for ``hw`` = (H, W) with horizontal FoV ``hfov_deg``, square pixels."""
        return intrinsics_from_fov(hfov_deg, int(hw[0]), int(hw[1]))

    def gl_matrices(self, pose: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> tuple[list, list]:
        """(view, projection): pybullet's column-major OpenGL matrices for camera-to-world
        ``pose`` (RDF) and intrinsics ``K`` at ``hw`` = (H, W)."""
        H, W = int(hw[0]), int(hw[1])
        K = np.asarray(K, np.float64)
        if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[1, 1] or abs(K[0, 2] - W / 2) > 1e-6 or abs(K[1, 2] - H / 2) > 1e-6:
            raise ValueError("pybullet world: K must have square pixels and the principal point at the image "
                             "centre (use PybulletWorld.camera)")
        gl = np.asarray(pose, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])   # RDF → OpenGL camera axes
        view = np.linalg.inv(gl)
        vfov = math.degrees(2 * math.atan(0.5 * H / K[1, 1]))
        proj = list(self._p.computeProjectionMatrixFOV(vfov, W / H, NEAR_M, FAR_M))
        # the tiny renderer samples pixel (u, v) half a pixel off the centre (u + ½, v + ½) of
        # the conventions; shift the image plane by half a pixel (one NDC pixel is 2 / W)
        proj[8] += 1.0 / W
        proj[9] += 1.0 / H
        return view.T.reshape(-1).tolist(), proj

    def render(self, pose: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> Render:
        """RGB, planar depth (+inf = no surface), labels (0 = sky) and instance ids (−1 =
        none) seen from camera-to-world ``pose`` (RDF) with intrinsics ``K`` at ``hw``."""
        H, W = int(hw[0]), int(hw[1])
        view, proj = self.gl_matrices(pose, K, hw)
        _, _, rgba, dbuf, seg = self._p.getCameraImage(W, H, view, proj, renderer=self._p.ER_TINY_RENDERER,
                                                       physicsClientId=self.cid)
        rgb = np.asarray(rgba, np.uint8).reshape(H, W, 4)[..., :3].copy()
        d = np.asarray(dbuf, np.float64).reshape(H, W)
        depth = np.full((H, W), np.inf, np.float32)
        hit = d < 1.0
        depth[hit] = (FAR_M * NEAR_M / (FAR_M - (FAR_M - NEAR_M) * d[hit])).astype(np.float32)
        seg = np.asarray(seg, np.int64).reshape(H, W)
        n = max(self._body_class) + 2
        cls_of, inst_of = np.zeros(n, np.int32), np.full(n, -1, np.int32)
        for uid, c in self._body_class.items():
            cls_of[uid + 1], inst_of[uid + 1] = c, self._body_inst[uid]
        idx = np.clip(seg, -1, n - 2) + 1
        return Render(rgb, depth, cls_of[idx], inst_of[idx])

    def ray_test(self, origins: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """pybullet's own ray test (collision shapes): (hit points (N, 3) m, NaN where none;
        class id (N,), 0 where none) of the segments ``origins`` → ``ends`` (N, 3)."""
        o, e = np.asarray(origins, np.float64).reshape(-1, 3), np.asarray(ends, np.float64).reshape(-1, 3)
        pts, cls = np.full(o.shape, np.nan), np.zeros(len(o), np.int32)
        for s in range(0, len(o), 4096):
            res = self._p.rayTestBatch(o[s:s + 4096].tolist(), e[s:s + 4096].tolist(), physicsClientId=self.cid)
            for i, h in enumerate(res):
                if h[0] >= 0:
                    pts[s + i], cls[s + i] = h[3], self._body_class.get(h[0], 0)
        return pts, cls

    # ------------------------------------------------------------------ free space

    def labels_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) int32 class of the solid at each point (N, 3) m; 0 = free (module docstring)."""
        pts = np.asarray(points, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        out = np.zeros(len(pts), np.int32)
        if len(pts) == 0:
            return out
        below = pts[:, 2] < 0.0
        out[below] = self.class_id("ground")
        above = np.flatnonzero(~below)
        out[above] = self._voxel_labels(np.floor(pts[above] / self.vox).astype(np.int64))
        return out

    def _voxel_labels(self, ijk: np.ndarray) -> np.ndarray:
        t = self.tile
        keys = np.floor_divide(ijk, t)
        uk, inv = np.unique(keys, axis=0, return_inverse=True)
        out = np.zeros(len(ijk), np.int32)
        local = ijk - keys * t
        for n, k in enumerate(uk):
            grid = self._tile_grid((int(k[0]), int(k[1]), int(k[2])))
            sel = np.flatnonzero(inv.reshape(-1) == n)
            loc = local[sel]
            out[sel] = grid[loc[:, 0], loc[:, 1], loc[:, 2]]
        return out

    def _tile_grid(self, key: tuple[int, int, int]) -> np.ndarray:
        """(tile, tile, tile) uint8 class ids of the voxels of tile ``key`` (computed once)."""
        grid = self._tiles.get(key)
        if grid is not None:
            return grid
        t, v = self.tile, self.vox
        lo = np.asarray(key, np.float64) * t * v - v          # the tile plus a one-voxel margin
        hi = lo + (t + 2) * v
        grid = np.zeros((t + 2, t + 2, t + 2), np.uint8)
        near = self._p.getOverlappingObjects(lo.tolist(), hi.tolist(), physicsClientId=self.cid) or []
        if hi[2] > 0.0 and any(u != self.ground_uid for u, _ in near):
            c = (np.arange(t + 2) + 0.5) * v
            for axis in range(3):
                a, b = [x for x in range(3) if x != axis]
                ua, ub = np.meshgrid(lo[a] + c, lo[b] + c, indexing="ij")
                start = np.zeros((ua.size, 3))
                start[:, a], start[:, b], start[:, axis] = ua.ravel(), ub.ravel(), lo[axis] - 1e-3
                end = start.copy()
                end[:, axis] = hi[axis] + 1e-3
                self._march(grid, start, end, axis, lo)
        out = np.zeros((t, t, t), np.uint8)       # dilate by one voxel (26-neighbourhood), crop the margin
        for dx in range(3):
            for dy in range(3):
                for dz in range(3):
                    np.maximum(out, grid[dx:dx + t, dy:dy + t, dz:dz + t], out=out)
        self._tiles[key] = out
        return out

    def _march(self, grid: np.ndarray, start: np.ndarray, end: np.ndarray, axis: int, lo: np.ndarray,
               max_hits: int = 64) -> None:
        """Cast rows ``start`` → ``end`` along ``axis``, hit after hit; mark each hit's voxel."""
        t, v = grid.shape[0], self.vox
        frm = start.copy()
        live = np.arange(len(frm))
        cls_of = np.zeros(max(self._body_class) + 1, np.uint8)
        for body_uid, c in self._body_class.items():
            cls_of[body_uid] = c
        for _ in range(max_hits):
            if len(live) == 0:
                return
            res = self._p.rayTestBatch(frm[live].tolist(), end[live].tolist(), physicsClientId=self.cid)
            uid = np.fromiter((h[0] for h in res), np.int64, len(res))
            hit = uid >= 0
            live, uid = live[hit], uid[hit]
            hp = np.array([h[3] for h, ok in zip(res, hit, strict=True) if ok], np.float64).reshape(-1, 3)
            body = (uid != self.ground_uid) & (uid < len(cls_of))
            ijk = np.clip(np.floor((hp[body] - lo) / v).astype(np.int64), 0, t - 1)
            grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.maximum(grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]],
                                                             cls_of[uid[body]])
            moved = hp[:, axis] - frm[live, axis] > 1e-6
            frm[live, axis] = hp[:, axis] + np.where(moved, 1e-3, 0.5 * v)   # stuck at the start: jump on
            live = live[frm[live, axis] < end[live, axis]]
