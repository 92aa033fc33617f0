"""Map snapshots: one directory with ``manifest.json`` and ``arrays.npz``.

The snapshot holds everything needed to continue exactly where the map stopped: config,
feature-space id, counters, RNG state, occupancy state (tiles expanded), semantic voxels,
frontier table, ray bins **and the pending (not yet accumulated) buffers** — nothing is
flushed, so a loaded map answers the same queries bit for bit and integrates the next
frames identically. Versioned: an unknown version or a missing file is a
:class:`SnapshotError` naming it.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from common.config import merge, read_document, to_dict

if TYPE_CHECKING:
    from semantic_map.config import MapConfig
    from semantic_map.map import RayFrontsMap

FORMAT = "rayfronts-map"
VERSION = 1
#: version of a generation's ``meta.json`` (``format_version``; absent = 1): 2 adds the
#: instance trackers, the run-time ``world_from_robot`` transforms and standing requests as
#: objects (docs/snapshot_format.md); this build reads 1 and 2
META_VERSION = 2


class SnapshotError(RuntimeError):
    """A snapshot that cannot be read (missing file, unknown format/version, bad content)."""


def _np(t: torch.Tensor | np.ndarray) -> np.ndarray:
    """A numpy copy of ``t`` (never a view of the map's memory: the copy is taken under the map
    lock and written after it is released)."""
    if isinstance(t, torch.Tensor):
        return t.detach().cpu().numpy().copy()
    return np.array(t, copy=True)


def save_map(m: RayFrontsMap, path: str | Path) -> Path:
    """Write map ``m`` to the directory ``path`` (:func:`capture_map` then :func:`write_capture`)."""
    return write_capture(capture_map(m), path)


def capture_map(m: RayFrontsMap) -> tuple[dict[str, np.ndarray], dict]:
    """``(arrays, manifest)``: copies of everything a snapshot holds, taken while the caller
    holds the map still; writing them (:func:`write_capture`) needs no lock."""
    state, meta = m.export_state()
    arrays = {k: _np(v) for k, v in state.items()}
    arrays["occ_ijk"] = arrays["occ_ijk"].astype(np.int64)
    arrays["occ_values"] = arrays["occ_values"].astype(np.int8)
    manifest = {
        "format": FORMAT, "version": VERSION, "feature_dim": meta["feature_dim"],
        "feature_space": meta["feature_space"], "config": to_dict(m.cfg), "counters": meta["counters"],
        "occupancy": meta["occupancy"], "last_fov_deg": meta["last_fov_deg"], "buffers": meta["buffers"],
        "stats": {k: v for k, v in m.stats().items() if k != "timings_ms_total"},
    }
    return arrays, manifest


def fsync_dir(path: str | Path) -> None:
    """Flush a directory's entries (new names, renames) to disk."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes_durably(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` and fsync the file (its directory is the caller's)."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def replace_file_durably(path: str | Path, data: bytes, tmp_name: str) -> None:
    """Replace the file ``path`` with ``data`` atomically and durably: written to ``tmp_name``
    beside it and fsynced, renamed over ``path``, then the directory fsynced."""
    path = Path(path)
    tmp = path.parent / tmp_name
    write_bytes_durably(tmp, data)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def write_capture(capture: tuple[dict[str, np.ndarray], dict], path: str | Path) -> Path:
    """Write a :func:`capture_map` result to the directory ``path``: ``arrays.npz`` and
    ``manifest.json``, each fsynced, then the directory."""
    arrays, manifest = capture
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    tmp = path / "arrays.npz.tmp"
    with open(tmp, "wb") as f:
        np.savez(f, **cast(dict[str, Any], arrays))   # numpy's stub reads a key as allow_pickle
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path / "arrays.npz")
    write_bytes_durably(path / "manifest.json", json.dumps(manifest, indent=2).encode())
    fsync_dir(path)
    return path


def read_manifest(path: str | Path) -> dict:
    path = Path(path)
    mf = path / "manifest.json"
    man = read_document(mf, json.loads, SnapshotError, f"snapshot {path} has no manifest.json",
                        f"snapshot manifest {mf} is not valid JSON")
    if man.get("format") != FORMAT:
        raise SnapshotError(f"{mf} is not a RayFronts map snapshot (format {man.get('format')!r})")
    if man.get("version") != VERSION:
        raise SnapshotError(f"snapshot {path} has format version {man.get('version')!r}; "
                            f"this build reads version {VERSION}")
    return man


