"""Map snapshots: save (atomic), restore on start, keep the newest N, and the snapshot
queryable (module map: :mod:`mapper.state`; ARCHITECTURE.md).

On-disk layout under ``snapshots.dir``::

    LATEST                   name of the newest complete snapshot (replaced atomically)
    snap-<ms>/map/           the map (RayFrontsMap.save)
    snap-<ms>/feature_space.bin   the feature-space envelope the map was built in
    snap-<ms>/meta.json      frames_mapped, stamp, version, per-robot mapped / last_seq

A snapshot is written into ``.tmp-snap-<ms>`` and renamed into place, then ``LATEST`` is
replaced, so a crash never leaves a half snapshot behind the pointer. Restore failures are
logged and the mapper starts empty.
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
                        "robots": {n: {"mapped": st.mapped, "last_seq": st.last_seq} for n, st in s.robots.items()}}
            path = write_snapshot(root, s.map, s.space_reply, meta, s.cfg.snapshots.keep)
        s.snap_version = version
        s.last_snapshot = {"path": str(path), "frames_mapped": meta["frames_mapped"], "stamp": meta["stamp"],
                           "seconds": time.perf_counter() - t0}
        log.info("snapshot %s (%d frames)", path, meta["frames_mapped"])
        return s.last_snapshot

    def restore(self) -> None:
        """Load the snapshot ``LATEST`` points to, if any (before the Zenoh entities exist)."""
        from common.feature_space import FeatureSpace
        from mapper.service_map import load_map

        s = self.state
        root = Path(s.cfg.snapshots.dir)
        ptr = root / "LATEST"
        if not ptr.is_file():
            return
        path = root / ptr.read_text().strip()
        try:
            meta = json.loads((path / "meta.json").read_text())
            envelope = (path / "feature_space.bin").read_bytes()
            _, body = decode_feature_space(envelope)
            fs = FeatureSpace.from_body(body)
            s.map = load_map(path / "map", s.cfg, fs)
            s.map_gen += 1
        except Exception as e:
            log.error("cannot restore snapshot %s: %s (starting empty)", path, e)
            s.map = None
            return
        s.space, s.space_reply = fs, envelope
        s.mapped = int(meta.get("frames_mapped", 0))
        s.version = s.snap_version = s.flushed_version = 1
        for name, r in meta.get("robots", {}).items():
            st = s.robot(name)
            st.mapped, st.last_seq = int(r.get("mapped", 0)), int(r.get("last_seq", -1))
        s.last_snapshot = {"path": str(path), "frames_mapped": s.mapped, "stamp": meta.get("stamp", 0.0),
                           "restored": True}
        log.info("restored snapshot %s (%d frames, space %s)", path, s.mapped, fs.id)

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
    m.save(tmp / "map")
    (tmp / "feature_space.bin").write_bytes(space_envelope)
    (tmp / "meta.json").write_text(json.dumps(meta))
    os.replace(tmp, root / name)
    (root / ".latest.tmp").write_text(name)
    os.replace(root / ".latest.tmp", root / "LATEST")
    snaps = sorted(p for p in root.glob("snap-*") if p.is_dir())
    for old in snaps[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return root / name
