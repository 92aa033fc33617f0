"""Map snapshots: save (atomic), restore on start, keep the newest N, and the snapshot
queryable (module map: ARCHITECTURE.md).

On-disk layout under ``snapshots.dir``::

    LATEST                   name of the newest complete snapshot (replaced atomically)
    snap-<ms>/map/           the map (RayFrontsMap.save)
    snap-<ms>/feature_space.bin   the feature-space envelope the map was built in
    snap-<ms>/meta.json      frames_mapped, stamp, version, per-robot mapped / last_seq, standing
                             queries and searches, run-time transforms, instance trackers
    snap-<ms>/instance_keys.npy   the instance trackers' voxel keys (meta.json's ``instances``)
    instance_ids.json        {"reserved_below": n}: search instance ids below n may have been
                             sent; a restart issues none of them again (crash included)

A snapshot is written into ``.tmp-snap-<ms>`` and renamed into place, then ``LATEST`` is
replaced, so a crash never leaves a half snapshot behind the pointer. The newest
``snapshots.keep`` generations stay on disk. Restore tries them newest first
(:func:`mapper.snapshot.snapshot_generations`; ``LATEST`` first) and takes the first intact
one, logging each broken one and saying in the log and in ``stats().snapshot``
(``fallback_from``) that it fell back; only when none is intact does the mapper start empty.

Restore = the same answers: a snapshot holds the map *with* its pending accumulation
buffers, and ``meta.json`` the map ``version`` and ``flushed_version`` at save time; restore
puts both back, so a map saved before its idle flush is flushed after the restart exactly as
it would have been (the old code set both to 1, the flush never came and the restored
mapper answered from the unflushed map: no rays, missing voxels).
"""
from __future__ import annotations

import base64
import io
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from common.messages import (
    MessageError,
    decode_feature_space,
    decode_query_request,
    decode_snapshot_request,
    encode_error,
    encode_query_request,
    encode_snapshot_reply,
)
from common.search_messages import decode_search_request, encode_search_request
from mapper.snapshot import (
    META_VERSION,
    capture_map,
    fsync_dir,
    replace_file_durably,
    write_bytes_durably,
    write_capture,
)
from mapper.state import MapperState, jsonable

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("rayfronts.mapper")


#: the instance trackers' voxel keys in a generation (``<name>.npy``)
INSTANCE_KEYS = "instance_keys"


