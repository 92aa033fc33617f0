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
  overlapping nothing is **missing**: with ``grace`` = N it stays matchable (by its last
  voxels) for N more updates without being current, and a group overlapping it then takes its
  id back (no event); after N updates unseen it ends (event ``lost``; N = 0: at once);
* an instance that keeps its id with more voxels than before grows (event ``grow``, with
  ``voxels`` its new count; a merge says ``merge`` instead).

Ids are positive integers, unique across the tracker's targets and never reused.
:meth:`InstanceTracker.state` / :meth:`InstanceTracker.load_state` carry the instances (the
missing ones too) across a restart as plain data.
The tracker keeps the components of each target's last voxel set: an update with the same
voxels (the same map version searched again) skips the labelling, and one with the same
voxels, confidences and frame returns at once (it would change nothing).
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


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 keys of :func:`pack_ijk` → (N, 3) int64 voxel indices."""
    k = np.asarray(keys, np.int64).reshape(-1)
    out = np.empty((len(k), 3), np.int64)
    np.right_shift(k, 42, out=out[:, 0])
    np.right_shift(k, 21, out=out[:, 1])
    out[:, 2] = k
    out &= (1 << 21) - 1
    out -= 1 << 20
    return out


def labels_of_sorted(keys: np.ndarray) -> np.ndarray:
    """:func:`connected_26` of the voxels of strictly ascending packed ``keys`` (N,): their
    labels in that order (the map's C++ kernel when built, else the paths of
    :func:`connected_26`)."""
    keys = np.asarray(keys, np.int64).reshape(-1)
    if len(keys) >= KERNEL_MIN_VOXELS:
        import semantic_map

        got = semantic_map.voxel_components_26(keys)
        if got is not None:
            return got
    return connected_26(unpack_keys(keys))


def key_order(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(order, keys[order])`` with ``order = np.argsort(keys, kind="stable")`` of packed
    voxel ``keys`` (N,) (the map's C++ radix sort when built and the keys' span allows it,
    else numpy; the same)."""
    keys = np.asarray(keys, np.int64).reshape(-1)
    if len(keys) >= KERNEL_MIN_VOXELS:
        import semantic_map

        got = semantic_map.voxel_key_order(keys)
        if got is not None:
            return got
    order = np.argsort(keys, kind="stable")
    return order, keys[order]


def connected_26(ijk: np.ndarray) -> np.ndarray:
    """26-connected components of a set of distinct voxel indices (N, 3) → (N,) int64 label
    per voxel, labels ``0..C-1`` numbered by each component's lowest voxel key."""
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    n = len(ijk)
    if n == 0:
        return np.zeros((0,), np.int64)
    keys = pack_ijk(ijk)
    if n >= KERNEL_MIN_VOXELS:
        import semantic_map

        order, sk = key_order(keys)
        got = semantic_map.voxel_components_26(sk)
        if got is not None:                    # the C++ union-find (same labels, numbered alike)
            lab = np.empty(n, np.int64)
            lab[order] = got
            return lab
    lo = ijk.min(0)
    shape = ijk.max(0) - lo + 1
    if float(np.prod(shape.astype(np.float64))) <= max(DENSE_MIN_CELLS, DENSE_CELLS_PER_VOXEL * n):
        return _relabel(_dense_labels(ijk - lo, (int(shape[0]), int(shape[1]), int(shape[2]))), keys)
    split = _split_labels(ijk)
    if split is not None:
        return _relabel(split, keys)
    return _sparse_labels(ijk, keys)


#: sets of at least this many voxels are labelled by the map's C++ kernel when it is built
#: (``semantic_map.voxel_components_26``), smaller ones (and all without it) by the paths below
KERNEL_MIN_VOXELS = 64

#: a spread-out set's dense parts: blocks of side ``2^SPLIT_SHIFT`` voxels holding at least
#: :data:`SPLIT_DENSE_VOXELS` of its voxels, at most :data:`SPLIT_MAX_BOXES` groups of them
SPLIT_SHIFT = 4
SPLIT_DENSE_VOXELS = 256
SPLIT_MAX_BOXES = 16


