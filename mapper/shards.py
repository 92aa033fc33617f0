"""Mapper shards: several mapper processes, each owning a part of the world, one query
answered by all of them (``common.fleet``, ``query_client.merge``).

A shard owns a region — a bounding box (``shard.region``), a set of square tiles
(``shard.tile_m`` + ``shard.tiles``), both, or neither — and optionally a list of robots
(``shard.robots``). A frame belongs to a shard when its robot is one of the shard's (or the
list is empty) and its **camera centre**, in the map's world frame (after
``world_from_robot``), lies in the region: each shard integrates whole frames, so its map
is exactly what one mapper would build from those frames, including the free space and the
semantic rays beyond range (cutting frames into parts would cut rays and free-space
carving at the border). Shards should own disjoint regions that together cover where the
robots go; a frame in no shard's region is mapped by none (counted as ``outside_shard``
in each shard's stats, not as a reject). Objects seen from both sides of a border appear in
both shards' maps; the client joins their clusters.

Decisions: the region test is on the camera centre, half-open boxes ``[min, max)``, tiles
``(floor(x / tile_m), floor(y / tile_m))`` written ``"i,j"``; every shard serves
``mapper/query`` (one get reaches them all) and attaches its shard info to the reply.
With ``shard.tile_m`` a shard subscribes only to the tile-routed frame keys of its tiles
plus a halo (:meth:`ShardFilter.subscription_tiles`, docs/key_space.md#shards); edge tiles
are in the robot's own pose frame, this filter stays in the map's world frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from common.config import ConfigError, field_
from common.keys import is_valid_id


@dataclass
class ShardSection:
    """This mapper as one shard of several (mapper config section ``shard``)."""

    name: str = field_("", "shard name ([A-Za-z0-9_-]); empty = not sharded (this mapper maps every frame)")
    region: list[float] = field_([], "bounding box of the camera centres this shard maps, [xmin, ymin, xmax, ymax] "
                                     "or [xmin, ymin, zmin, xmax, ymax, zmax] (m, map world frame); empty = no box")
    tile_m: float = field_(0.0, "tile size (m) of shard.tiles; 0 = no tiles")
    tiles: list[str] = field_([], "tiles this shard maps, 'i,j' = floor(x / tile_m), floor(y / tile_m) of the "
                                  "camera centre; empty = no tile restriction")
    robots: list[str] = field_([], "robots whose frames this shard maps; empty = every robot")
    halo_tiles: int = field_(1, "with shard.tile_m > 0: subscribe to the tile-routed frame keys of the shard's "
                                "tiles (shard.tiles, or the tiles shard.region covers) plus this many tiles "
                                "around them; edges publish with publish.tile_m = shard.tile_m")


#: a shard subscribing to more tile keys than this subscribes to every frame instead
MAX_TILE_SUBSCRIPTIONS = 1024


class ShardFilter:
    """Which frames a shard maps (see module doc); ``accepts`` is cheap (per frame)."""

    def __init__(self, cfg: ShardSection):
        self.name = cfg.name
        if cfg.name and not is_valid_id(cfg.name):
            raise ConfigError(f"shard.name {cfg.name!r}: use 1-64 characters from [A-Za-z0-9_-]")
        r = [float(v) for v in cfg.region]
        if len(r) == 4:
            r = [r[0], r[1], -math.inf, r[2], r[3], math.inf]
        if r and (len(r) != 6 or not all(lo < hi for lo, hi in zip(r[:3], r[3:], strict=True))):
            raise ConfigError(f"shard.region must be [xmin, ymin, xmax, ymax] or 6 values with min < max, "
                              f"got {list(cfg.region)}")
        self.lo = np.array(r[:3]) if r else None
        self.hi = np.array(r[3:]) if r else None
        self.tile_m = float(cfg.tile_m)
        self.tiles: set[tuple[int, int]] = set()
        for t in cfg.tiles:
            try:
                i, j = (int(v) for v in str(t).split(","))
            except ValueError:
                raise ConfigError(f"shard.tiles: {t!r} is not 'i,j' (two integers)") from None
            self.tiles.add((i, j))
        if self.tiles and self.tile_m <= 0:
            raise ConfigError("shard.tiles needs shard.tile_m > 0")
        for rb in cfg.robots:
            if not is_valid_id(rb):
                raise ConfigError(f"shard.robots: invalid robot id {rb!r}")
        self.robots = set(cfg.robots)

    @property
    def active(self) -> bool:
        return bool(self.name) or self.lo is not None or bool(self.tiles) or bool(self.robots)

    def subscription_tiles(self, cfg: ShardSection) -> set[tuple[int, int]] | None:
        """Tiles whose frame keys this shard subscribes to (``frames_tile_all``), or ``None`` for
        every frame (no ``tile_m``, no tiles and no finite x/y region, or more than
        ``MAX_TILE_SUBSCRIPTIONS`` tiles). Tiles: ``shard.tiles``, else those the region's x/y
        box covers, grown by ``shard.halo_tiles`` on every side. Edges tile in their robot's own
        pose frame (docs/key_space.md#shards)."""
        if self.tile_m <= 0:
            return None
        t, h = self.tile_m, max(0, int(cfg.halo_tiles))
        if self.tiles:
            base = set(self.tiles)
        elif self.lo is not None and np.all(np.isfinite(self.lo[:2])) and np.all(np.isfinite(self.hi[:2])):
            i0, j0 = math.floor(self.lo[0] / t), math.floor(self.lo[1] / t)
            i1, j1 = math.ceil(self.hi[0] / t) - 1, math.ceil(self.hi[1] / t) - 1
            if (i1 - i0 + 1 + 2 * h) * (j1 - j0 + 1 + 2 * h) > MAX_TILE_SUBSCRIPTIONS:
                return None
            base = {(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)}
        else:
            return None
        out = {(i + di, j + dj) for i, j in base for di in range(-h, h + 1) for dj in range(-h, h + 1)}
        return out if len(out) <= MAX_TILE_SUBSCRIPTIONS else None

    def tile_of(self, xyz: Sequence[float] | np.ndarray) -> tuple[int, int]:
        return (math.floor(float(xyz[0]) / self.tile_m), math.floor(float(xyz[1]) / self.tile_m))

    def accepts(self, robot: str, pose_world: np.ndarray) -> bool:
        """True when this shard maps a frame of ``robot`` taken at ``pose_world`` (4×4, map frame)."""
        if self.robots and robot not in self.robots:
            return False
        c = np.asarray(pose_world, np.float64)[:3, 3]
        if self.lo is not None and not (np.all(c >= self.lo) and np.all(c < self.hi)):
            return False
        if self.tiles and self.tile_of(c) not in self.tiles:
            return False
        return True
