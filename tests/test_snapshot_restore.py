"""Snapshot restore against the configured map: a differing map config is one clear error
(or an explicit choice), and a snapshot is durable and written outside the map lock."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import numpy as np
import pytest
import torch

from common.config import ConfigError
from common.feature_space import FeatureSpace
from common.messages import encode_feature_space
from common.pca import PCA
from mapper.service_config import load_mapper_config
from mapper.service_map import create_map
from mapper.snapshot import capture_map, map_config_changes
from mapper.snapshot_store import SnapshotStore, write_snapshot
from mapper.state import MapperState


def _snapshot(root, overrides: list[str]) -> FeatureSpace:
    """A snapshot in ``root`` of a small map built with the mapper config ``overrides``."""
    rng = np.random.default_rng(0)
    pca = PCA.fit(rng.normal(size=(500, 12)), 4)
    fs = FeatureSpace("label", "1", 12, pca=pca)
    cfg = load_mapper_config(None, overrides)
    m = create_map(cfg, fs)
    g = torch.Generator().manual_seed(0)
    m.fuse_samples(torch.rand((50, 3), generator=g) * 5, torch.rand((50, 3), generator=g),
               torch.randn((50, 4), generator=g))
    write_snapshot(root, capture_map(m), encode_feature_space("t", fs.to_body()), {"frames_mapped": 7, "robots": {}})
    return fs


def _restore(root, overrides: list[str]) -> MapperState:
    state = MapperState(load_mapper_config(None, [f"snapshots.dir={root}", *overrides]), threading.Event())
    SnapshotStore(state).restore()
    return state


def test_same_config_restores(tmp_path):
    _snapshot(tmp_path, ["map.vox_size=0.5"])
    st = _restore(tmp_path, ["map.vox_size=0.5"])
    assert st.map is not None and st.map.n_voxels() > 0 and st.mapped == 7


def test_differing_map_config_is_one_line_naming_the_keys(tmp_path):
    _snapshot(tmp_path, ["map.vox_size=0.5"])
    gen = next(tmp_path.glob("snap-*"))
    assert map_config_changes(gen / "map", load_mapper_config(None, ["map.vox_size=0.25"]).map) == \
        {"vox_size": (0.5, 0.25)}
    with pytest.raises(ConfigError) as e:
        _restore(tmp_path, ["map.vox_size=0.25"])
    msg = str(e.value)
    assert "\n" not in msg and "map.vox_size: snapshot 0.5 vs configured 0.25" in msg
    assert "snapshots.map_config=snapshot" in msg and "snapshots.map_config=command_line" in msg


def test_config_conflict_choices(tmp_path):
    _snapshot(tmp_path, ["map.vox_size=0.5"])
    kept = _restore(tmp_path, ["map.vox_size=0.25", "snapshots.map_config=snapshot"])
    assert kept.map is not None and kept.map.cfg.vox_size == 0.5 and kept.mapped == 7
    fresh = _restore(tmp_path, ["map.vox_size=0.25", "snapshots.map_config=command_line"])
    assert fresh.map is None and fresh.mapped == 0          # an empty map: created with the first frame
    assert len(list(tmp_path.glob("snap-*"))) == 1          # the snapshot stays on disk


def test_mapper_cli_refuses_a_conflicting_snapshot_with_one_line(tmp_path):
    _snapshot(tmp_path, ["map.vox_size=0.5"])
    out = subprocess.run([sys.executable, "-m", "apps.cli", "mapper", f"snapshots.dir={tmp_path}",
                          "map.vox_size=0.25", "--mode", "peer", "--listen", "tcp/127.0.0.1:0"],
                         capture_output=True, text=True, timeout=120, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert out.returncode == 2, out.stderr[-2000:]
    lines = [ln for ln in out.stderr.splitlines() if "map.vox_size" in ln]
    assert len(lines) == 1 and "snapshot 0.5 vs configured 0.25" in lines[0]
    assert "Traceback" not in out.stderr


def test_snapshot_is_fsynced_before_latest_moves(tmp_path, monkeypatch):
    """Every file of the generation and its directories are fsynced before LATEST is replaced."""
    order: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def track_fsync(fd):
        order.append("fsync:" + os.readlink(f"/proc/self/fd/{fd}"))
        return real_fsync(fd)

    def track_replace(a, b):
        order.append(f"replace:{os.path.basename(a)}->{os.path.basename(b)}")
        return real_replace(a, b)

    monkeypatch.setattr(os, "fsync", track_fsync)
    monkeypatch.setattr(os, "replace", track_replace)
    _snapshot(tmp_path, ["map.vox_size=0.5"])
    latest = next(i for i, e in enumerate(order) if e.endswith("->LATEST"))
    before = order[:latest]
    for name in ("arrays.npz.tmp", "manifest.json", "feature_space.bin", "meta.json", ".latest.tmp"):
        assert any(e.startswith("fsync:") and e.endswith(name) for e in before), (name, order)
    gen = next(tmp_path.glob("snap-*")).name
    renamed = next(i for i, e in enumerate(order) if e.endswith("->" + gen))
    assert any(e == f"fsync:{tmp_path}" for e in order[renamed:latest]), order   # the rename is durable
    assert order[-1] == f"fsync:{tmp_path}"                                     # and so is LATEST's


def test_snapshot_writes_outside_the_map_lock(tmp_path, monkeypatch):
    """SnapshotStore.save copies the map under the lock and writes after releasing it."""
    import mapper.snapshot_store as store

    _snapshot(tmp_path / "seed", ["map.vox_size=0.5"])
    st = _restore(tmp_path / "seed", ["map.vox_size=0.5"])
    st.cfg.snapshots.dir = str(tmp_path / "out")
    held = []
    real = store.write_snapshot

    def spy(*a, **kw):
        held.append(st.lock._is_owned())
        return real(*a, **kw)

    monkeypatch.setattr(store, "write_snapshot", spy)
    SnapshotStore(st).save()
    assert held == [False]
    again = _restore(tmp_path / "out", ["map.vox_size=0.5"])
    assert torch.equal(again.map.voxels().features, st.map.voxels().features)


def test_standing_queries_are_saved_and_resume(tmp_path):
    from common.messages import QueryRequest

    _snapshot(tmp_path / "seed", ["map.vox_size=0.5"])
    st = _restore(tmp_path / "seed", ["map.vox_size=0.5"])
    st.cfg.snapshots.dir = str(tmp_path / "out")
    reqs = [QueryRequest(text="water tower", top_k=4, standing=True, id="w1"),
            QueryRequest(embedding=np.arange(4, dtype=np.float32), softmax=True, standing=True, id="e2")]
    st.standing = {r.id: r for r in reqs}
    SnapshotStore(st).save()
    again = _restore(tmp_path / "out", ["map.vox_size=0.5"])
    assert sorted(again.standing) == ["e2", "w1"]
    w, e = again.standing["w1"], again.standing["e2"]
    assert (w.text, w.top_k, w.standing) == ("water tower", 4, True)
    assert e.softmax and np.array_equal(e.embedding, reqs[1].embedding)
    assert again.standing_due.is_set()      # answered once on the restored map


def test_instance_ids_sent_after_the_newest_snapshot_are_not_reissued_after_a_crash(tmp_path):
    """The snapshot's counter is 1; 300 ids are then sent (two reservation blocks) and the
    process dies without another save: the restarted mapper continues above every id sent."""
    _snapshot(tmp_path, ["map.vox_size=0.5"])
    first = _restore(tmp_path, ["map.vox_size=0.5"])
    assert first.trackers.next_id == 1
    sent = [first.trackers.new_id() for _ in range(300)]
    assert sent == list(range(1, 301)) and first.trackers.reserve_errors == 0
    reserved = json.loads((tmp_path / "instance_ids.json").read_text())["reserved_below"]
    assert reserved > max(sent)
    again = _restore(tmp_path, ["map.vox_size=0.5"])        # no save in between: a crash
    assert again.trackers.new_id() > max(sent)
    # without the reservation file only the snapshot's counter is left, and ids repeat
    (tmp_path / "instance_ids.json").unlink()
    assert _restore(tmp_path, ["map.vox_size=0.5"]).trackers.new_id() == 1


def test_a_failing_id_reservation_is_counted_and_the_id_still_issued(tmp_path, caplog):
    (tmp_path / "instance_ids.json").mkdir()                  # the rename onto it fails
    st = _restore(tmp_path, [])
    assert "instance_ids.json is unreadable" in caplog.text
    assert [st.trackers.new_id() for _ in range(3)] == [1, 2, 3]
    assert st.trackers.reserve_errors == 3 and st.trackers.reserved_below == 1
    assert "could not reserve instance ids below 2" in caplog.text
