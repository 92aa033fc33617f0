"""Occupancy grid (int8 log-odds voxels): OpenVDB extension or pure-torch backend.

``make_occupancy(vox, lo, hi, backend="auto")`` returns a grid implementing
:class:`semantic_map.occupancy.base.OccupancyGrid`; ``"auto"`` picks ``"vdb"`` when the C++
extension ``semantic_map._vdbocc`` imports and ``"torch"`` otherwise (warning once). Both
backends give identical results. Voxel indices: ``floor(xyz / vox)``
(:func:`common.conventions.voxel_index`).
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from .base import OccupancyGrid
from .torch_backend import TorchOccupancy
from .vdb_backend import VdbOccupancy
from .vdb_backend import available as vdb_available

if TYPE_CHECKING:
    import torch

__all__ = ["OccupancyGrid", "TorchOccupancy", "VdbOccupancy", "make_occupancy",
           "backend_name", "from_state", "vdb_available"]

_log = logging.getLogger(__name__)
_warned = False
BACKENDS = ("auto", "vdb", "torch")


def backend_name(backend: str = "auto") -> str:
    """The concrete backend ``backend`` resolves to ("vdb" or "torch")."""
    global _warned
    if backend not in BACKENDS:
        raise ValueError(f"unknown occupancy backend {backend!r}; use one of {BACKENDS}")
    if backend != "auto":
        return backend
    if vdb_available():
        return "vdb"
    if not _warned:
        from .vdb_backend import IMPORT_ERROR
        _log.warning("OpenVDB occupancy extension not available (%s); using the torch "
                     "backend (same results, slower)", IMPORT_ERROR)
        _warned = True
    return "torch"


def make_occupancy(vox: float, lo: int = -5, hi: int = 30, backend: str = "auto",
                   device: str | torch.device = "cpu") -> OccupancyGrid:
    """New empty occupancy grid with voxel size ``vox`` (m) and clamp bounds [lo, hi]."""
    name = backend_name(backend)
    cls = VdbOccupancy if name == "vdb" else TorchOccupancy
    return cls(vox, lo, hi, device=device)


def from_state(state: dict, backend: str = "auto") -> OccupancyGrid:
    """Grid restored from ``grid.state()`` (any backend's) into ``backend``."""
    for key in ("vox", "lo", "hi", "ijk", "values"):
        if key not in state:
            raise ValueError(f"occupancy state lacks {key!r}")
    g = make_occupancy(state["vox"], state["lo"], state["hi"], backend=backend)
    g.load_state(state)
    return g
