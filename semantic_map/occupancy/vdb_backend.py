"""OpenVDB occupancy grid: a thin wrapper around the ``semantic_map._vdbocc`` C++ extension.

The extension owns an ``openvdb::Grid<Tree4<int8_t, 5, 4, 3>>`` (background 0). This
wrapper validates inputs (the same checks as the torch backend), converts them to the
contiguous int32 / float64 numpy arrays the extension takes, and sorts outputs so that
both backends return identical tensors.
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch

from ._inputs import as_ijk, as_inc, check_bounds, check_frontier_args, check_tolerance, pack, prepare_rays
from .base import BBox, ChangeLog, GridInput

try:  # the extension is optional (built only where OpenVDB was found)
    from semantic_map import _vdbocc  # type: ignore[attr-defined]
    IMPORT_ERROR: Exception | None = None
except ImportError as e:  # pragma: no cover - depends on the build
    _vdbocc = None
    IMPORT_ERROR = e


def available() -> bool:
    """True if the OpenVDB extension imported."""
    return _vdbocc is not None


def _np_i32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.numpy().astype(np.int32, copy=False))


def _sorted(ijk: np.ndarray, *cols):
    t = torch.from_numpy(np.asarray(ijk, dtype=np.int64).reshape(-1, 3))
    order = torch.argsort(pack(t))
    return (t[order],) + tuple(torch.from_numpy(np.asarray(c))[order] for c in cols)


class VdbOccupancy:
    """Occupancy grid stored in OpenVDB. See :class:`semantic_map.occupancy.base.OccupancyGrid`."""

    backend = "vdb"

    def __init__(self, vox: float, lo: int = -5, hi: int = 30, device: str | torch.device = "cpu",
                 _grid: Any = None) -> None:
        if _vdbocc is None:
            raise ImportError(f"the OpenVDB occupancy extension semantic_map._vdbocc is not built "
                              f"({IMPORT_ERROR}); install libopenvdb-dev libboost-iostreams-dev "
                              f"and re-run `pip install -e .`, or use backend='torch'")
        self.vox, self.lo, self.hi = check_bounds(vox, lo, hi)
        torch.device(device)  # validates the name; the OpenVDB grid always lives on the CPU
        self.device = torch.device("cpu")
        self._g = _grid if _grid is not None else _vdbocc.Grid(self.vox, self.lo, self.hi)
        self.revision = 0  # counts calls that may change values (update, prune, load_state)
        self.changes = ChangeLog()

    @property
    def num_active(self) -> int:
        return int(self._g.num_active)

    @property
    def leaf_count(self) -> int:
        return int(self._g.leaf_count)

    @property
    def tile_count(self) -> int:
        """Active tiles (pruned nodes) at any level."""
        return int(self._g.tile_count)

    def memory_bytes(self) -> int:
        return int(self._g.mem_bytes())

    def update(self, ijk: GridInput, inc: GridInput | int) -> None:
        ijk = as_ijk(ijk)
        inc = as_inc(inc, ijk.shape[0])
        if ijk.shape[0]:
            self.revision += 1
            self.changes.add(ijk)
            self._g.update(_np_i32(ijk), _np_i32(inc))

    def query(self, ijk: GridInput) -> torch.Tensor:
        ijk = as_ijk(ijk)
        if ijk.shape[0] == 0:
            return torch.empty(0, dtype=torch.int8)
        return torch.from_numpy(np.asarray(self._g.query(_np_i32(ijk))))

    def frontiers(self, min_unobserved: int, min_free: int, min_occupied: int = 0,
                  radius: int = 1, bbox: BBox | None = None) -> torch.Tensor:
        (mu, mf, mo), r, bbox = check_frontier_args(min_unobserved, min_free, min_occupied,
                                                    radius, bbox)
        use_bbox = bbox is not None
        bmin = tuple(bbox[0]) if bbox is not None else (0, 0, 0)
        bmax = tuple(bbox[1]) if bbox is not None else (0, 0, 0)
        out = self._g.frontiers(mu, mf, mo, r, use_bbox, bmin, bmax)
        return _sorted(out)[0]

    def prune(self, tolerance: int) -> None:
        tol = check_tolerance(tolerance)
        self.revision += 1
        self.changes.everything()
        self._g.prune(tol)

    def active(self) -> tuple[torch.Tensor, torch.Tensor]:
        ijk, vals = self._g.active()
        return _sorted(ijk, vals)

    def occupied(self) -> np.ndarray:
        ijk, vals = self._g.active()
        return np.asarray(ijk)[np.asarray(vals) > 0].astype(np.int64)

    def first_blocked(self, origins: GridInput, directions: GridInput, max_dist: float) -> torch.Tensor:
        o, d, v, max_dist = prepare_rays(origins, directions, max_dist, self.vox)
        if o.shape[0] == 0:
            return torch.empty(0, dtype=torch.float64)
        res = self._g.first_blocked(o.numpy(), d.numpy(), _np_i32(v), max_dist)
        return torch.from_numpy(np.asarray(res))

    def state(self) -> dict:
        ijk, vals = self.active()
        return {"vox": self.vox, "lo": self.lo, "hi": self.hi,
                "ijk": ijk.numpy(), "values": vals.numpy()}

    def load_state(self, state: dict) -> None:
        """Replace the map by ``state`` (see :meth:`state`); tiles come back as voxels."""
        ijk = as_ijk(state["ijk"], "state['ijk']")
        vals = torch.as_tensor(np.asarray(state["values"])).reshape(-1)
        if vals.shape[0] != ijk.shape[0]:
            raise ValueError("state: 'ijk' and 'values' lengths differ")
        if vals.numel() and (int(vals.min()) < -128 or int(vals.max()) > 127):
            raise ValueError("state: values must fit int8")
        keys = pack(ijk)
        if keys.numel() > 1 and torch.unique(keys).numel() != keys.numel():
            raise ValueError("state: duplicate voxel indices")
        g = _vdbocc.Grid(self.vox, self.lo, self.hi)
        if ijk.shape[0]:
            g.set_values(_np_i32(ijk), np.ascontiguousarray(vals.numpy().astype(np.int8)))
        self._g = g
        self.revision += 1
        self.changes.everything()

    def save(self, path: str | os.PathLike) -> None:
        """Write the grid (tiles included) to an OpenVDB ``.vdb`` file."""
        self._g.save(os.fspath(path))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "VdbOccupancy":
        """Read a grid written by :meth:`save` (clamp bounds are stored as metadata)."""
        if _vdbocc is None:
            raise ImportError(f"semantic_map._vdbocc is not built ({IMPORT_ERROR})")
        path = os.fspath(path)
        if not os.path.exists(path):
            raise FileNotFoundError(path)
        g = _vdbocc.Grid.load(path)
        return cls(g.vox, g.lo, g.hi, _grid=g)


#: what the ``convention`` metadata of :func:`write_standard_grids`' grids says
STANDARD_CONVENTION = ("rayfronts occupancy: map frame, metres, z up; index (i,j,k) is the centre of the map voxel "
                       "covering [ijk*vox, (ijk+1)*vox); log_odds: int8 log-odds as float, > 0 occupied, < 0 free, "
                       "inactive = unknown; occupied: true where log_odds > 0")


def write_standard_grids(path: str | os.PathLike, state: dict) -> None:
    """Write an occupancy ``state`` (:meth:`VdbOccupancy.state` of either backend) to the ``.vdb``
    file ``path`` as OpenVDB's standard grid types, which OpenVDB's own tools and Python
    module read: a ``FloatGrid`` "log_odds" (the int8 log-odds as float, active where
    observed, i.e. value != 0) and a ``BoolGrid`` "occupied" (true where > 0). Transform:
    voxel size ``vox`` metres, index (i, j, k) at the voxel centre ``(ijk + 0.5) * vox``; grid
    metadata ``occ_lo``, ``occ_hi``, ``voxel_size_m`` and ``convention``
    (:data:`STANDARD_CONVENTION`)."""
    if _vdbocc is None:
        raise ImportError(f"the OpenVDB extension semantic_map._vdbocc is not built ({IMPORT_ERROR})")
    ijk = np.ascontiguousarray(np.asarray(state["ijk"]).reshape(-1, 3).astype(np.int32))
    vals = np.ascontiguousarray(np.asarray(state["values"]).reshape(-1).astype(np.int8))
    _vdbocc.write_standard(os.fspath(path), ijk, vals, float(state["vox"]), int(state["lo"]), int(state["hi"]),
                           STANDARD_CONVENTION)
