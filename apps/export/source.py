"""Where ``rayfronts export`` reads the map: a snapshot on disk or a running mapper.

A snapshot path may be a snapshots root (``LATEST`` + ``snap-<ms>/``: the newest intact
generation is taken, as the mapper's restore does), one generation (``meta.json``,
``feature_space.bin``, ``map/``) or a bare map directory (``manifest.json`` + ``arrays.npz``;
without the feature space, so no ``--query`` / ``--label``). From a running mapper the
export asks it to save a snapshot now (the ``<prefix>/mapper/snapshot`` queryable,
:meth:`query_client.Client.snapshot`) and reads that generation, which must therefore be
readable here (same machine or a shared directory); the mapper keeps running.
Layout: [docs/snapshot_format.md](../../docs/snapshot_format.md).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from semantic_map.map import RayFrontsMap


class UserError(ValueError):
    """A bad export request (exit code 2, one line naming what to set)."""


@dataclass
class Source:
    """One generation to export: its map directory, and when known its generation directory
    (``meta.json``, ``feature_space.bin``) and where it came from (for messages)."""

    map_dir: Path
    generation: Path | None
    origin: str
    meta: dict = field(default_factory=dict)

    def space_envelope(self) -> bytes | None:
        """The ``rayfronts.feature_space`` message the map was built in (None: bare map dir)."""
        if self.generation is None:
            return None
        return (self.generation / "feature_space.bin").read_bytes()

    def feature_space(self) -> FeatureSpace:
        """The decoded feature space (for query scores); a :class:`UserError` without one."""
        from common.feature_space import FeatureSpace
        from common.messages import decode_feature_space

        env = self.space_envelope()
        if env is None:
            raise UserError(f"{self.origin} is a bare map directory without feature_space.bin: --query / --label "
                            "need a whole snapshot generation (the directory holding meta.json and map/)")
        _, body = decode_feature_space(env)
        return FeatureSpace.from_body(body)


def from_snapshot_dir(path: str | Path) -> Source:
    """The generation to read under ``path`` (module docstring); :class:`UserError` when there
    is none, a ``SnapshotError`` when the one found is broken."""
    p = Path(path)
    if not p.is_dir():  # checked before the map's modules (torch) load: the error comes at once
        raise UserError(f"snapshot directory {p} does not exist (set --snapshot to a snapshots.dir, "
                        "one snap-<ms> generation or its map/ directory)")
    from mapper.snapshot import SnapshotError, check_generation, read_manifest, snapshot_generations

    if (p / "manifest.json").is_file():
        read_manifest(p)
        return Source(p, None, str(p))
    if (p / "map").is_dir():
        return Source(p / "map", p, str(p), check_generation(p))
    errors = []
    for gen in snapshot_generations(p):
        try:
            return Source(gen / "map", gen, str(gen), check_generation(gen))
        except SnapshotError as e:  # a broken newest generation: fall back, as the mapper's restore does
            errors.append(str(e))
    if errors:
        raise SnapshotError(f"no intact snapshot generation in {p}: {'; '.join(errors)}")
    raise UserError(f"{p} holds no snapshot (no LATEST / snap-<ms>/, meta.json + map/, or manifest.json); "
                    "set --snapshot to a mapper's snapshots.dir")


def from_mapper(connect: str, prefix: str | None, timeout: float) -> Source:
    """Ask the mapper at ``connect`` to save a snapshot now and return it (module docstring)."""
    from query_client import Client, QueryError

    with Client(connect=connect, prefix=prefix, timeout=timeout) as c:
        try:
            info = c.snapshot(save=True, timeout=timeout)
        except QueryError as e:
            if "no map yet" in str(e):
                raise UserError(f"the mapper at {connect} has an empty map (no frames mapped yet): nothing to "
                                "export; try again once an edge has sent frames") from None
            raise
    path = Path(str(info.get("path", "")))
    if not (path / "map").is_dir():
        raise UserError(f"the mapper saved its snapshot to {path} on its own machine, which is not readable "
                        "here; run the export there or copy that directory and use --snapshot")
    meta = json.loads((path / "meta.json").read_text())
    return Source(path / "map", path, f"mapper {connect} snapshot {path}", meta)


def load(src: Source, backend: str = "auto") -> RayFrontsMap:
    """The map of ``src`` (``load_map``: the saved config, occupancy ``backend``)."""
    from mapper.snapshot import load_map
    from semantic_map.map import RayFrontsMap

    return load_map(src.map_dir, RayFrontsMap, occupancy_backend=backend)
