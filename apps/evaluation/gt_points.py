"""External semantic ground truth: labelled point clouds, voxelised by majority vote.

Used where the frames carry no labels (NICE-SLAM Replica: the reference evaluates against
external GT point clouds; docs/method.md#evaluation). Files, in the source's world frame (metres):

* ``.npz``: ``xyz`` (N, 3) float, ``labels`` (N,) int (class id, 0 = unlabelled) and
  optionally ``class_names`` (K,) str (index = class id);
* ``.ply`` (ascii, binary little / big endian): the ``vertex`` element's ``x, y, z`` and an
  integer property (``label`` by default) as class id. Elements before ``vertex`` must
  have no list properties (as written by Open3D / trimesh / Habitat exports).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


#: a PLY header element: (name, count, [(property, numpy type code | None for a list property)])
_PlyElement = tuple[str, int, list[tuple[str, str | None]]]


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """The scalar properties of a PLY file's ``vertex`` element: ``{name: (N,) array}``."""
    p = Path(path)
    fmt, elements, body = _read_ply_header(p)
    if fmt == "ascii":
        return _ascii_vertices(p, elements, body)
    return _binary_vertices(p, elements, body, "<" if fmt == "binary_little_endian" else ">")


def _read_ply_header(p: Path) -> tuple[str, list[_PlyElement], bytes]:
    """``(format, elements, body bytes after the header)`` of the PLY file ``p``."""
    raw = p.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{p}: not a PLY file (no 'ply' magic / 'end_header')")
    nl = raw.find(b"\n", end)
    body = raw[nl + 1:]
    elements: list[tuple[str, int, list[tuple[str, str | None]]]]
    fmt, elements = None, []            # [(name, count, [(prop, dtype | None for list)])]
    for line in raw[:end].decode("ascii", "replace").splitlines():
        t = line.split()
        if not t:
            continue
        if t[0] == "format":
            fmt = t[1]
        elif t[0] == "element":
            elements.append((t[1], int(t[2]), []))
        elif t[0] == "property" and elements:
            elements[-1][2].append(_ply_property(p, t))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{p}: unsupported PLY format {fmt!r}")
    return fmt, elements, body


def _ply_property(p: Path, t: list[str]) -> tuple[str, str | None]:
    """``(name, numpy type code)`` of a header ``property`` line's tokens ``t`` (None for a list)."""
    if t[1] == "list":
        return (t[-1], None)
    if t[1] not in _PLY_TYPES:
        raise ValueError(f"{p}: unknown PLY property type {t[1]!r}")
    return (t[2], _PLY_TYPES[t[1]])


def _check_scalar_props(p: Path, name: str, props: list[tuple[str, str | None]]) -> None:
    """Raise unless element ``name`` (read or skipped before the vertices) has only scalar properties."""
    if any(dt is None for _, dt in props):
        if name == "vertex":
            raise ValueError(f"{p}: list properties in the vertex element are not supported")
        raise ValueError(f"{p}: element {name!r} with list properties comes before 'vertex'")


def _ascii_vertices(p: Path, elements: list[_PlyElement], body: bytes) -> dict[str, np.ndarray]:
    """The ``vertex`` properties of an ascii PLY body (one element row per line)."""
    offset = 0
    lines = body.decode("ascii", "replace").splitlines()
    for name, count, props in elements:
        _check_scalar_props(p, name, props)
        if name == "vertex":
            vals = np.loadtxt(lines[offset:offset + count], ndmin=2) if count else np.zeros((0, len(props)))
            if vals.shape[1] < len(props):
                raise ValueError(f"{p}: vertex rows have {vals.shape[1]} values, header declares {len(props)}")
            return {n: vals[:, i].astype(dt) for i, (n, dt) in enumerate(props)}
        offset += count
    raise ValueError(f"{p}: no 'vertex' element")


def _binary_vertices(p: Path, elements: list[_PlyElement], body: bytes, end_c: str) -> dict[str, np.ndarray]:
    """The ``vertex`` properties of a binary PLY body with byte order ``end_c`` (``<`` / ``>``),
    in native byte order."""
    offset = 0
    for name, count, props in elements:
        _check_scalar_props(p, name, props)
        dt = np.dtype([(n, end_c + str(t)) for n, t in props])
        if name == "vertex":
            need = count * dt.itemsize
            if len(body) - offset < need:
                raise ValueError(f"{p}: truncated vertex data ({len(body) - offset} of {need} bytes)")
            arr = np.frombuffer(body, dtype=dt, count=count, offset=offset)
            return {n: arr[n].astype(arr.dtype[n].newbyteorder("=")) for n, _ in props}
        offset += count * dt.itemsize
    raise ValueError(f"{p}: no 'vertex' element")


def load_labelled_points(path: str | Path, label_field: str = "label"
                         ) -> tuple[np.ndarray, np.ndarray, list[str] | None]:
    """``(xyz (N, 3) float64, labels (N,) int64, class_names or None)`` from ``.npz`` / ``.ply``."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"GT point file not found: {p}")
    if p.suffix.lower() == ".npz":
        with np.load(p, allow_pickle=False) as z:
            if "xyz" not in z or "labels" not in z:
                raise ValueError(f"{p}: needs arrays 'xyz' (N, 3) and 'labels' (N,), has {sorted(z.files)}")
            xyz, lab = np.asarray(z["xyz"], np.float64), np.asarray(z["labels"])
            names = [str(n) for n in z["class_names"]] if "class_names" in z else None
    elif p.suffix.lower() == ".ply":
        v = read_ply_vertices(p)
        miss = [k for k in ("x", "y", "z", label_field) if k not in v]
        if miss:
            raise ValueError(f"{p}: vertex element lacks {miss}; has {sorted(v)}")
        xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
        lab, names = v[label_field], None
    else:
        raise ValueError(f"{p}: GT points must be .npz or .ply")
    if xyz.ndim != 2 or xyz.shape[1] != 3 or lab.shape != (xyz.shape[0],):
        raise ValueError(f"{p}: xyz must be (N, 3) and labels (N,), got {xyz.shape} and {lab.shape}")
    if not np.issubdtype(lab.dtype, np.integer):
        if not np.all(np.isfinite(lab)) or np.any(lab != np.round(lab)):
            raise ValueError(f"{p}: labels must be integer class ids")
    return xyz, lab.astype(np.int64), names


def voxelize_labels(xyz: np.ndarray, labels: np.ndarray, vox: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxels holding labelled points (label > 0) and their majority label (ties → the
    smallest id): ``(centres (M, 3) float64, labels (M,) int64)``, voxel = ``floor(xyz / vox)``."""
    from apps.evaluation.data import pack
    from common.conventions import voxel_index

    keep = (labels > 0) & np.isfinite(xyz).all(1)
    xyz, labels = xyz[keep], labels[keep]
    if not len(xyz):
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    ijk = np.asarray(voxel_index(xyz, vox), dtype=np.int64)
    key = pack(ijk)
    pair = np.stack([key, labels], 1)
    up, inv, cnt = np.unique(pair, axis=0, return_inverse=True, return_counts=True)
    order = np.lexsort((up[:, 1], -cnt, up[:, 0]))            # per voxel: most points, then smallest label
    up = up[order]
    first = np.r_[True, up[1:, 0] != up[:-1, 0]]
    best = up[first]
    vk = best[:, 0]
    # voxel centres from one point of each voxel
    _, idx = np.unique(key, return_index=True)
    ijk_u = ijk[idx]
    assert np.array_equal(key[idx], vk)
    return (ijk_u.astype(np.float64) + 0.5) * vox, best[:, 1]