class SnapshotStore:
    """Snapshots of the shared map in ``cfg.snapshots.dir``."""

    IDS_FILE = "instance_ids.json"

    def __init__(self, state: MapperState) -> None:
        self.state = state
        if state.cfg.snapshots.dir:
            state.trackers.reserve = self.reserve_instance_ids

    def reserve_instance_ids(self, below: int) -> None:
        """Persist that instance ids below ``below`` may be in use (write, fsync, rename):
        called by the tracker store before it hands out an id at or above the last ceiling,
        so ids sent after the newest snapshot survive a crash as reserved."""
        root = Path(self.state.cfg.snapshots.dir)
        root.mkdir(parents=True, exist_ok=True)
        replace_file_durably(root / self.IDS_FILE, json.dumps({"reserved_below": int(below)}).encode(),
                             self.IDS_FILE + ".tmp")

    def _restore_instance_ids(self, root: Path) -> None:
        """Continue instance ids above the persisted reservation (a broken file is logged:
        then only the snapshot's counter holds)."""
        f = root / self.IDS_FILE
        if not f.exists():
            return
        try:
            below = int(json.loads(f.read_text())["reserved_below"])
        except Exception as e:
            log.error("%s is unreadable (%s): instance ids continue from the snapshot's counter", f, e)
            return
        self.state.trackers.continue_from(below)
        log.info("instance ids continue from %d (reserved before the restart)", below)

    def save(self) -> dict:
        """Write the map atomically (tmp dir, then rename) to ``snapshots.dir/snap-<n>``."""
        state = self.state
        root = Path(state.cfg.snapshots.dir)
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        generation = state.trackers.generation                # read first: a later update is saved next time
        trackers, tracker_keys = state.trackers.state()      # whole updates (the trackers' mutex)
        fleet = getattr(state, "fleet", None)
        with state.lock:
            if state.map is None:
                raise MessageError("nothing to snapshot: no map yet")
            version = state.version
            with state.robots_lock:
                meta = {"format_version": META_VERSION, "frames_mapped": state.mapped, "stamp": time.time(),
                        "version": version,
                        "flushed_version": state.flushed_version,
                        "robots": {n: {"mapped": st.mapped, "last_seq": st.last_seq} for n, st in state.robots.items()},
                        # only the live ones: a lease run out = its client is gone (mapper.leases)
                        "standing": [_saved_entry(encode_query_request(r))
                                     for k, r in list(state.standing.items()) if state.query_leases.live(k)],
                        "standing_searches": [_saved_entry(encode_search_request(r))
                                              for k, r in list(state.standing_searches.items())
                                              if state.search_leases.live(k)],
                        "instance_next_id": state.trackers.next_id, "instances": trackers,
                        "world_from_robot": fleet.transforms.runtime() if fleet is not None else {}}
            capture = capture_map(state.map)     # copies, under the lock; written after it
        assert state.space_reply is not None     # set with the map (create_map, restore)
        path = write_snapshot(root, capture, state.space_reply, meta, state.cfg.snapshots.keep,
                              arrays={INSTANCE_KEYS: tracker_keys})
        state.snap_version, state.snap_trackers = version, generation
        state.last_snapshot = {"path": str(path), "frames_mapped": meta["frames_mapped"], "stamp": meta["stamp"],
                           "seconds": time.perf_counter() - t0}
        log.info("snapshot %s (%d frames)", path, meta["frames_mapped"])
        return state.last_snapshot

    def restore(self) -> None:
        """Load the newest intact snapshot generation, if any (before the Zenoh entities
        exist); a broken newer one is logged and skipped (module docstring)."""
        from common.feature_space import FeatureSpace
        from mapper.service_map import restore_map
        from mapper.snapshot import check_generation, snapshot_generations

        state = self.state
        root = Path(state.cfg.snapshots.dir)
        self._restore_instance_ids(root)
        gens = snapshot_generations(root)
        if not gens:
            log.info("no snapshot in %s: starting with an empty map", root)
            return
        broken: list[str] = []
        for path in gens:
            log.info("restoring snapshot %s", path)
            try:
                meta = check_generation(path)
                envelope = (path / "feature_space.bin").read_bytes()
                _, body = decode_feature_space(envelope)
                fs = FeatureSpace.from_body(body)
                m = restore_map(path / "map", state.cfg, fs)
            except Exception as e:
                log.error("snapshot %s is broken (%s); trying the generation before it", path, e)
                broken.append(str(path))
                continue
            break
        else:
            log.error("no intact snapshot in %s (%d broken): starting with an empty map", root, len(broken))
            return
        if not self._keep_after_config_check(path):
            return
        state.map = m
        state.map_gen += 1
        state.space, state.space_reply = fs, envelope
        state.warm_up_text(fs)
        state.mapped = int(meta.get("frames_mapped", 0))
        # the map's version and flush state as saved: a map saved with frames still in its
        # accumulation buffers is flushed by the idle flush, as it would have been
        state.version = max(1, int(meta.get("version", 1)))
        state.flushed_version = int(meta.get("flushed_version", state.version - 1))
        state.snap_version = state.version
        state.snap_trackers = state.trackers.generation
        for name, r in meta.get("robots", {}).items():
            st = state.robot(name)
            st.mapped, st.last_seq = int(r.get("mapped", 0)), int(r.get("last_seq", -1))
        self._restore_standing(meta.get("standing", []))
        self._restore_searches(meta.get("standing_searches", []), int(meta.get("instance_next_id", 1)))
        self._restore_trackers(path, meta)
        self._restore_transforms(meta.get("world_from_robot", {}))
        state.last_snapshot = {"path": str(path), "frames_mapped": state.mapped, "stamp": meta.get("stamp", 0.0),
                           "restored": True}
        if broken:
            state.last_snapshot["fallback_from"] = broken
        log.info("restored snapshot %s (%d frames, space %s, %s)%s", path, state.mapped, fs.id,
                 "flush pending" if state.flushed_version != state.version else "flushed",
                 f"; fell back from {len(broken)} broken newer generation(s)" if broken else "")

    def _restore_standing(self, saved: list) -> None:
        """Standing queries saved with the snapshot resume under their ids (watchers keep
        receiving on ``mapper/queries/<id>``); an unreadable one is logged and skipped."""
        state = self.state
        for req in _decode_saved(saved, decode_query_request, "standing query"):
            state.standing[req.id] = req
            if req.client:                   # a client's: a fresh lease it renews (mapper.leases)
                state.query_leases.restore(req.id, req.client, req.lease_s)
        if state.standing:
            state.standing_due.set()         # answer them once on the restored map
        if saved:
            log.info("restored %d standing quer%s: %s", len(state.standing), "y" if len(state.standing) == 1 else "ies",
                     ", ".join(sorted(state.standing)))

    def _restore_searches(self, saved: list, next_id: int) -> None:
        """Standing searches saved with the snapshot resume under their ids (the search server
        re-runs them on the restored map and publishes on ``mapper/searches/<id>``); instance
        ids continue from the saved counter or the reservation (:meth:`reserve_instance_ids`),
        whichever is higher, so none is reused."""
        state = self.state
        state.trackers.continue_from(next_id)
        for req in _decode_saved(saved, decode_search_request, "standing search"):
            state.standing_searches[req.id] = req
            if req.client:                   # a client's: a fresh lease it renews (mapper.leases)
                state.search_leases.restore(req.id, req.client, req.lease_s)
        if saved:
            log.info("restored %d standing search(es): %s", len(state.standing_searches),
                     ", ".join(sorted(state.standing_searches)))

    def _restore_trackers(self, path: Path, meta: dict) -> None:
        """The instance trackers as saved (format 2): the same objects keep their ids. A
        format-1 snapshot has none (objects get new ids); unreadable ones are logged and the
        trackers start empty (ids still continue above every id issued)."""
        desc = meta.get("instances")
        if desc is None:
            log.info("snapshot %s holds no instance trackers (format 1): objects get new ids", path)
            return
        try:
            keys = np.load(path / f"{INSTANCE_KEYS}.npy", allow_pickle=False)
            self.state.trackers.load_state(desc, keys)
        except Exception as e:
            log.error("snapshot %s: instance trackers unreadable (%s); objects get new ids", path, e)
            return
        log.info("restored %d instance tracker(s), ids from %d", len(self.state.trackers),
                 self.state.trackers.next_id)

    def _restore_transforms(self, saved: dict) -> None:
        """``world_from_robot`` transforms set at run time before the save are set again (they
        override the configured ones, as they did then); a bad one is logged and skipped."""
        fleet = getattr(self.state, "fleet", None)
        if not saved or fleet is None:
            return
        from mapper.robot_registry import TransformError

        for robot, vals in saved.items():
            try:
                fleet.transforms.set(str(robot), vals)
            except TransformError as e:
                log.error("snapshot: the saved world_from_robot of robot %s is unusable (%s); skipped", robot, e)
                continue
            log.info("robot %s: world_from_robot set at run time restored from the snapshot", robot)

    def _keep_after_config_check(self, path: Path) -> bool:
        """Whether the restored generation at ``path`` is kept, given ``snapshots.map_config``
        when its map config differs from the configured one; 'error' raises a one-line
        :class:`common.config.ConfigError` naming the keys."""
        from common.config import ConfigError
        from mapper.snapshot import map_config_changes

        state = self.state
        changes = map_config_changes(path / "map", state.cfg.map)
        if not changes:
            return True
        said = ", ".join(f"map.{k}: snapshot {a!r} vs configured {b!r}" for k, (a, b) in changes.items())
        mode = state.cfg.snapshots.map_config
        if mode == "snapshot":
            log.warning("snapshot %s: keeping its map config (%s)", path, said)
            return True
        if mode == "command_line":
            log.warning("snapshot %s: map config differs (%s); starting an empty map with the configured one", path,
                        said)
            return False
        raise ConfigError(f"snapshot {path} was mapped with another map config ({said}); restart with "
                          "snapshots.map_config=snapshot to keep the snapshot's, snapshots.map_config=command_line to "
                          "start an empty map with this one, or the same map.* settings")

    def on_snapshot(self, query: zenoh.Query) -> None:
        state = self.state
        try:
            try:
                action = decode_snapshot_request(query.payload.to_bytes()) if query.payload is not None else "describe"
                if action == "save":
                    if not state.cfg.snapshots.dir:
                        raise MessageError("snapshots are off (set snapshots.dir)")
                    info = self.save()
                else:
                    info = dict(state.last_snapshot)
                payload = encode_snapshot_reply(jsonable(info))
            except (MessageError, OSError) as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("snapshot callback: %s", e)


