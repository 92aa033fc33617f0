"""Object instances with stable ids, tracked across map updates (pure computation).

An :class:`InstanceTracker` is fed, at each map update, the voxels whose confidence for a
target is above the caller's threshold (integer voxel indices ``ijk = floor(xyz / vox)``,
world frame, metres, z up; :func:`common.conventions.voxel_index`). Per target it groups them
26-connected (:func:`connected_26`) and matches the groups to the previous instances of
that target by voxel overlap:

* a group overlapping exactly one previous instance keeps its id (the instance grows or
  shrinks);
* a previous instance overlapping several groups is **split**: its id stays on the largest
  group (most voxels; ties by the group holding the lowest voxel key), the other groups get
  new ids (event ``split`` with ``parent`` = the old id);
* a group overlapping several previous instances is a **merge**: it keeps the oldest id
  (smallest ``first_seen``, ties by smallest id; event ``merge`` with ``merged`` = the other
  ids, which end);
* a group overlapping nothing is a new instance (event ``new``); a previous instance
  overlapping nothing ends (event ``lost``).

Ids are positive integers, unique across the tracker's targets and never reused.
Frame counters are the map's (``observations`` counts distinct update frames in which the
instance was seen; an update at the same frame as the previous one does not count twice).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from common.conventions import voxel_center

#: 13 half-space neighbour offsets of the 26-neighbourhood (each undirected edge once)
_HALF_26 = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) > (0, 0, 0)], np.int64)


def pack_ijk(ijk: np.ndarray) -> np.ndarray:
    """(N, 3) int voxel indices → (N,) int64 keys preserving lexicographic (i, j, k) order
    (21 bits per axis, indices in ``[-2^20, 2^20)``, as :mod:`semantic_map.cell_keys`)."""
    a = np.asarray(ijk, np.int64).reshape(-1, 3) + (1 << 20)
    if a.size and (a.min() < 0 or a.max() >= (1 << 21)):
        raise ValueError("voxel index outside the packable range [-2^20, 2^20)")
    return (a[:, 0] << 42) | (a[:, 1] << 21) | a[:, 2]


def connected_26(ijk: np.ndarray) -> np.ndarray:
    """26-connected components of a set of distinct voxel indices (N, 3) → (N,) int64 label
    per voxel, labels ``0..C-1`` numbered by each component's lowest voxel key."""
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    n = len(ijk)
    if n == 0:
        return np.zeros((0,), np.int64)
    keys = pack_ijk(ijk)
    lo = ijk.min(0)
    shape = ijk.max(0) - lo + 1
    if int(np.prod(shape)) <= max(DENSE_MIN_CELLS, DENSE_CELLS_PER_VOXEL * n):
        return _relabel(_dense_labels(ijk - lo, (int(shape[0]), int(shape[1]), int(shape[2]))), keys)
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    parent = np.arange(n, dtype=np.int64)
    ra, rb = [], []
    for off in _HALF_26:
        nk = pack_ijk(ijk + off)
        pos = np.clip(np.searchsorted(sk, nk), 0, n - 1)
        hit = sk[pos] == nk
        ra.append(np.flatnonzero(hit))
        rb.append(order[pos[hit]])
    a, b = np.concatenate(ra), np.concatenate(rb)
    # min-label propagation with pointer jumping (vectorised union-find)
    while True:
        pa, pb = parent[a], parent[b]
        lo = np.minimum(pa, pb)
        np.minimum.at(parent, pa, lo)
        np.minimum.at(parent, pb, lo)
        while True:
            nxt = parent[parent]
            if np.array_equal(nxt, parent):
                break
            parent = nxt
        if np.array_equal(parent[a], parent[b]):
            break
    return _relabel(parent, keys)


#: a group's bounding box up to this many cells (or DENSE_CELLS_PER_VOXEL per voxel) is
#: labelled on a dense grid (scipy.ndimage), larger sparse sets by union-find on keys
DENSE_MIN_CELLS = 1 << 18
DENSE_CELLS_PER_VOXEL = 16