def _split_labels(ijk: np.ndarray) -> np.ndarray | None:
    """Component ids (any numbering) of a spread-out voxel set: each group of touching dense
    blocks gives a box (its blocks' bounding box); the voxels inside a compact box are
    labelled on a dense grid, the others by :func:`_sparse_labels`, and the two are joined by
    the edges from the others to the boxes' voxels (the only edges neither saw). None when
    there is no compact box, too many, or two boxes closer than two voxels."""
    bk = pack_ijk(ijk >> SPLIT_SHIFT)                              # floor division (arithmetic shift)
    ub, cnt = np.unique(bk, return_counts=True)
    db = ub[cnt >= SPLIT_DENSE_VOXELS]
    if not len(db) or len(db) == len(ub):
        return None
    bijk = unpack_keys(db)
    grp = connected_26(bijk)
    if grp.max() + 1 > SPLIT_MAX_BOXES:
        return None
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    for g in range(int(grp.max()) + 1):
        b = bijk[grp == g]
        lo, hi = b.min(0) << SPLIT_SHIFT, ((b.max(0) + 1) << SPLIT_SHIFT) - 1
        if any(((lo - 1 <= h) & (hi + 1 >= q)).all() for q, h in boxes):
            return None                                            # boxes that may touch
        boxes.append((lo, hi))
    lab = np.full(len(ijk), -1, np.int64)
    used = 0
    inside: list[np.ndarray] = []
    for lo, hi in boxes:
        sel = np.flatnonzero(((ijk >= lo) & (ijk <= hi)).all(1))
        shape = hi - lo + 1
        if not len(sel) or float(np.prod(shape.astype(np.float64))) > max(DENSE_MIN_CELLS,
                                                                          DENSE_CELLS_PER_VOXEL * len(sel)):
            continue
        gl = _dense_labels(ijk[sel] - lo, (int(shape[0]), int(shape[1]), int(shape[2]))) - 1   # ndimage: 1..L
        lab[sel] = gl + used
        used += int(gl.max()) + 1
        inside.append(sel)
    if not inside:
        return None
    r = np.flatnonzero(lab < 0)
    if not len(r):
        return lab
    lab[r] = _sparse_labels(ijk[r], pack_ijk(ijk[r])) + used
    d = np.concatenate(inside)
    dk = pack_ijk(ijk[d])
    o = np.argsort(dk, kind="stable")
    dk, dl = dk[o], lab[d][o]
    near = np.zeros(len(r), bool)                                  # the others within a voxel of a box
    for lo, hi in boxes:
        near |= ((ijk[r] >= lo - 1) & (ijk[r] <= hi + 1)).all(1)
    rn = r[near]
    ea, eb = [lab[:0]], [lab[:0]]
    for off in np.concatenate([_HALF_26, -_HALF_26]):
        nb = ijk[rn] + off
        ok = ((nb >= -(1 << 20)) & (nb < (1 << 20))).all(1)
        nk = pack_ijk(nb[ok])
        pos = np.minimum(np.searchsorted(dk, nk), len(dk) - 1)
        hit = dk[pos] == nk
        ea.append(lab[rn[ok][hit]])
        eb.append(dl[pos[hit]])
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_lab = int(lab.max()) + 1
    a, b = np.concatenate(ea), np.concatenate(eb)
    _, joined = connected_components(coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n_lab, n_lab)),
                                     directed=False)
    return joined.astype(np.int64)[lab]


