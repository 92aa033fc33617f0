"""The file formats of ``rayfronts export`` (docs/export.md): PLY voxels, Nav2 map_server
PGM + YAML, and the helpers that write a file atomically. OpenVDB grids are written by the
C++ extension (:func:`semantic_map.occupancy.vdb_backend.write_standard_grids`).

Conventions: the map (world) frame, metres, z up; voxel ``ijk`` covers
``[ijk·vox, (ijk+1)·vox)`` (docs/conventions.md).
"""
from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from planning.occupancy_queries import FREE, OCCUPIED

#: map_server trinary pixel values (negate 0): occupied black, free white, unknown grey
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
#: map_server thresholds on occ = (255 - pixel) / 255: 0 -> 1.0 occupied, 254 -> 0.004 free,
#: 205 -> 0.196078 between them (unknown); the values ROS map_saver writes
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196

#: PLY type names of the numpy dtypes written
_PLY_TYPES = {np.dtype("<f4"): "float", np.dtype("u1"): "uchar", np.dtype("<i4"): "int"}


def write_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path`` and rename it over ``path``
    (a failed write leaves no half file; the temporary one is removed)."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def ply_bytes(xyz: np.ndarray, rgb: np.ndarray, extra: dict[str, np.ndarray] | None = None,
              comments: tuple[str, ...] = ()) -> bytes:
    """A binary little-endian PLY with one ``vertex`` element: ``x, y, z`` float32 (metres),
    ``red, green, blue`` uchar, then each ``extra`` column (float32 or int32) in order;
    ``comments`` go into the header (one line each)."""
    n = len(xyz)
    cols: list[tuple[str, np.ndarray, str]] = [(a, xyz[:, i], "<f4") for i, a in enumerate("xyz")]
    cols += [(c, rgb[:, i], "u1") for i, c in enumerate(("red", "green", "blue"))]
    for name, v in (extra or {}).items():
        cols.append((name, v, "<i4" if np.issubdtype(np.asarray(v).dtype, np.integer) else "<f4"))
    dt = np.dtype([(name, t) for name, _, t in cols])
    rows = np.empty(n, dt)
    for name, v, _ in cols:
        rows[name] = np.asarray(v).reshape(n)
    head = ["ply", "format binary_little_endian 1.0"]
    head += [f"comment {' '.join(c.split())}" for c in comments]
    head.append(f"element vertex {n}")
    head += [f"property {_PLY_TYPES[np.dtype(t)]} {name}" for name, _, t in cols]
    head.append("end_header")
    return ("\n".join(head) + "\n").encode("ascii", "replace") + rows.tobytes()


def pgm_pixels(states: np.ndarray) -> np.ndarray:
    """(height, width) uint8 image of a costmap slice ``states`` (nx, ny) (FREE / OCCUPIED /
    UNKNOWN): column = x cell, row 0 = the highest y cell (an image's top row, as map_server
    reads it: its last row is the cell at ``origin``)."""
    pix = np.full(states.shape, PGM_UNKNOWN, np.uint8)
    pix[states == OCCUPIED] = PGM_OCCUPIED
    pix[states == FREE] = PGM_FREE
    return np.ascontiguousarray(pix.T[::-1])


def pgm_bytes(pix: np.ndarray) -> bytes:
    """Binary PGM (P5, maxval 255) of a (height, width) uint8 image."""
    h, w = pix.shape
    return f"P5\n{w} {h}\n255\n".encode("ascii") + np.ascontiguousarray(pix, np.uint8).tobytes()


def map_server_yaml(image: str, resolution: float, origin_xy: np.ndarray, comments: tuple[str, ...] = ()) -> str:
    """The YAML map_server loads with ``image`` (a file name beside it): trinary mode,
    ``resolution`` metres per cell, ``origin`` [x, y, yaw] of the lower-left cell's corner."""
    lines = [f"# {' '.join(c.split())}" for c in comments]
    lines += [f"image: {image}", "mode: trinary", f"resolution: {float(resolution)!r}",
              f"origin: [{float(origin_xy[0])!r}, {float(origin_xy[1])!r}, 0.0]", "negate: 0",
              f"occupied_thresh: {OCCUPIED_THRESH}", f"free_thresh: {FREE_THRESH}"]
    return "\n".join(lines) + "\n"