def _dense_labels(ijk0: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Component id per voxel (any numbering) of voxels ``ijk0`` (N, 3) >= 0 in a box ``shape``."""
    from scipy import ndimage

    grid = np.zeros(shape, bool)
    grid[ijk0[:, 0], ijk0[:, 1], ijk0[:, 2]] = True
    lab, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    return lab[ijk0[:, 0], ijk0[:, 1], ijk0[:, 2]].astype(np.int64)


def _relabel(comp: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Component ids ``comp`` (N,) renumbered 0..C-1 in order of each component's lowest key."""
    _, inv = np.unique(comp, return_inverse=True)
    first_key = np.full(int(inv.max()) + 1, np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first_key, inv, keys)
    rank = np.empty(len(first_key), np.int64)
    rank[np.argsort(first_key, kind="stable")] = np.arange(len(first_key))
    return rank[inv]


@dataclass
class Instance:
    """One tracked object: box and centroid in world metres (voxel centres; the box spans
    voxel centres, not faces), ``confidence`` the max voxel confidence, ``voxels`` its count,
    ``observations`` distinct map frames it was seen in, ``first_seen``/``last_seen`` map
    frame counters. ``keys`` (packed voxel indices, sorted) is the tracker's own state."""

    id: int
    target: str
    centroid: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    confidence: float
    voxels: int
    observations: int
    first_seen: int
    last_seen: int
    keys: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0,), np.int64))

    def as_dict(self) -> dict:
        """Plain-Python fields (lists of floats), without the voxel keys."""
        return dict(id=int(self.id), target=self.target, centroid=[float(v) for v in self.centroid],
                    box_min=[float(v) for v in self.box_min], box_max=[float(v) for v in self.box_max],
                    confidence=float(self.confidence), voxels=int(self.voxels),
                    observations=int(self.observations), first_seen=int(self.first_seen),
                    last_seen=int(self.last_seen))


@dataclass
class InstanceEvent:
    """What an update did to an id: ``kind`` in {"new", "split", "merge", "lost"}; ``parent``
    the split instance (split); ``merged`` the ids absorbed into ``id`` (merge)."""

    kind: str
    id: int
    target: str
    frame: int
    parent: int | None = None
    merged: list[int] = field(default_factory=list)

    def as_dict(self) -> dict:
        d: dict = dict(kind=self.kind, id=int(self.id), target=self.target, frame=int(self.frame))
        if self.parent is not None:
            d["parent"] = int(self.parent)
        if self.merged:
            d["merged"] = [int(i) for i in self.merged]
        return d


