"""Map snapshots: save (atomic), restore on start, keep the newest N, and the snapshot
queryable (module map: :mod:`mapper.state`; ARCHITECTURE.md).

On-disk layout under ``snapshots.dir``::

    LATEST                   name of the newest complete snapshot (replaced atomically)
    snap-<ms>/map/           the map (RayFrontsMap.save)
    snap-<ms>/feature_space.bin   the feature-space envelope the map was built in
    snap-<ms>/meta.json      frames_mapped, stamp, version, per-robot mapped / last_seq

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

import json
import logging
import os
import shutil
import time
from pathlib import Path

from common.messages import (
    MessageError,
    decode_feature_space,
    decode_snapshot_request,
    encode_error,
    encode_snapshot_reply,
)
from mapper.snapshot import save_map
from mapper.state import MapperState, jsonable

log = logging.getLogger("rayfronts.mapper")


class SnapshotStore:
    """Snapshots of the shared map in ``cfg.snapshots.dir``."""

    def __init__(self, state: MapperState):
        self.state = state

    def save(self) -> dict:
        """Write the map atomically (tmp dir, then rename) to ``snapshots.dir/snap-<n>``."""
        s = self.state
        root = Path(s.cfg.snapshots.dir)
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        with s.lock:
            if s.map is None:
                raise MessageError("nothing to snapshot: no map yet")
            version = s.version
            with s.qlock:
                meta = {"frames_mapped": s.mapped, "stamp": time.time(), "version": version,
                        "flushed_version": s.flushed_version,
                        "robots": {n: {"mapped": st.mapped, "last_seq": st.last_seq} for n, st in s.robots.items()}}
            path = write_snapshot(root, s.map, s.space_reply, meta, s.cfg.snapshots.keep)
        s.snap_version = version
        s.last_snapshot = {"path": str(path), "frames_mapped": meta["frames_mapped"], "stamp": meta["stamp"],
                           "seconds": time.perf_counter() - t0}
        log.info("snapshot %s (%d frames)", path, meta["frames_mapped"])
        return s.last_snapshot

    def restore(self) -> None:
        """Load the newest intact snapshot generation, if any (before the Zenoh entities
        exist); a broken newer one is logged and skipped (module docstring)."""
        from common.feature_space import FeatureSpace
        from mapper.service_map import restore_map
        from mapper.snapshot import check_generation, snapshot_generations

        s = self.state
        root = Path(s.cfg.snapshots.dir)
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
                m = restore_map(path / "map", s.cfg, fs)
            except Exception as e:
                log.error("snapshot %s is broken (%s); trying the generation before it", path, e)
                broken.append(str(path))
                continue
            break
        else:
            log.error("no intact snapshot in %s (%d broken): starting with an empty map", root, len(broken))
            return
        s.map = m
        s.map_gen += 1
        s.space, s.space_reply = fs, envelope
        s.mapped = int(meta.get("frames_mapped", 0))
        # the map's version and flush state as saved: a map saved with frames still in its
        # accumulation buffers is flushed by the idle flush, as it would have been
        s.version = max(1, int(meta.get("version", 1)))
        s.flushed_version = int(meta.get("flushed_version", s.version - 1))
        s.snap_version = s.version
        for name, r in meta.get("robots", {}).items():
            st = s.robot(name)
            st.mapped, st.last_seq = int(r.get("mapped", 0)), int(r.get("last_seq", -1))
        s.last_snapshot = {"path": str(path), "frames_mapped": s.mapped, "stamp": meta.get("stamp", 0.0),
                           "restored": True}
        if broken:
            s.last_snapshot["fallback_from"] = broken
        log.info("restored snapshot %s (%d frames, space %s, %s)%s", path, s.mapped, fs.id,
                 "flush pending" if s.flushed_version != s.version else "flushed",
                 f"; fell back from {len(broken)} broken newer generation(s)" if broken else "")

    def on_snapshot(self, query) -> None:
        s = self.state
        try:
            try:
                action = decode_snapshot_request(query.payload.to_bytes()) if query.payload is not None else "describe"
                if action == "save":
                    if not s.cfg.snapshots.dir:
                        raise MessageError("snapshots are off (set snapshots.dir)")
                    info = self.save()
                else:
                    info = dict(s.last_snapshot)
                payload = encode_snapshot_reply(jsonable(info))
            except (MessageError, OSError) as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("snapshot callback: %s", e)


def write_snapshot(root: Path, m, space_envelope: bytes, meta: dict, keep: int = 2) -> Path:
    """Write ``root/snap-<ms>`` atomically (a ``.tmp-`` dir renamed into place, then the
    ``LATEST`` pointer replaced) with the map, its feature-space envelope and ``meta``;
    keeps the newest ``keep`` snapshots. The caller holds the map lock."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = f"snap-{int(time.time() * 1000):015d}"
    tmp = root / f".tmp-{name}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    save_map(m, tmp / "map")
    (tmp / "feature_space.bin").write_bytes(space_envelope)
    (tmp / "meta.json").write_text(json.dumps(meta))
    os.replace(tmp, root / name)
    (root / ".latest.tmp").write_text(name)
    os.replace(root / ".latest.tmp", root / "LATEST")
    snaps = sorted(p for p in root.glob("snap-*") if p.is_dir())
    for old in snaps[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return root / name
