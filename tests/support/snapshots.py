"""A query copy followed over map changes: the setting of the incremental-sync tests
(a default-config map of 20,000 voxels in a 16-d label feature space, built by
``apps.bench.query.build_map``)."""
from __future__ import annotations

from collections.abc import Iterator

import torch

from apps.bench.query import _change, _space, build_map
from semantic_map.query_copy import QueryCopy


class ChangingMap:
    """A map (``map``), its feature space (``fs``) and a :class:`QueryCopy` (``snap``) that
    :meth:`steps` syncs before each step and changes after it."""

    def __init__(self, seed: int = 0, change_seed: int = 3):
        """``seed`` fills the map; ``change_seed`` draws the changes between steps."""
        self.fs = _space(16)
        _, self.map = build_map(20_000, 16, 100, self.fs, seed=seed)
        self.snap = QueryCopy()
        self._g = torch.Generator().manual_seed(change_seed)

    def steps(self, n: int) -> Iterator[int]:
        """Yield steps ``0 .. n-1`` with ``snap`` reserved and synced to the map (``snap.sync(map,
        step)``); after each step one frame's worth of fusion (a few hundred new voxels) and the
        removal of the first 300 voxels (rows move)."""
        for step in range(n):
            self.snap.reserve(self.map)
            self.snap.sync(self.map, step)
            yield step
            _change(self.map, 16, self._g, 28)
            self.map.remove_voxels(self.map.voxel_ijk()[:300])
