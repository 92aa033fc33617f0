"""Search answering for planners, free of Zenoh (the queryable is :mod:`mapper.search_server`).

A search scores every voxel and ray of the query copy
(:class:`semantic_map.query_copy.QueryCopy`) with the softmax probability of each
target over targets + background phrases at ``search.temperature`` (the paper's querying;
text embedded as :func:`mapper.query_answer.embed_text` does), then:

* ``found``: objects with stable ids (docs/identity.md): one identity tracker per target
  (:class:`planning.instances.InstanceTracker`, :func:`identity_key`) follows the voxels
  whose probability over the target + the configured background is above
  ``search.identity_threshold``, whatever the request; the request's threshold, background
  and other targets then choose which of each object's voxels it sees (:func:`_request_view`).
  Filtered to the request's area / z band, best first: confidence (to 3 decimals: softmax at
  temperature 100 saturates), then size;
* ``look_next``: :func:`planning.look_next.look_next` on the map's occupancy and frontiers
  (read under the map lock by the caller through ``read_map``), with each ray's ``ray_z``
  (:func:`planning.look_next.ray_outlier_z` of :func:`distinct_cosines`: how far its
  cosine to what sets a target apart from the other phrases stands out among all the map's
  rays — evidence for far targets whose probabilities are ~0; a ray toward a similar class,
  a radio tower for a water tower, reads ~0 where its raw cosine would stand out; 0 within
  ``search.ray_cosine_resolution`` of the median, the features' float16 rounding on the wire);
* ``beyond``: best rays per target, triangulated estimates
  (:func:`planning.beyond.triangulate`) and the search volume of the best rays' cones.

World frame, metres, z up; timings in milliseconds.
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import logging
import threading
import time
import weakref
from collections import OrderedDict
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from common.cones import cone_union_volume
from common.conventions import voxel_index
from common.search_messages import SearchReply, SearchRequest
from planning.beyond import triangulate
from planning.instances import (
    InstanceTracker,
    InstanceViews,
    key_order,
    pack_ijk,
    request_views,
    tracked_views,
    unpack_keys,
)
from planning.look_next import Goal, LookNextCache, look_next, points_in_polygon, ray_outlier_z
from semantic_map import kernels
from semantic_map.query import PreparedRows, score_rows, softmax_share
from semantic_map.query_copy import PARALLEL_MIN_SCORES, one_thread

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from mapper.search_config import SearchSection
    from mapper.service_config import MapperConfig, QuerySection
    from semantic_map.map import RayFrontsMap
    from semantic_map.query_copy import QueryCopy

log = logging.getLogger("rayfronts.mapper")

#: look-next's target-free work per map (:class:`planning.look_next.LookNextCache`), used
#: under the map lock (``read_map``), so by one search at a time
_LOOK_NEXT: "weakref.WeakKeyDictionary[object, LookNextCache]" = weakref.WeakKeyDictionary()


def look_next_cache(m: RayFrontsMap) -> LookNextCache:
    """The look-next cache of map ``m`` (created on first use)."""
    c = _LOOK_NEXT.get(m)
    if c is None:
        c = _LOOK_NEXT[m] = LookNextCache()
    return c


#: requests' scores kept per query copy at its current revision (:class:`_Scored`)
SCORED_ENTRIES = 8
#: beyond parts kept per :class:`_Scored` (areas and settings; the oldest out first)
BEYOND_AREAS = 16
#: search volumes of the last best-ray sets (:func:`_search_volume`)
VOLUME_ENTRIES = 32


class _Scored:
    """What a search computes from the query copy for one set of phrases, kept while the copy
    stays at one revision (several robots' standing searches, a planner's repeated search):
    voxel probabilities ``vs``, ray scores ``rs`` / cosines ``rcos``, identity
    probabilities ``ident``, per target what the identity tracker was last fed from them
    (``fed``: tracker, key, token, threshold, its input count after the feed) and the
    tracker's instances as seen then (``views``), and the ``beyond`` part per area. Each is what a fresh
    computation at that revision gives (the same code on the same rows)."""

    def __init__(self, vs: np.ndarray, rs: np.ndarray, rcos: np.ndarray) -> None:
        self.vs, self.rs, self.rcos = vs, rs, rcos
        self.ident: np.ndarray | None = None
        self.fed: dict[int, tuple] = {}
        self.views: dict[int, tuple] = {}            # target -> (tracker, its version, InstanceViews)
        self.beyond: dict[tuple, dict] = {}           # the request's area and settings -> beyond


class _ScoredStore:
    """:class:`_Scored` entries of one query copy, all of one revision (at most
    :data:`SCORED_ENTRIES`, least recently used first out)."""

    def __init__(self) -> None:
        self.revision = -1
        self.entries: OrderedDict[tuple, _Scored] = OrderedDict()
        self.hits = 0                        # requests answered from a kept entry (for tests)

    def get(self, revision: int, key: tuple) -> _Scored | None:
        if revision != self.revision:
            self.revision = revision
            self.entries.clear()
        e = self.entries.get(key)
        if e is not None:
            self.entries.move_to_end(key)
            self.hits += 1
        return e

    def put(self, key: tuple, e: _Scored) -> None:
        self.entries[key] = e
        while len(self.entries) > SCORED_ENTRIES:
            self.entries.popitem(last=False)


_SCORED: "weakref.WeakKeyDictionary[object, _ScoredStore]" = weakref.WeakKeyDictionary()
_SCORED_LOCK = threading.Lock()


def _scored_key(snap, fs, q_all: torch.Tensor, req: SearchRequest, phrases: list[str], n_bg: int,
                cfg) -> tuple | None:
    """The key of a request's :class:`_Scored` (None: the copy has no revision to hold it to)."""
    if getattr(snap, "revision", None) is None:
        return None
    scfg = cfg.search
    qb = q_all.detach().to(torch.float32).cpu().contiguous().numpy()
    return (fs.id, str(cfg.device), float(scfg.temperature), hashlib.sha1(qb.tobytes()).hexdigest(), qb.shape,
            tuple(req.targets), req.embeddings is None, tuple(phrases), int(n_bg), tuple(scfg.background))