def _sparse_labels(ijk: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """:func:`connected_26` of distinct voxels ``ijk`` (N, 3) with packed ``keys`` by sorted
    searches: edges between key-sorted voxels by one sorted search per half-offset (packing is
    linear: ``key + delta`` is the neighbour's key unless an axis leaves the packable range,
    checked below), components by scipy's graph traversal."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(ijk)
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    biased = ijk[order] + (1 << 20)
    at_edge = bool(((biased == 0) | (biased == (1 << 21) - 1)).any())
    ra, rb = [], []
    for off in _HALF_26:
        nk = sk + ((int(off[0]) << 42) + (int(off[1]) << 21) + int(off[2]))
        pos = np.minimum(np.searchsorted(sk, nk), n - 1)
        hit = np.flatnonzero(sk[pos] == nk)
        if at_edge:                              # a carry / borrow between axes is no neighbour
            hit = hit[(biased[pos[hit]] - biased[hit] == off).all(1)]
        ra.append(hit)
        rb.append(pos[hit])
    ea, eb = np.concatenate(ra), np.concatenate(rb)
    graph = coo_matrix((np.ones(len(ea), np.int8), (ea, eb)), shape=(n, n)).tocsr()
    _, lab_sorted = connected_components(graph, directed=False)
    lab_sorted = lab_sorted.astype(np.int64)
    run_max = np.maximum.accumulate(lab_sorted)
    if run_max[0] == 0 and bool((np.diff(run_max) <= 1).all()):
        # components already numbered in order of first (lowest-key) voxel: no renumbering
        lab = np.empty(n, np.int64)
        lab[order] = lab_sorted
        return lab
    lab = np.empty(n, np.int64)
    lab[order] = lab_sorted
    return _relabel(lab, keys)


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
    """What an update did to an id: ``kind`` in {"new", "grow", "split", "merge", "lost"};
    ``parent`` the split instance (split); ``merged`` the ids absorbed into ``id`` (merge);
    ``voxels`` the instance's new voxel count (grow)."""

    kind: str
    id: int
    target: str
    frame: int
    parent: int | None = None
    merged: list[int] = field(default_factory=list)
    voxels: int | None = None

    def as_dict(self) -> dict:
        d: dict = dict(kind=self.kind, id=int(self.id), target=self.target, frame=int(self.frame))
        if self.parent is not None:
            d["parent"] = int(self.parent)
        if self.merged:
            d["merged"] = [int(i) for i in self.merged]
        if self.voxels is not None:
            d["voxels"] = int(self.voxels)
        return d


def _overlap_pairs(prev: list[Instance], sorted_keys: np.ndarray, sorted_labels: np.ndarray,
                   n_groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sparse voxel overlaps between previous instances and new groups: ``(i, j, count)``
    arrays, one entry per overlapping (previous instance i, group j) pair, sorted by (i, j).
    ``sorted_keys`` the new voxels' keys ascending, ``sorted_labels`` their groups."""
    empty = np.zeros((0,), np.int64)
    if not prev or not len(sorted_keys):
        return empty, empty, empty
    pk = np.concatenate([p.keys for p in prev])
    owner = np.repeat(np.arange(len(prev), dtype=np.int64), [len(p.keys) for p in prev])
    pos = np.minimum(np.searchsorted(sorted_keys, pk), len(sorted_keys) - 1)
    hit = sorted_keys[pos] == pk
    code, cnt = np.unique(owner[hit] * n_groups + sorted_labels[pos[hit]], return_counts=True)
    return code // n_groups, code % n_groups, cnt.astype(np.int64)


def _groups(keys: np.ndarray, labels: np.ndarray, conf: np.ndarray, min_voxels: int) -> tuple:
    """The groups of at least ``min_voxels`` of voxels with strictly ascending packed ``keys``,
    component ``labels`` (0..C-1) and confidences ``conf`` (all in key order), renumbered
    0..G-1 in label order: ``(kept, labels, grouped, counts, index sums, minima, maxima,
    max conf)`` — positions of the kept voxels, their new labels, the kept voxels' keys
    ordered by group then key, and per group (G,) / (G, 3) int64 / (G,) float64. The map's
    C++ kernel when built (``semantic_map.voxel_instance_groups``), else numpy; the same."""
    import semantic_map

    got = semantic_map.voxel_instance_groups(keys, labels, conf, min_voxels) if len(keys) >= KERNEL_MIN_VOXELS else None
    if got is not None:
        return got
    sizes = np.bincount(labels) if len(labels) else np.zeros((0,), np.int64)
    keep = np.flatnonzero(sizes >= min_voxels)
    remap = np.full(len(sizes), -1, np.int64)
    remap[keep] = np.arange(len(keep))
    sel = np.flatnonzero(remap[labels] >= 0) if len(labels) else np.zeros((0,), np.int64)
    kl = remap[labels[sel]]
    by_group = np.argsort(kl, kind="stable")          # grouped, keys ascending within a group
    counts = sizes[keep].astype(np.int64)
    grouped = keys[sel][by_group]
    if not len(counts):
        z = np.zeros((0, 3), np.int64)
        return sel, kl, grouped, counts, z, z, z, np.zeros((0,), np.float64)
    starts = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    gijk = unpack_keys(grouped)
    return (sel, kl, grouped, counts, np.add.reduceat(gijk, starts, axis=0), np.minimum.reduceat(gijk, starts, axis=0),
            np.maximum.reduceat(gijk, starts, axis=0), np.maximum.reduceat(conf[sel][by_group], starts))


class InstanceTracker:
    """Stable instance ids per target across map updates (see the module docstring).

    ``vox``: voxel size (m). ``min_voxels``: groups smaller than this are ignored (noise).
    ``grace``: updates a missing instance stays matchable before it is ``lost``.
    """

    def __init__(self, vox: float, min_voxels: int = 1, id_source: Callable[[int], int] | None = None,
                 grace: int = 0):
        """``id_source(n)``: where new ids come from — it issues ``n`` consecutive ids and
        returns the first (one counter shared by several trackers, kept across restarts),
        default this tracker's own counter from 1."""
        if vox <= 0:
            raise ValueError(f"vox must be > 0, got {vox}")
        self.vox = float(vox)
        self.min_voxels = max(1, int(min_voxels))
        self.grace = max(0, int(grace))
        self.next_id = 1
        self._id_source = id_source
        self.instances: dict[str, list[Instance]] = {}
        self.missing: dict[str, list[tuple[Instance, int]]] = {}   # target -> (instance, updates unseen)
        self.updates = 0
        self.inputs = 0                  # +1 per update, repeat or load_state: the input as last fed
        self.version = 0                 # +1 per update or load_state: the instances as they are
        # target -> (keys, their ascending order, labels in that order) last seen
        self._components: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._last: dict[str, tuple[np.ndarray, np.ndarray, int]] = {}    # target -> (keys, conf, frame) last seen

    def _new_ids(self, n: int) -> int:
        """The first of ``n`` consecutive new ids."""
        if self._id_source is not None:
            return self._id_source(n)
        i = self.next_id
        self.next_id += n
        return i

    def update(self, target: str, ijk: np.ndarray, confidence: np.ndarray, frame: int,
               keys: np.ndarray | None = None) -> list[InstanceEvent]:
        """Track ``target``'s voxels above threshold at map frame ``frame``: ``ijk`` (N, 3)
        distinct voxel indices, ``confidence`` (N,) in [0, 1]; or ``ijk=None`` and their
        :func:`pack_ijk` ``keys`` (N,) (the same update). Returns the events."""
        if keys is None:
            ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
            keys = pack_ijk(ijk)
        else:
            keys = np.asarray(keys, np.int64).reshape(-1)
        conf = np.asarray(confidence, np.float64).reshape(-1)
        if len(conf) != len(keys):
            raise ValueError(f"{len(keys)} voxels but {len(conf)} confidences")
        frame = int(frame)
        self.updates += 1
        self.inputs += 1
        self.version += 1
        same = self._last.get(target)
        if (same is not None and same[2] == frame and target in self.instances and np.array_equal(same[0], keys)
                and np.array_equal(same[1], conf)):
            # the same input as the last update (the same map version searched again): it would
            # rebuild the same instances (each its own heir, same frame) with no events
            return []
        self._last[target] = (keys, conf.copy(), frame)
        last = self._components.get(target)
        if last is not None and np.array_equal(last[0], keys):
            order, labels = last[1], last[2]       # same voxels as the last update (same map version)
            skeys = keys[order]
        else:
            order, skeys = key_order(keys)              # the one sort: labels come in key order
            labels = labels_of_sorted(skeys)
            self._components[target] = (keys, order, labels)
        sel, labels, gkeys, counts, isum, imin, imax, cmax = _groups(skeys, labels, conf[order], self.min_voxels)
        cur = self.instances.get(target, [])
        gone = self.missing.get(target, [])
        prev = cur + [g for g, _ in gone]            # missing instances stay matchable (grace)
        skeys = skeys[sel] if prev else skeys[:0]         # kept voxels, keys ascending (for the overlaps)
        n_groups = len(counts)
        bounds = np.zeros(n_groups + 1, np.int64)
        np.cumsum(counts, out=bounds[1:])
        pi, pj, pc = _overlap_pairs(prev, skeys, labels, n_groups)
        # each previous instance goes to its largest overlapping group (ties: lowest group label)
        goes_to = np.full(len(prev), -1, np.int64)
        if len(pi):
            o = np.lexsort((pj, -counts[pj], pi))
            first = np.flatnonzero(np.r_[True, pi[o][1:] != pi[o][:-1]])
            goes_to[pi[o][first]] = pj[o][first]
        # a group without heirs splits from the previous instance overlapping it most (ties: lowest i)
        parent_of = np.full(n_groups, -1, np.int64)
        if len(pi):
            o = np.lexsort((pi, -pc, pj))
            first = np.flatnonzero(np.r_[True, pj[o][1:] != pj[o][:-1]])
            parent_of[pj[o][first]] = pi[o][first]
        heirs_of: dict[int, list[Instance]] = {}
        for i in np.flatnonzero(goes_to >= 0):
            heirs_of.setdefault(int(goes_to[i]), []).append(prev[i])
        if n_groups:
            centroid = (isum.astype(np.float64) / counts[:, None] + 0.5) * self.vox
            bmin = voxel_center(imin, self.vox)
            bmax = voxel_center(imax, self.vox)
        # ids of the groups without heirs, in group order, taken as one block
        fresh = np.ones(n_groups, bool)
        fresh[list(heirs_of)] = False
        first_id = self._new_ids(int(fresh.sum()))
        new_ids = np.cumsum(fresh) - 1 + first_id
        events: list[InstanceEvent] = []
        out: list[Instance] = []
        conf_l, count_l, bound_l = cmax.tolist(), counts.tolist(), bounds.tolist()
        for j in range(n_groups):
            inst = Instance(0, target, centroid[j], bmin[j], bmax[j], conf_l[j], count_l[j], 1, frame,
                            frame, gkeys[bound_l[j]:bound_l[j + 1]])
            heirs = heirs_of.get(j)
            if heirs:
                heirs.sort(key=lambda p: (p.first_seen, p.id))
                old = heirs[0]
                inst.id, inst.first_seen = old.id, old.first_seen
                inst.observations = old.observations + (1 if frame != old.last_seen else 0)
                if len(heirs) > 1:
                    events.append(InstanceEvent("merge", old.id, target, frame, merged=[h.id for h in heirs[1:]]))
                elif inst.voxels > old.voxels:
                    events.append(InstanceEvent("grow", old.id, target, frame, voxels=inst.voxels))
            else:
                inst.id = int(new_ids[j])
                if parent_of[j] >= 0:
                    events.append(InstanceEvent("split", inst.id, target, frame, parent=prev[parent_of[j]].id))
                else:
                    events.append(InstanceEvent("new", inst.id, target, frame))
            out.append(inst)
        seen = np.zeros(len(prev), bool)
        seen[pi] = True
        unseen = [(prev[i], 1 if i < len(cur) else gone[i - len(cur)][1] + 1) for i in np.flatnonzero(~seen)]
        events += [InstanceEvent("lost", p.id, target, frame) for p, n in unseen if n > self.grace]
        out.sort(key=lambda x: x.id)
        self.instances[target] = out
        self.missing[target] = [(p, n) for p, n in unseen if n <= self.grace]
        return events

    def repeat(self) -> list[InstanceEvent]:
        """An update with the same input as the last one (the caller knows it is): it changes
        nothing but the update count and has no events, as :meth:`update` would find."""
        self.updates += 1
        self.inputs += 1
        return []

    def state(self) -> tuple[list[dict], np.ndarray]:
        """``(instances, keys)``: every current and missing instance as
        :meth:`Instance.as_dict` plus ``missed`` (updates unseen, 0 = current) and ``n_keys``,
        and their voxel keys concatenated in that order (int64): what :meth:`load_state`
        restores (the caches of the last input are not kept)."""
        rows: list[dict] = []
        keys: list[np.ndarray] = []
        for target in sorted(set(self.instances) | set(self.missing)):
            both = [(i, 0) for i in self.instances.get(target, [])] + list(self.missing.get(target, []))
            for inst, missed in both:
                rows.append(dict(inst.as_dict(), missed=int(missed), n_keys=len(inst.keys)))
                keys.append(np.asarray(inst.keys, np.int64))
        return rows, (np.concatenate(keys) if keys else np.zeros((0,), np.int64))

    def load_state(self, rows: list[dict], keys: np.ndarray) -> None:
        """Put back what :meth:`state` returned (raises ValueError/KeyError/TypeError on
        malformed data, leaving the tracker as it was)."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        if sum(int(r["n_keys"]) for r in rows) != len(keys):
            raise ValueError(f"instance rows name {sum(int(r['n_keys']) for r in rows)} voxel keys, {len(keys)} given")
        instances: dict[str, list[Instance]] = {}
        missing: dict[str, list[tuple[Instance, int]]] = {}
        at = 0
        for r in rows:
            n = int(r["n_keys"])
            inst = Instance(int(r["id"]), str(r["target"]), np.asarray(r["centroid"], np.float64),
                            np.asarray(r["box_min"], np.float64), np.asarray(r["box_max"], np.float64),
                            float(r["confidence"]), int(r["voxels"]), int(r["observations"]), int(r["first_seen"]),
                            int(r["last_seen"]), np.sort(keys[at:at + n]))
            at += n
            if int(r["missed"]) == 0:
                instances.setdefault(inst.target, []).append(inst)
            else:
                missing.setdefault(inst.target, []).append((inst, int(r["missed"])))
        for v in instances.values():
            v.sort(key=lambda x: x.id)
        self.instances, self.missing = instances, missing
        self.inputs += 1
        self.version += 1
        self._components.clear()
        self._last.clear()

    def current(self, target: str | None = None) -> list[Instance]:
        """The live instances (of ``target``, else of every target), by id."""
        if target is not None:
            return list(self.instances.get(target, []))
        return sorted((i for v in self.instances.values() for i in v), key=lambda x: x.id)


@dataclass
class InstanceViews:
    """Instances as one request sees them, as arrays (row ``k`` describes ``instances[k]``):
    ``centroid``, ``box_min`` / ``box_max`` (voxel centres, m, float64, (K, 3)),
    ``confidence`` (K,) the max voxel confidence and ``voxels`` (K,) the count of the
    instance's voxels the request sees. :meth:`as_dicts` gives the reply's rows."""

    instances: list[Instance]
    centroid: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    confidence: np.ndarray
    voxels: np.ndarray

    def __len__(self) -> int:
        return len(self.instances)

    def as_dict(self, k: int) -> dict:
        """Row ``k`` as :meth:`Instance.as_dict` with the request's figures."""
        d = self.instances[k].as_dict()
        d.update(centroid=[float(v) for v in self.centroid[k]], box_min=[float(v) for v in self.box_min[k]],
                 box_max=[float(v) for v in self.box_max[k]], confidence=float(self.confidence[k]),
                 voxels=int(self.voxels[k]))
        return d


def tracked_views(instances: list[Instance]) -> InstanceViews:
    """The instances with their own figures: what a request sees when its voxels are exactly
    those the tracker was fed (the same probabilities and threshold as the identity's)."""
    k = len(instances)
    return InstanceViews(list(instances),
                         np.asarray([i.centroid for i in instances], np.float64).reshape(k, 3),
                         np.asarray([i.box_min for i in instances], np.float64).reshape(k, 3),
                         np.asarray([i.box_max for i in instances], np.float64).reshape(k, 3),
                         np.asarray([i.confidence for i in instances], np.float64).reshape(k),
                         np.asarray([i.voxels for i in instances], np.int64).reshape(k))


def request_views(instances: list[Instance], rk: np.ndarray, rijk: np.ndarray, rconf: np.ndarray, vox: float,
                  min_voxels: int) -> InstanceViews:
    """Each instance seen through a request's voxels: ``rk`` their packed keys ascending,
    ``rijk`` (M, 3) / ``rconf`` (M,) in the same order. An instance keeps the voxels of its
    own (``Instance.keys``) that are among them; it is left out with fewer than
    ``max(1, min_voxels)``. One sorted search for all instances' keys, per-instance
    reductions over the hits."""
    k = len(instances)
    lens = np.asarray([len(i.keys) for i in instances], np.int64).reshape(k)
    if not len(rk) or not lens.sum():
        return tracked_views([])
    allk = np.concatenate([i.keys for i in instances])
    owner = np.repeat(np.arange(k, dtype=np.int64), lens)
    pos = np.minimum(np.searchsorted(rk, allk), len(rk) - 1)
    hit = rk[pos] == allk
    owner, pos = owner[hit], pos[hit]                  # grouped by instance (owner ascending)
    cnt = np.bincount(owner, minlength=k)
    seen = np.flatnonzero(cnt)
    starts = np.r_[0, np.cumsum(cnt[seen])[:-1]].astype(np.int64)
    ijk = rijk[pos]
    isum = np.add.reduceat(ijk, starts, axis=0) if len(seen) else np.zeros((0, 3), np.int64)
    lo = np.minimum.reduceat(ijk, starts, axis=0) if len(seen) else np.zeros((0, 3), np.int64)
    hi = np.maximum.reduceat(ijk, starts, axis=0) if len(seen) else np.zeros((0, 3), np.int64)
    cmax = np.maximum.reduceat(rconf[pos], starts) if len(seen) else np.zeros((0,), np.float64)
    ok = cnt[seen] >= max(1, int(min_voxels))
    n = cnt[seen][ok]
    return InstanceViews([instances[int(i)] for i in seen[ok]],
                         (isum[ok].astype(np.float64) / n[:, None] + 0.5) * vox,
                         voxel_center(lo[ok], vox), voxel_center(hi[ok], vox),
                         np.asarray(cmax[ok], np.float64), n.astype(np.int64))