def write_snapshot(root: Path, capture: tuple[dict, dict], space_envelope: bytes, meta: dict,
                   keep: int = 2, arrays: dict | None = None) -> Path:
    """Write ``root/snap-<ms>`` atomically with a map ``capture`` (:func:`mapper.snapshot.capture_map`,
    taken under the map lock; no lock is needed here), its feature-space envelope, ``meta``
    and ``arrays`` (``<name>.npy`` each); keeps the newest ``keep`` snapshots.

    Durable before visible: every file and directory of the generation is fsynced, then the
    ``.tmp-`` dir is renamed into place and the root fsynced, then ``LATEST`` is written,
    fsynced and renamed over the old pointer, and the root fsynced again — after a power loss
    ``LATEST`` never names a generation whose bytes are not on disk."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = f"snap-{int(time.time() * 1000):015d}"
    tmp = root / f".tmp-{name}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    write_capture(capture, tmp / "map")
    write_bytes_durably(tmp / "feature_space.bin", space_envelope)
    write_bytes_durably(tmp / "meta.json", json.dumps(meta).encode())
    for array_name, a in (arrays or {}).items():
        buf = io.BytesIO()
        np.save(buf, a, allow_pickle=False)
        write_bytes_durably(tmp / f"{array_name}.npy", buf.getvalue())
    fsync_dir(tmp)
    os.replace(tmp, root / name)
    fsync_dir(root)
    replace_file_durably(root / "LATEST", name.encode(), ".latest.tmp")
    snaps = sorted(p for p in root.glob("snap-*") if p.is_dir())
    for old in snaps[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return root / name


def _saved_entry(message: bytes) -> dict:
    """One standing query / search as ``meta.json`` keeps it (format 2): an object whose
    ``request`` is the base64 request message (room for more fields, e.g. a lease)."""
    return {"request": base64.b64encode(message).decode()}


def _decode_saved(saved: list, decode, what: str) -> list:
    """The requests saved in ``meta.json``: :func:`_saved_entry` objects (format 2; other
    fields ignored) or bare base64 messages (format 1); an unreadable one is one error line
    and skipped."""
    out = []
    for item in saved:
        try:
            out.append(decode(base64.b64decode(item["request"] if isinstance(item, dict) else item)))
        except (MessageError, ValueError, TypeError, KeyError) as e:
            log.error("snapshot: a saved %s is unreadable (%s); skipped", what, e)
    return out