def _overlaps(prev: list[Instance], keys: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(P, C) voxel overlap counts between previous instances and new groups."""
    n_groups = int(labels.max()) + 1 if len(labels) else 0
    out = np.zeros((len(prev), n_groups), np.int64)
    if not prev or not len(keys):
        return out
    order = np.argsort(keys, kind="stable")
    sk, sl = keys[order], labels[order]
    for i, p in enumerate(prev):
        pos = np.clip(np.searchsorted(sk, p.keys), 0, len(sk) - 1)
        hit = sk[pos] == p.keys
        if hit.any():
            out[i] = np.bincount(sl[pos[hit]], minlength=n_groups)
    return out


class InstanceTracker:
    """Stable instance ids per target across map updates (see the module docstring).

    ``vox``: voxel size (m). ``min_voxels``: groups smaller than this are ignored (noise).
    """

    def __init__(self, vox: float, min_voxels: int = 1, id_source: Callable[[], int] | None = None):
        """``id_source``: where new ids come from (one counter shared by several trackers, kept
        across restarts), default this tracker's own counter from 1."""
        if vox <= 0:
            raise ValueError(f"vox must be > 0, got {vox}")
        self.vox = float(vox)
        self.min_voxels = max(1, int(min_voxels))
        self.next_id = 1
        self._id_source = id_source
        self.instances: dict[str, list[Instance]] = {}
        self.updates = 0

    def _new_id(self) -> int:
        if self._id_source is not None:
            return self._id_source()
        i = self.next_id
        self.next_id += 1
        return i

    def update(self, target: str, ijk: np.ndarray, confidence: np.ndarray, frame: int) -> list[InstanceEvent]:
        """Track ``target``'s voxels above threshold at map frame ``frame``: ``ijk`` (N, 3)
        distinct voxel indices, ``confidence`` (N,) in [0, 1]. Returns the events."""
        ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
        conf = np.asarray(confidence, np.float64).reshape(-1)
        if len(conf) != len(ijk):
            raise ValueError(f"{len(ijk)} voxels but {len(conf)} confidences")
        frame = int(frame)
        self.updates += 1
        keys = pack_ijk(ijk)
        labels = connected_26(ijk)
        sizes = np.bincount(labels) if len(labels) else np.zeros((0,), np.int64)
        keep = np.flatnonzero(sizes >= self.min_voxels)
        remap = np.full(len(sizes), -1, np.int64)
        remap[keep] = np.arange(len(keep))
        sel = remap[labels] >= 0 if len(labels) else np.zeros((0,), bool)
        ijk, conf, keys, labels = ijk[sel], conf[sel], keys[sel], remap[labels[sel]]
        sizes = sizes[keep]
        prev = self.instances.get(target, [])
        ov = _overlaps(prev, keys, labels)
        # each previous instance goes to its largest overlapping group (ties: lowest group label)
        goes_to = np.full(len(prev), -1, np.int64)
        for i in range(len(prev)):
            js = np.flatnonzero(ov[i])
            if len(js):
                goes_to[i] = js[np.argmax(sizes[js])]
        events: list[InstanceEvent] = []
        out: list[Instance] = []
        by_group = np.argsort(labels, kind="stable")
        bounds = np.searchsorted(labels[by_group], np.arange(len(sizes) + 1))
        for j in range(len(sizes)):
            m = by_group[bounds[j]:bounds[j + 1]]          # this group's rows (ascending)
            heirs = [prev[i] for i in np.flatnonzero(goes_to == j)]
            heirs.sort(key=lambda p: (p.first_seen, p.id))
            gk = np.sort(keys[m])
            centres = voxel_center(ijk[m], self.vox).astype(np.float64)
            inst = Instance(0, target, centres.mean(0), centres.min(0), centres.max(0), float(conf[m].max()),
                            len(m), 1, frame, frame, gk)
            if heirs:
                old = heirs[0]
                inst.id, inst.first_seen = old.id, old.first_seen
                inst.observations = old.observations + (1 if frame != old.last_seen else 0)
                if len(heirs) > 1:
                    events.append(InstanceEvent("merge", old.id, target, frame, merged=[h.id for h in heirs[1:]]))
            else:
                inst.id = self._new_id()
                parents = np.flatnonzero(ov[:, j]) if len(prev) else np.zeros((0,), np.int64)
                if len(parents):
                    par = prev[parents[np.argmax(ov[parents, j])]]
                    events.append(InstanceEvent("split", inst.id, target, frame, parent=par.id))
                else:
                    events.append(InstanceEvent("new", inst.id, target, frame))
            out.append(inst)
        for i, p in enumerate(prev):
            if not ov[i].any():
                events.append(InstanceEvent("lost", p.id, target, frame))
        out.sort(key=lambda x: x.id)
        self.instances[target] = out
        return events

    def current(self, target: str | None = None) -> list[Instance]:
        """The live instances (of ``target``, else of every target), by id."""
        if target is not None:
            return list(self.instances.get(target, []))
        return sorted((i for v in self.instances.values() for i in v), key=lambda x: x.id)
