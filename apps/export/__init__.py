"""``rayfronts export``: the map in standard files (docs/export.md).

Reads the map from a snapshot directory (``--snapshot DIR``) or a running mapper
(``--connect ENDPOINT``: it saves a snapshot now, :mod:`apps.export.source`) and writes one
format:

* ``ply``: the semantic voxels, binary little-endian PLY: ``x, y, z`` float32 (voxel centres,
  metres, map frame), ``red, green, blue`` uchar; ``--query TEXT`` adds a float ``score`` (that
  query's cosine score per voxel, as the mapper scores it), ``--label TEXT`` (repeated) an int
  ``label`` (the index of the best-scoring label);
* ``vdb``: the occupancy as OpenVDB standard grids (FloatGrid ``log_odds``, BoolGrid ``occupied``);
* ``map_server``: a PGM + YAML of the z band ``[--z-min, --z-max]`` as Nav2's map_server loads
  them (trinary), equal to the mapper's ``occupancy_slice`` of that band;
* ``snapshot``: a snapshots directory (``LATEST`` + ``snap-<ms>/``) a mapper restores from.

The loaded map's pending accumulation buffers are processed first (as the mapper's idle
flush does), except for ``snapshot``, which keeps them as saved. Bad input (missing
snapshot, empty map, unwritable ``--out``, options that do not fit the format) is one line
and exit code 2; a mapper asked for its map keeps running.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from apps.export.source import Source, UserError

if TYPE_CHECKING:
    from semantic_map.map import RayFrontsMap

HELP = "write the map as standard files: PLY voxels, OpenVDB occupancy, Nav2 map_server PGM + YAML, snapshot"
FORMATS = ("ply", "vdb", "map_server", "snapshot")
#: default z band (m) of map_server, the mapper's ``ros.costmap_z_band``
DEFAULT_Z_BAND = (0.2, 1.5)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--connect", metavar="ENDPOINT", default=None,
                     help="a running mapper's Zenoh endpoint (it saves a snapshot now, which must be readable here)")
    src.add_argument("--snapshot", metavar="DIR", default=None,
                     help="a mapper's snapshots.dir, one snap-<ms> generation, or its map/ directory")
    parser.add_argument("--format", required=True, choices=FORMATS, help="what to write (docs/export.md)")
    parser.add_argument("--out", "-o", required=True, metavar="PATH",
                        help="the file to write (ply: .ply, vdb: .vdb, map_server: the .yaml, its .pgm beside it; "
                             "snapshot: a directory)")
    parser.add_argument("--query", metavar="TEXT", default=None,
                        help="ply: add a float 'score' per voxel, this text query's cosine score")
    parser.add_argument("--label", metavar="TEXT", action="append", default=None,
                        help="ply (repeat for each label): add an int 'label', the index of the best-scoring label")
    parser.add_argument("--z-min", type=float, default=DEFAULT_Z_BAND[0],
                        help=f"map_server: bottom of the z band, metres (default {DEFAULT_Z_BAND[0]})")
    parser.add_argument("--z-max", type=float, default=DEFAULT_Z_BAND[1],
                        help=f"map_server: top of the z band, metres (default {DEFAULT_Z_BAND[1]})")
    parser.add_argument("--stride", type=int, default=1,
                        help="map_server: map voxels per cell side (cell = stride x voxel size; default 1)")
    parser.add_argument("--prefix", default=None, help="--connect: key-space prefix (default rayfronts)")
    parser.add_argument("--timeout", type=float, default=60.0,
                        help="--connect: seconds to wait for the mapper's snapshot (default 60)")
    parser.add_argument("--text-model-dir", default="",
                        help="--query / --label: directory of the text model when the feature space needs one on disk")


def _check_options(args: argparse.Namespace) -> None:
    if (args.query is not None or args.label) and args.format != "ply":
        raise UserError(f"--query / --label add PLY properties; they do not apply to --format {args.format}")
    if args.query is not None and not args.query.strip():
        raise UserError("--query is empty: give the text whose scores to add")
    if args.label and not all(t.strip() for t in args.label):
        raise UserError("--label is empty: give one label text per --label")
    if not (math.isfinite(args.z_min) and math.isfinite(args.z_max)) or args.z_max < args.z_min:
        raise UserError(f"bad z band [--z-min {args.z_min}, --z-max {args.z_max}]: need finite z-min <= z-max")
    if args.stride < 1:
        raise UserError(f"--stride must be >= 1, got {args.stride}")


def check_writable(out: Path, directory: bool = False) -> None:
    """A :class:`UserError` unless ``out`` can be written (a file, or with ``directory`` a
    snapshots directory): its parent exists and takes a new file (tried, so a read-only file
    system fails here too, before the map is loaded)."""
    parent = out if (directory and out.is_dir()) else out.parent
    what = "--out"
    if out.is_dir() and not directory:
        raise UserError(f"{what} {out} is a directory; give a file name")
    if out.exists() and directory and not out.is_dir():
        raise UserError(f"{what} {out} is a file; --format snapshot writes a directory")
    if not parent.is_dir():
        raise UserError(f"{what} {out}: directory {parent} does not exist (create it or choose another --out)")
    probe = parent / f".rayfronts-export-probe-{os.getpid()}"
    try:
        probe.touch()
        probe.unlink()
    except OSError as e:
        raise UserError(f"{what} {out} is not writable ({e.strerror or e}); choose another --out") from None


def _source(args: argparse.Namespace) -> Source:
    from apps.export import source

    if args.snapshot is not None:
        return source.from_snapshot_dir(args.snapshot)
    return source.from_mapper(args.connect, args.prefix, args.timeout)


def voxel_scores(m: RayFrontsMap, src: Source, texts: list[str], model_dir: str = "") -> np.ndarray:
    """(len(texts), N) float32 cosine score of each text query per semantic voxel, in the order
    of :func:`mapper.service_map.voxel_arrays`, computed as the mapper scores a query
    (:func:`mapper.query_answer.embed_text` with the "auto" templates, :func:`scores_for`)."""
    from mapper.query_answer import embed_text, scores_for

    fs = src.feature_space()
    feats = m.voxels().features
    return np.stack([scores_for(fs, feats, embed_text(fs, t, "cpu", model_dir), False, None) for t in texts])


def export_ply(m: RayFrontsMap, src: Source, out: Path, args: argparse.Namespace) -> str:
    from apps.export.formats import ply_bytes, write_atomically
    from mapper.service_map import voxel_arrays

    if m.n_voxels() == 0:
        raise UserError(f"the map of {src.origin} has no semantic voxels yet (empty map): nothing to export")
    xyz, _, rgb = voxel_arrays(m)
    extra: dict[str, np.ndarray] = {}
    comments = [f"rayfronts export of {src.origin}", "frame map, metres, z up; x y z = voxel centres",
                f"vox_size {float(m.cfg.vox_size)!r}"]
    texts = ([args.query] if args.query is not None else []) + list(args.label or [])
    if texts:
        sc = voxel_scores(m, src, texts, args.text_model_dir)
        if args.query is not None:
            extra["score"] = sc[0].astype(np.float32)
            comments.append(f"score = cosine score of query: {args.query}")
        if args.label:
            extra["label"] = sc[1 if args.query is not None else 0:].argmax(0).astype(np.int32)
            comments += [f"label {i} {t}" for i, t in enumerate(args.label)]
    data = ply_bytes(xyz, rgb, extra, tuple(comments))
    write_atomically(out, lambda p: p.write_bytes(data))
    return f"{len(xyz)} voxels"


def _observed(m: RayFrontsMap, src: Source) -> dict:
    st = m.occupancy_view().state()
    if not (np.asarray(st["values"]) != 0).any():
        raise UserError(f"the map of {src.origin} has no observed occupancy yet (empty map): nothing to export")
    return st


def export_vdb(m: RayFrontsMap, src: Source, out: Path, args: argparse.Namespace) -> str:
    from apps.export.formats import write_atomically
    from semantic_map.occupancy.vdb_backend import available, write_standard_grids

    if not available():
        raise UserError("--format vdb needs the OpenVDB extension semantic_map._vdbocc, which is not built here "
                        "(install libopenvdb-dev and reinstall)")
    st = _observed(m, src)
    write_atomically(out, lambda p: write_standard_grids(p, st))
    return f"{int((np.asarray(st['values']) != 0).sum())} observed voxels"


def export_map_server(m: RayFrontsMap, src: Source, out: Path, args: argparse.Namespace) -> str:
    """PGM + YAML of the slice over the xy extent of the observed voxels."""
    from apps.export.formats import map_server_yaml, pgm_bytes, pgm_pixels, write_atomically
    from planning.occupancy_queries import costmap_slice

    st = _observed(m, src)
    ijk = np.asarray(st["ijk"])[np.asarray(st["values"]) != 0]
    vox = float(st["vox"])
    lo, hi = (ijk[:, :2].min(0) + 0.5) * vox, (ijk[:, :2].max(0) + 0.5) * vox  # centres of the end voxels
    try:
        states, origin, cell = costmap_slice(m.occupancy_view(), vox, lo, hi, (args.z_min, args.z_max), args.stride)
    except ValueError as e:
        raise UserError(f"{e} (--stride)") from None
    pgm = out.with_suffix(".pgm")
    text = map_server_yaml(pgm.name, cell, origin, (f"rayfronts export of {src.origin}",
                                                   f"z band [{args.z_min}, {args.z_max}] m, map frame"))
    data = pgm_bytes(pgm_pixels(states))
    write_atomically(pgm, lambda p: p.write_bytes(data))
    write_atomically(out, lambda p: p.write_text(text))
    return f"{states.shape[0]}x{states.shape[1]} cells of {cell} m, image {pgm}"


def export_snapshot(m: RayFrontsMap, src: Source, out: Path, args: argparse.Namespace) -> str:
    """A new generation under ``out`` (``LATEST`` names it; existing generations stay)."""
    from mapper.snapshot import capture_map
    from mapper.snapshot_store import write_snapshot

    env = src.space_envelope()
    if env is None:
        raise UserError(f"{src.origin} is a bare map directory without feature_space.bin; --format snapshot "
                        "needs a whole generation (the directory holding meta.json and map/)")
    meta = dict(src.meta) or {"frames_mapped": int(m.schedule_counters().get("frames", 0))}
    path = write_snapshot(out, capture_map(m), env, meta, keep=1 << 30)
    return f"generation {path.name}"


EXPORTS = {"ply": export_ply, "vdb": export_vdb, "map_server": export_map_server, "snapshot": export_snapshot}


def run(args: argparse.Namespace) -> int:
    from apps.export.source import load

    _check_options(args)
    out = Path(args.out)
    check_writable(out, directory=args.format == "snapshot")
    if args.format == "map_server" and out.suffix != ".yaml":
        raise UserError(f"--out {out}: --format map_server writes the map's YAML; give a .yaml name "
                        "(the .pgm goes beside it)")
    src = _source(args)
    m = load(src)
    if args.format != "snapshot":
        m.flush()
    what = EXPORTS[args.format](m, src, out, args)
    print(f"wrote {out} ({args.format}: {what})")
    return 0