def _scored(snap, key: tuple | None, compute: Callable[[], _Scored]) -> _Scored:
    """The request's scores at the copy's revision: kept, else computed and kept."""
    if key is None:
        return compute()
    with _SCORED_LOCK:
        store = _SCORED.get(snap)
        if store is None:
            store = _SCORED[snap] = _ScoredStore()
        e = store.get(int(snap.revision), key)
    if e is None:
        e = compute()
        with _SCORED_LOCK:
            if store.revision == int(snap.revision):
                store.put(key, e)
    return e


_VOLUMES: OrderedDict[tuple, float] = OrderedDict()


def _search_volume(o: np.ndarray, d: np.ndarray, half_angle: float, qcfg) -> float:
    """:func:`common.cones.cone_union_volume` of the best rays' cones (its per-cone step in
    C++ when built), kept for the last :data:`VOLUME_ENTRIES` inputs (the same best rays over
    several searches)."""
    key = (hashlib.sha1(np.ascontiguousarray(o, np.float64).tobytes() + np.ascontiguousarray(d, np.float64).tobytes())
           .hexdigest(), o.shape, float(half_angle), float(qcfg.search_range_m), float(qcfg.search_cell_m),
           int(qcfg.search_samples))
    with _SCORED_LOCK:
        v = _VOLUMES.get(key) if VOLUME_ENTRIES > 0 else None
        if v is not None:
            _VOLUMES.move_to_end(key)
            return v
    v = float(cone_union_volume(o, d, half_angle, qcfg.search_range_m, qcfg.search_cell_m,
                                max_cells=qcfg.search_samples, weighted_union=kernels.cone_weighted_union()))
    with _SCORED_LOCK:
        _VOLUMES[key] = v
        while len(_VOLUMES) > VOLUME_ENTRIES:
            _VOLUMES.popitem(last=False)
    return v