def map_config_changes(path: str | Path, cfg: MapConfig) -> dict[str, tuple]:
    """``{key: (snapshot value, cfg value)}`` for every map config key (dotted) in which the
    snapshot at ``path`` (a map directory) differs from the map config ``cfg``."""
    saved = read_manifest(path)["config"]
    want = to_dict(cfg)
    out: dict[str, tuple] = {}

    def walk(a: dict, b: dict, prefix: str) -> None:
        for k in sorted(set(a) | set(b)):
            x, y = a.get(k), b.get(k)
            if isinstance(x, dict) and isinstance(y, dict):
                walk(x, y, f"{prefix}{k}.")
            elif x != y:
                out[f"{prefix}{k}"] = (x, y)

    walk(saved, want, "")
    return out


def load_map(path: str | Path, map_cls: type[RayFrontsMap], device: str | torch.device = "cpu",
             occupancy_backend: str = "auto") -> RayFrontsMap:
    """A ``map_cls`` (:class:`semantic_map.map.RayFrontsMap`, passed in by the caller so this
    module does not import the map) restored from the snapshot at ``path``, with its saved config."""
    from semantic_map.config import MapConfig

    path = Path(path)
    man = read_manifest(path)
    af = path / "arrays.npz"
    if not af.is_file():
        raise SnapshotError(f"snapshot {path} has no arrays.npz")
    try:
        z = dict(np.load(af))
    except Exception as e:  # noqa: BLE001 - any read problem is a snapshot problem
        raise SnapshotError(f"cannot read {af}: {e}") from None
    cfg = merge(MapConfig(), man["config"])
    return map_cls.from_state(cfg, _SavedArrays(z, path), man, device=device, occupancy_backend=occupancy_backend)


class _SavedArrays(dict):
    """A snapshot's arrays by name; a missing one is a :class:`SnapshotError` naming it."""

    def __init__(self, arrays: dict[str, np.ndarray], path: Path) -> None:
        super().__init__(arrays)
        self.path = path

    def __missing__(self, name: str) -> np.ndarray:
        raise SnapshotError(f"snapshot {self.path} lacks array {name!r}")


# --------------------------------------------------------------- generations on disk
#: name prefix of one snapshot generation directory under ``snapshots.dir`` (``snap-<ms>``)
GENERATION_PREFIX = "snap-"


def snapshot_generations(root: str | Path) -> list[Path]:
    """The snapshot generations under ``root``, newest first.

    A generation is a ``snap-<ms>`` directory (written as ``.tmp-snap-<ms>`` and renamed into
    place, so a half-written one never has this name). The ``LATEST`` pointer, when it names
    an existing generation, comes first even if a clock step made its name sort lower; the
    others follow newest name first. Restore tries them in this order and takes the first
    intact one (:func:`check_generation` + a full load), so a corrupt newest snapshot falls
    back to the one before it instead of starting empty.
    """
    root = Path(root)
    if not root.is_dir():
        return []
    gens = sorted((p for p in root.iterdir() if p.name.startswith(GENERATION_PREFIX) and p.is_dir()),
                  key=lambda p: p.name, reverse=True)
    ptr = root / "LATEST"
    if ptr.is_file():
        try:
            latest = root / ptr.read_text().strip()
        except (OSError, UnicodeDecodeError):
            latest = None
        if latest is not None and latest in gens:
            gens.remove(latest)
            gens.insert(0, latest)
    return gens


def check_generation(path: str | Path) -> dict:
    """Cheap structural check of one generation (the files exist, manifests parse); returns
    its ``meta.json``. Raises :class:`SnapshotError` naming what is wrong. The arrays are
    checked when they are loaded (zip CRCs), see :func:`load_map`."""
    path = Path(path)
    for name in ("meta.json", "feature_space.bin", "map/manifest.json", "map/arrays.npz"):
        if not (path / name).is_file():
            raise SnapshotError(f"snapshot {path} lacks {name}")
    try:
        meta = json.loads((path / "meta.json").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SnapshotError(f"snapshot {path}: meta.json is not valid JSON: {e}") from None
    if not isinstance(meta, dict):
        raise SnapshotError(f"snapshot {path}: meta.json is not an object")
    if meta.get("format_version", 1) not in range(1, META_VERSION + 1):
        raise SnapshotError(f"snapshot {path}: meta.json has format_version {meta.get('format_version')!r}; "
                            f"this build reads 1..{META_VERSION}")
    read_manifest(path / "map")
    return meta
