"""Independent readers of the files ``rayfronts export`` writes, run as a child process of
Debian's own Python (``/usr/bin/python3``), where Debian's ``python3-openvdb`` (OpenVDB's
Python module) and ``python3-meshio`` live (deploy/setup_dev.sh installs them with the test
extra). Imports nothing of ours.

``/usr/bin/python3 standard_readers.py ply FILE OUT.npz``: meshio's PLY reader; ``points``,
one array per vertex property.
``/usr/bin/python3 standard_readers.py vdb FILE OUT.npz``: ``pyopenvdb.readAll``; per grid
``<name>_ijk`` (M, 3) and ``<name>_value`` (M,) of every active value (tiles expanded),
``<name>_world`` (the world position of index (1, 2, 3)), ``<name>_meta`` (JSON of the
grid's metadata), ``<name>_type``.
"""
import json
import sys

import numpy as np


def read_ply(path, out):
    import meshio

    m = meshio.read(path, file_format="ply")
    np.savez(out, points=np.asarray(m.points), **{k: np.asarray(v) for k, v in m.point_data.items()})


def read_vdb(path, out):
    import pyopenvdb as vdb

    grids, _ = vdb.readAll(path)
    arrays = {}
    for g in grids:
        ijk, val = [], []
        for it in g.citerOnValues():  # voxels and active tiles
            lo, hi = np.array(it.min), np.array(it.max)
            cells = np.stack(np.meshgrid(*[np.arange(lo[a], hi[a] + 1) for a in range(3)], indexing="ij"), -1)
            ijk.append(cells.reshape(-1, 3))
            val.append(np.full(len(ijk[-1]), it.value))
        arrays[g.name + "_ijk"] = np.concatenate(ijk) if ijk else np.zeros((0, 3), int)
        arrays[g.name + "_value"] = np.concatenate(val) if val else np.zeros(0)
        arrays[g.name + "_world"] = np.array(g.transform.indexToWorld((1, 2, 3)))
        arrays[g.name + "_meta"] = np.array(json.dumps({k: (list(v) if isinstance(v, tuple) else v)
                                                        for k, v in dict(g.metadata).items()}, default=str))
        arrays[g.name + "_type"] = np.array(type(g).__name__)
    arrays["names"] = np.array([g.name for g in grids])
    np.savez(out, **arrays)


if __name__ == "__main__":
    {"ply": read_ply, "vdb": read_vdb}[sys.argv[1]](sys.argv[2], sys.argv[3])