class TrackerStore:
    """Identity trackers, one per target (:func:`identity_key`; LRU, at most ``max_trackers``).
    Their ids come from one counter (``next_id``): ids are unique over all targets and never
    reused after a restart, a crash included.

    With a ``reserve`` callback, ids are handed out from durably reserved blocks: before an
    id at or above ``reserved_below`` is returned, ``reserve(n)`` is called with the new
    ceiling ``n`` (``id_block`` ids beyond the last id issued) and must persist it; a restart continues from the
    persisted ceiling (:class:`mapper.snapshot_store.SnapshotStore`), so an id sent after the
    newest snapshot is not issued again. A failing ``reserve`` is logged and counted
    (``reserve_errors``) and the id is still issued: an answer is not refused for a disk error.

    ``mutex`` is held while trackers change (:func:`answer_search`) and while they are copied
    for a snapshot (:meth:`state`), so a snapshot holds whole updates.
    """

    def __init__(self, max_trackers: int = 32, reserve: Callable[[int], None] | None = None,
                 id_block: int = 256):
        self.max = max(1, int(max_trackers))
        self._t: OrderedDict = OrderedDict()
        self.next_id = 1
        self.reserve = reserve
        self.id_block = max(1, int(id_block))
        self.reserved_below = 1          # ids < this are covered by the last successful reserve()
        self.reserve_errors = 0
        self._lock = threading.Lock()
        self.mutex = threading.RLock()
        self._events: dict[tuple, tuple[tuple, list[dict]]] = {}   # key -> (update token, its events)
        self.generation = 0              # +1 per tracker update with a new input (a snapshot is due)

    def new_id(self) -> int:
        """The next instance id (thread-safe)."""
        return self.new_ids(1)

    def new_ids(self, n: int) -> int:
        """Issue ``n`` consecutive instance ids and return the first (thread-safe; ``n`` = 0:
        the next id, none issued)."""
        with self._lock:
            i = self.next_id
            if n > 0 and self.reserve is not None and i + n - 1 >= self.reserved_below:
                ceiling = i + n - 1 + self.id_block
                try:
                    self.reserve(ceiling)
                    self.reserved_below = ceiling
                except Exception as e:   # the ids are still issued; the next call tries again
                    self.reserve_errors += 1
                    log.error("could not reserve instance ids below %d: %s", ceiling, e)
            self.next_id += max(0, int(n))
            return i

    def continue_from(self, next_id: int) -> None:
        """Issue no id below ``next_id`` (a restored counter or reservation)."""
        with self._lock:
            self.next_id = max(self.next_id, int(next_id))

    def get(self, key: tuple, vox: float, min_voxels: int, grace: int = 0) -> InstanceTracker:
        """The tracker of ``key`` (created on first use; a map with another voxel size resets it)."""
        t = self._t.get(key)
        if t is None or t.vox != float(vox):
            t = InstanceTracker(vox, min_voxels, id_source=self.new_ids, grace=grace)
            self._t[key] = t
            self._events.pop(key, None)
        t.min_voxels, t.grace = max(1, int(min_voxels)), max(0, int(grace))
        self._t.move_to_end(key)
        while len(self._t) > self.max:
            old, _ = self._t.popitem(last=False)
            self._events.pop(old, None)
        return t

    def update(self, key: tuple, ijk: np.ndarray | None, conf: np.ndarray, frame: int, token: tuple,
               keys: np.ndarray | None = None) -> list[dict]:
        """Update ``key``'s tracker (:meth:`get` first) with its identity voxels (``ijk``, or
        their packed ``keys``: :meth:`planning.instances.InstanceTracker.update`); returns the
        events of the tracker's last update: a repeat at the same ``token`` (map version and
        frame) returns the events of the update it repeats, so every search of one map
        version reports what that version changed."""
        t = self._t[key]
        return self._record(key, [e.as_dict() for e in t.update(str(key[1]), ijk, conf, frame, keys=keys)], token)

    def repeat(self, key: tuple, token: tuple) -> list[dict]:
        """:meth:`update` with the same voxels, confidences and frame as the tracker's last
        update (known to the caller): what it returns, without comparing the input again."""
        return self._record(key, [e.as_dict() for e in self._t[key].repeat()], token)

    def _record(self, key: tuple, ev: list[dict], token: tuple) -> list[dict]:
        last = self._events.get(key)
        if last is None or last[0] != token:
            self.generation += 1
        if not ev and last is not None and last[0] == token:
            return list(last[1])
        self._events[key] = (token, ev)
        return ev

    def state(self) -> tuple[dict, np.ndarray]:
        """``(description, voxel keys)`` of every tracker (JSON-able; the keys concatenated in
        the description's order): what :meth:`load_state` restores."""
        with self.mutex:
            trackers, keys = [], []
            for key, t in self._t.items():
                rows, k = t.state()
                trackers.append({"key": list(key), "vox": t.vox, "min_voxels": t.min_voxels, "grace": t.grace,
                                 "updates": t.updates, "instances": rows})
                keys.append(k)
            return ({"next_id": self.next_id, "trackers": trackers},
                    np.concatenate(keys) if keys else np.zeros((0,), np.int64))

    def load_state(self, desc: dict, keys: np.ndarray) -> None:
        """Restore :meth:`state`'s trackers (raises ValueError/KeyError/TypeError on malformed
        data; then nothing is restored) and continue ids above the saved counter."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        restored: OrderedDict = OrderedDict()
        at = 0
        for d in desc["trackers"]:
            t = InstanceTracker(float(d["vox"]), int(d["min_voxels"]), id_source=self.new_ids, grace=int(d["grace"]))
            n = sum(int(r["n_keys"]) for r in d["instances"])
            t.load_state(d["instances"], keys[at:at + n])
            t.updates = int(d["updates"])
            at += n
            restored[(str(d["key"][0]), str(d["key"][1]))] = t
        if at != len(keys):
            raise ValueError(f"the trackers name {at} voxel keys, {len(keys)} saved")
        with self.mutex:
            self._t = restored
            self._events.clear()
        self.continue_from(int(desc.get("next_id", 1)))

    def __len__(self) -> int:
        return len(self._t)


def identity_key(req: SearchRequest, i: int) -> tuple[str, str]:
    """Identity of the request's ``i``-th target (its tracker): ``("text", phrase)``, or
    ``("embedding", sha1 of the float32 row)`` for a request's own embeddings. The request's
    background, other targets and threshold are not part of it."""
    if req.embeddings is None:
        return ("text", req.targets[i])
    row = np.ascontiguousarray(np.asarray(req.embeddings, np.float32).reshape(len(req.targets), -1)[i])
    return ("embedding", hashlib.sha1(row.tobytes()).hexdigest())


def embed_phrases(fs: FeatureSpace, req: SearchRequest, background: list[str], device: str | torch.device,
                  model_dir: str, templates: str) -> torch.Tensor:
    """(T + B, lang_dim) embeddings of the targets (or the request's embeddings) and background."""
    from mapper.query_answer import embed_text

    rows = ([torch.as_tensor(req.embeddings, dtype=torch.float32)] if req.embeddings is not None
            else [embed_text(fs, t, device, model_dir, templates) for t in req.targets])
    rows += [embed_text(fs, b, device, model_dir, templates) for b in background]
    q = torch.cat([r.reshape(-1, r.shape[-1]) for r in rows]).to(torch.float32)
    if q.shape[1] != fs.lang_dim:
        from common.messages import MessageError

        raise MessageError(f"embeddings have {q.shape[1]} dims, the map's language space has {fs.lang_dim}")
    return q


def _probabilities(prep: PreparedRows, q: torch.Tensor, n_targets: int, temperature: float) -> np.ndarray:
    """(T, N) softmax probabilities of the targets over targets + background."""
    if len(prep) == 0:
        return np.zeros((n_targets, 0), np.float32)
    return _target_softmax(score_rows(prep, q, None), n_targets, temperature)


def _target_softmax(sim: torch.Tensor, n_targets: int, temperature: float) -> np.ndarray:
    """(T, N) the first ``n_targets`` rows of the softmax over all rows of ``temperature · sim``."""
    p = torch.softmax(temperature * sim, dim=0) if sim.numel() else sim
    return p[:n_targets].detach().cpu().numpy().astype(np.float32, copy=False)


def _ray_scores(prep: PreparedRows, q: torch.Tensor, n_targets: int, temperature: float, nearest: int = 0,
                evidence: str = "distinct") -> tuple[np.ndarray, np.ndarray]:
    """(T, N) softmax probabilities of the targets over targets + background, and (T, N)
    the rows' ray evidence: :func:`distinct_cosines` or (``evidence="margin"``)
    :func:`margin_cosines` against ``nearest`` phrases (one similarity pass for all)."""
    if len(prep) == 0:
        return np.zeros((n_targets, 0), np.float32), np.zeros((n_targets, 0), np.float32)
    sim = score_rows(prep, q, None)
    s = sim.detach().cpu().numpy()
    evidence_of = margin_cosines if evidence == "margin" else distinct_cosines
    ev = evidence_of(s, q, n_targets, nearest)
    return _target_softmax(sim, n_targets, temperature), ev


def _nearest_phrases(qn: np.ndarray, t: int, nearest: int) -> np.ndarray:
    """Indices of the phrases other than ``t`` (rows of unit embeddings ``qn``), only the
    ``nearest`` closest to it when ``nearest`` > 0 (cosine; ties by order), ascending."""
    rest = np.r_[0:t, t + 1:len(qn)]
    if 0 < nearest < len(rest):
        rest = np.sort(rest[np.argsort(-(qn[rest] @ qn[t]), kind="stable")[:nearest]])
    return rest


def margin_cosines(sim: np.ndarray, q: torch.Tensor, n_targets: int, nearest: int = 0) -> np.ndarray:
    """(T, N): each row's cosine to each target less its best cosine to the target's
    ``nearest`` closest other phrases (0: all others), from the rows' cosines ``sim`` (Q, N)
    to the ``Q`` phrases ``q``: the target's margin over what resembles it. A ray toward a
    similar class (a radio tower for a water tower) reads below a ray of sky — the similar
    phrase ("tower") gains on it more than the target does — one holding a share of the target
    reads above; the raw cosine where there is no other phrase."""
    s = np.asarray(sim, np.float64)
    qn = torch.nn.functional.normalize(q.to(torch.float64), dim=1).cpu().numpy()
    out = np.zeros((n_targets, s.shape[1]), np.float32)
    for t in range(n_targets):
        rest = _nearest_phrases(qn, t, nearest)
        out[t] = s[t] - s[rest].max(0) if len(rest) else s[t]
    return out


def distinct_cosines(sim: np.ndarray, q: torch.Tensor, n_targets: int, nearest: int = 0) -> np.ndarray:
    """(T, N): each row's cosine to what sets each target apart from the other phrases — the
    part ``u`` of the target's unit embedding that no combination of the other phrases'
    unit embeddings explains (least squares), from the rows' cosines ``sim`` (Q, N) to the
    ``Q`` phrases ``q``: ``(cos_t − Σ_j a_j cos_j) / |u|``. A ray toward a class similar to
    the target (a radio tower for a water tower) reads ~0, one that holds a share of the
    target reads that share; the raw cosine where there is no other phrase, 0 where the
    others explain the target wholly. ``nearest`` > 0: only the target's ``nearest`` closest
    other phrases (cosine of the embeddings; ties by order) explain it — a vocabulary of a
    hundred phrases spans the whole feature space and would explain every target."""
    s = np.asarray(sim, np.float64)
    qn = torch.nn.functional.normalize(q.to(torch.float64), dim=1).cpu().numpy()
    out = np.zeros((n_targets, s.shape[1]), np.float32)
    for t in range(n_targets):
        rest = _nearest_phrases(qn, t, nearest)
        if not len(rest):
            out[t] = s[t]
            continue
        a = np.linalg.lstsq(qn[rest] @ qn[rest].T, qn[rest] @ qn[t], rcond=1e-9)[0]
        u2 = 1.0 - float(qn[t] @ qn[rest].T @ a)
        if u2 > 1e-9:
            out[t] = (s[t] - a @ s[rest]) / np.sqrt(u2)
    return out


def _voxel_probabilities(snap: QueryCopy, fs: FeatureSpace, prep: PreparedRows, q: torch.Tensor, n_targets: int,
                         temperature: float, device: str | torch.device) -> np.ndarray:
    """:func:`_probabilities` of the voxels, with the background's per-voxel log-sum-exp taken
    from the snapshot's cache (:meth:`QueryCopy.phrase_logsumexp`, kept per map version
    and updated for changed rows): only the targets are scored per search. Equal to the full
    softmax up to float32 rounding (``semantic_map.query.softmax_share``)."""
    lse_of = getattr(snap, "phrase_logsumexp", None)
    if len(prep) == 0 or n_targets >= q.shape[0] or lse_of is None:
        return _probabilities(prep, q, n_targets, temperature)
    lse = lse_of(fs, q[n_targets:], temperature, device)
    if lse is None:
        return _probabilities(prep, q, n_targets, temperature)
    s = score_rows(prep, q[:n_targets])
    with (one_thread() if s.numel() < PARALLEL_MIN_SCORES else contextlib.nullcontext()):
        p = softmax_share(s, lse, temperature)
    return p.detach().cpu().numpy().astype(np.float32, copy=False)


def _voxel_ijk(snap: QueryCopy, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 3) int64 voxel indices of snapshot rows (from the keys when the snapshot
    gives them, else ``floor(centre / vox)``)."""
    if not len(rows):
        return np.zeros((0, 3), np.int64)
    if hasattr(snap, "voxel_ijk"):
        return snap.voxel_ijk(rows)
    return voxel_index(snap.voxel_xyz(rows).astype(np.float64), snap.vox)


def _voxel_keys(snap: QueryCopy, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) :func:`planning.instances.pack_ijk` keys of snapshot rows (the snapshot's
    own keys when it gives them)."""
    if len(rows) and hasattr(snap, "voxel_keys"):
        return snap.voxel_keys(rows)
    return pack_ijk(_voxel_ijk(snap, rows))


def _in_area(xyz: np.ndarray, poly, z_band) -> np.ndarray:
    ok = np.ones(len(xyz), bool)
    if poly is not None and len(xyz):
        ok &= points_in_polygon(xyz[:, :2], poly)
    if z_band is not None and len(xyz):
        ok &= (xyz[:, 2] >= z_band[0]) & (xyz[:, 2] <= z_band[1])
    return ok


def _identity_probabilities(snap: QueryCopy, fs: FeatureSpace, prep: PreparedRows, q: torch.Tensor,
                            targets: list[str], text: bool, phrases: list[str], canonical: list[str],
                            temperature: float, device: str | torch.device,
                            request: tuple[np.ndarray, int] | None = None) -> np.ndarray:
    """(T, N) each target's probability over itself + the canonical background (``canonical``,
    the configured ``search.background`` less the target's own phrase), whatever the request's
    background and other targets: the voxels an object's identity is tracked on. ``q`` holds
    the targets' rows then ``phrases``' (which include every canonical phrase). ``request``:
    the request's probabilities and background length, reused where they are the same thing
    (one target softmaxed against exactly the canonical phrases)."""
    T = len(targets)
    out = np.zeros((T, len(prep)), np.float32)
    if len(prep) == 0:
        return out
    groups: dict[tuple, list[int]] = {}
    for t in range(T):
        rows = tuple(T + j for j, b in enumerate(phrases) if b in canonical and not (text and b == targets[t]))
        groups.setdefault(rows, []).append(t)
    if request is not None and T == 1 and list(groups) == [tuple(range(T, T + request[1]))]:
        return request[0]
    lse_of = getattr(snap, "phrase_logsumexp", None)
    for rows, ts in groups.items():
        lse = lse_of(fs, q[list(rows)], temperature, device) if (lse_of is not None and rows) else None
        if lse is not None:
            s = score_rows(prep, q[ts])
            with (one_thread() if s.numel() < PARALLEL_MIN_SCORES else contextlib.nullcontext()):
                for k, t in enumerate(ts):
                    out[t] = softmax_share(s[k:k + 1], lse, temperature)[0].detach().cpu().numpy()
            continue
        sim = score_rows(prep, q[list(ts) + list(rows)], None)
        for k, t in enumerate(ts):
            out[t] = _target_softmax(torch.cat([sim[k:k + 1], sim[len(ts):]]), 1, temperature)[0]
    return out


def _found(views: list[tuple[InstanceViews, str]], req: SearchRequest) -> list[dict]:
    """The request's instances (each target's :class:`InstanceViews` and name) inside its area /
    z band, best first (confidence to 3 decimals, voxels, id), at most ``max_instances``;
    only those are turned into the reply's rows."""
    poly, zb = req.polygon(), req.z_band
    parts: list[tuple[InstanceViews, str, np.ndarray]] = []
    for v, name in views:
        ok = np.ones(len(v), bool)
        if poly is not None and len(v):
            ok &= points_in_polygon(v.centroid[:, :2], poly)
        if zb is not None and len(v):
            ok &= ~((v.box_max[:, 2] < zb[0]) | (v.box_min[:, 2] > zb[1]))
        parts.append((v, name, np.flatnonzero(ok)))
    if not parts or not req.max_instances:
        return []
    conf = np.asarray([round(c, 3) for v, _, k in parts for c in v.confidence[k].tolist()], np.float64)
    size = np.concatenate([v.voxels[k] for v, _, k in parts])
    ids = np.asarray([v.instances[i].id for v, _, k in parts for i in k.tolist()], np.int64)
    part = np.repeat(np.arange(len(parts)), [len(k) for _, _, k in parts])
    row = np.concatenate([k for _, _, k in parts])
    out = []
    for c in np.lexsort((ids, -size, -conf))[:req.max_instances].tolist():   # stable, as a sort by key
        v, name, _ = parts[int(part[c])]
        d = v.as_dict(int(row[c]))
        d["target"] = name
        out.append(d)
    return out


def _instances(snap: QueryCopy, fs: FeatureSpace, vprep: PreparedRows, q: torch.Tensor, sc: _Scored,
               req: SearchRequest, phrases: list[str], n_bg: int, cfg: MapperConfig, trackers: TrackerStore,
               map_version: int) -> tuple[list[dict], list[dict]]:
    """``(found, events)``: every target's identity tracker (:func:`identity_key`) updated
    with the voxels whose identity probability is above ``search.identity_threshold``, then
    seen through the request's probabilities ``sc.vs`` (T, N) and threshold (docs/identity.md;
    when those are the identity's, the tracker's own instances). A tracker last fed from
    ``sc`` at this token is not fed the same voxels again (it would change nothing).
    ``q``: the targets' rows then ``phrases``' (the request's ``n_bg`` background phrases first)."""
    scfg = cfg.search
    vs = sc.vs
    if sc.ident is None:
        sc.ident = _identity_probabilities(snap, fs, vprep, q, list(req.targets), req.embeddings is None, phrases,
                                           list(scfg.background), scfg.temperature, cfg.device, request=(vs, n_bg))
    ident = sc.ident
    token = (int(map_version), int(snap.frames_mapped))
    views: list[tuple[InstanceViews, str]] = []
    events: list[dict] = []
    with trackers.mutex:
        for ti, name in enumerate(req.targets):
            key = identity_key(req, ti)
            tracker = trackers.get(key, snap.vox, scfg.min_instance_voxels, scfg.instance_grace)
            fed = (key, token, float(scfg.identity_threshold), tracker.inputs)
            last = sc.fed.get(ti)
            if last is not None and last[0]() is tracker and last[1:] == fed:
                ev = trackers.repeat(key, token)           # the same input as its last update
            else:
                rows = np.flatnonzero(ident[ti] > scfg.identity_threshold)
                ev = trackers.update(key, None, ident[ti, rows], snap.frames_mapped, token,
                                     keys=_voxel_keys(snap, rows))
            sc.fed[ti] = (weakref.ref(tracker), key, token, float(scfg.identity_threshold), tracker.inputs)
            events += [dict(e, target=name) for e in ev]
            if ident is vs and req.threshold == scfg.identity_threshold:
                # the request sees exactly the voxels the tracker was fed: its instances as they are
                kept = sc.views.get(ti)
                if kept is None or kept[0]() is not tracker or kept[1] != tracker.version:
                    kept = sc.views[ti] = (weakref.ref(tracker), tracker.version, tracked_views(tracker.current()))
                views.append((kept[2], name))
                continue
            rrows = np.flatnonzero(vs[ti] > req.threshold)
            o, rk = key_order(_voxel_keys(snap, rrows))
            views.append((request_views(tracker.current(), rk, unpack_keys(rk), vs[ti, rrows][o], snap.vox,
                                        scfg.min_instance_voxels), name))
    return _found(views, req), events


def _beyond(snap: QueryCopy, rs: np.ndarray, targets: list[str], scfg: SearchSection, qcfg: QuerySection,
            angle_err: float, keep: np.ndarray) -> dict:
    """Best rays per target, triangulated estimates, search volume of the best rays' cones."""
    o, d = snap.ray_origins.astype(np.float64), snap.ray_dirs.astype(np.float64)
    rays: list[dict] = []
    ests: list[dict] = []
    best_all: list[tuple[float, int]] = []
    idx = np.flatnonzero(keep)
    for t, name in enumerate(targets):
        if not len(idx):
            break
        top = idx[np.argsort(-rs[t, idx], kind="stable")[:scfg.beyond_rays]]
        best_all.extend((float(rs[t, i]), int(i)) for i in top)
        rays += [dict(origin=[float(v) for v in o[i]], direction=[float(v) for v in d[i]], score=float(rs[t, i]),
                      target=name) for i in top]
        for e in triangulate(o[top], d[top], rs[t, top], max_gap_m=scfg.max_gap_m, angle_err_deg=angle_err,
                             max_range_m=qcfg.search_range_m):
            e.target = name
            ests.append(e.as_dict())
    rays.sort(key=lambda r: -r["score"])
    ests.sort(key=lambda e: -e["score"])
    best_all.sort(key=lambda x: -x[0])
    sel = np.array(list(dict.fromkeys(i for _, i in best_all))[:qcfg.search_rays], np.int64)
    vol = 0.0
    if len(sel):
        vol = _search_volume(o[sel], d[sel], snap.half_angle, qcfg)
    return dict(rays=rays[:max(10, 2 * len(targets))], estimates=ests[:10], search_volume_m3=vol)


def answer_search(snap: QueryCopy, fs: FeatureSpace, req: SearchRequest, cfg: MapperConfig, trackers: TrackerStore,
                  read_map: Callable[[Callable[[RayFrontsMap], list[Goal]]], list[Goal] | None] | None,
                  map_version: int = 0) -> SearchReply:
    """Answer ``req`` from query copy ``snap`` (module docstring). ``cfg`` the mapper
    config (``search``, ``query``, ``map``, ``device``, ``text_model_dir``); ``read_map(fn)``
    runs ``fn(map)`` under the map lock and returns its result (None: no look-next)."""
    scfg, qcfg = cfg.search, cfg.query
    tm: dict[str, float] = {}
    t0 = t = time.perf_counter()
    background = [b for b in (req.background if req.background is not None else scfg.background)
                  if b not in req.targets]
    # the identity's canonical background (search.background) is embedded after the request's
    phrases = background + [b for b in scfg.background if b not in background]
    q_all = embed_phrases(fs, req, phrases, cfg.device, cfg.text_model_dir, getattr(qcfg, "templates", "auto"))
    q = q_all[:len(req.targets) + len(background)]
    tm["encode"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    vprep, rprep = snap.prepared(fs, cfg.device)
    T = len(req.targets)

    def score() -> _Scored:
        vs = _voxel_probabilities(snap, fs, vprep, q, T, scfg.temperature, cfg.device)
        with one_thread():                      # a few thousand rays: no parallel region
            return _Scored(vs, *_ray_scores(rprep, q, T, scfg.temperature, scfg.distinct_phrases, scfg.ray_evidence))

    sc = _scored(snap, _scored_key(snap, fs, q_all, req, phrases, len(background), cfg), score)
    rs, rcos = sc.rs, sc.rcos
    tm["similarity"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    found, events = _instances(snap, fs, vprep, q_all, sc, req, phrases, len(background), cfg, trackers,
                               map_version)
    tm["instances"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    rkeep = _in_area(snap.ray_origins.astype(np.float64), req.polygon(), req.z_band)
    # outliers among all the map's rays, then the area's
    rz = ray_outlier_z(rcos, scfg.ray_cosine_resolution)[:, rkeep]
    goals: list[dict] = []
    if read_map is not None and req.max_goals > 0:
        def run(m: RayFrontsMap) -> list[Goal]:
            with one_thread():                  # many small torch ops (on a loaded machine every
                # parallel region would wait on a descheduled worker)
                f = m.frontiers().centres.detach().cpu().numpy().astype(np.float64).reshape(-1, 3)
                if req.polygon() is not None or req.z_band is not None:
                    f = f[_in_area(f, req.polygon(), req.z_band)]
                radius = scfg.ray_radius_m if scfg.ray_radius_m > 0 else float(m.cfg.beta)
                return look_next(m.occupancy_view(), float(m.cfg.vox_size), f, snap.ray_origins[rkeep],
                                 snap.ray_dirs[rkeep], rs[:, rkeep].T, list(req.targets), req.from_xyz,
                                 ray_z=rz.T, ray_radius_m=radius, standoff_m=scfg.standoff_m,
                                 sensing_radius_m=scfg.sensing_radius_m, max_goals=req.max_goals,
                                 cache=look_next_cache(m))
        got = read_map(run)
        if got is None:
            tm["stale"] = 1.0
        else:
            goals = [g.as_dict() for g in got]
    tm["look_next"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    angle_err = scfg.angle_err_deg if scfg.angle_err_deg > 0 else float(cfg.map.angle_bin_size) / 2
    bkey = (hashlib.sha1(np.packbits(rkeep).tobytes()).hexdigest(), len(rkeep), angle_err, float(snap.half_angle),
            scfg.beyond_rays, scfg.max_gap_m, qcfg.search_range_m, qcfg.search_rays, qcfg.search_cell_m,
            qcfg.search_samples)
    if bkey not in sc.beyond:
        with one_thread():
            sc.beyond[bkey] = _beyond(snap, rs, list(req.targets), scfg, qcfg, angle_err, rkeep)
        while len(sc.beyond) > BEYOND_AREAS:
            sc.beyond.pop(next(iter(sc.beyond)))
    beyond = copy.deepcopy(sc.beyond[bkey])
    tm["beyond"] = (time.perf_counter() - t) * 1e3
    tm["total"] = (time.perf_counter() - t0) * 1e3
    return SearchReply(id=req.id, found=found, look_next=goals, beyond=beyond, events=events,
                       frames_mapped=int(snap.frames_mapped), map_version=int(map_version), timings_ms=tm)


def text_similarities(snap: QueryCopy, fs: FeatureSpace, texts: list[str], cfg: MapperConfig, softmax: bool
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each text's similarity to every voxel and ray of query copy ``snap``: ``(voxel
    centres (N, 3) m, voxel scores (Q, N), ray scores (Q, R))`` (rays in ``snap.ray_origins`` /
    ``ray_dirs`` order). Scores: cosine, or with ``softmax`` the softmax across the texts at
    ``search.temperature`` (upstream RayFronts' ``compute_prob``; one text → all 1)."""
    from mapper.query_answer import embed_text

    q = torch.cat([embed_text(fs, t, cfg.device, cfg.text_model_dir, getattr(cfg.query, "templates", "auto"))
                   .reshape(1, -1) for t in texts]).to(torch.float32)
    vprep, rprep = snap.prepared(fs, cfg.device)
    temp = float(cfg.search.temperature)
    with one_thread():
        vs = score_rows(vprep, q, None, softmax=softmax, temperature=temp) if len(vprep) else torch.zeros(len(q), 0)
        rs = score_rows(rprep, q, None, softmax=softmax, temperature=temp) if len(rprep) else torch.zeros(len(q), 0)
    xyz = snap.voxel_xyz(np.arange(snap.n_voxels)) if snap.n_voxels else np.zeros((0, 3), np.float32)
    return (np.asarray(xyz, np.float32).reshape(-1, 3), vs.detach().cpu().numpy().astype(np.float32),
            rs.detach().cpu().numpy().astype(np.float32))
