"""Mapper shards: several mapper processes, each owning a part of the world, one query
answered by all of them (``common.robot_messages``, ``query_client.merge``).

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

Routing without flags: a named shard announces what it owns (``common.shard_routing``) on
``<p>/mapper/shards/<name>/routing``; edges address each frame to the shards that own its
camera centre (``frames/s.<a>.<b>.``) and a named shard subscribes to the frames addressed to
it and to the plain frame key (edges that do not route yet, frames no shard owns).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.config import ConfigError, field_
from common.shard_routing import DEFAULT_HALO_M, ShardRegion, ShardRoutingError


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
    halo_m: float = field_(DEFAULT_HALO_M, "a named shard announces what it owns on mapper/shards/<name>/routing "
                                           "and edges send it the frames whose camera centre lies in its region "
                                           "or within this many metres of it (docs/key_space.md#shards)")


#: a shard subscribing to more tile keys than this subscribes to every frame instead
MAX_TILE_SUBSCRIPTIONS = 1024


class ShardFilter:
    """Which frames a shard maps (see module doc); ``accepts`` is cheap (per frame). The
    ownership test itself is :class:`common.shard_routing.ShardRegion` (``region``), which
    edges and clients apply to the shard's announcement."""

    def __init__(self, cfg: ShardSection):
        try:
            self.region = ShardRegion.make(cfg.name, cfg.region, cfg.tile_m, cfg.tiles, cfg.robots, cfg.halo_m)
        except ShardRoutingError as e:
            raise ConfigError(f"shard.{e}") from None
        self.name = cfg.name
        self.lo, self.hi = self.region.lo, self.region.hi
        self.tile_m = self.region.tile_m
        self.tiles = self.region.tiles
        self.robots = self.region.robots

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
        elif (self.lo is not None and self.hi is not None and np.all(np.isfinite(self.lo[:2]))
              and np.all(np.isfinite(self.hi[:2]))):
            i0, j0 = math.floor(self.lo[0] / t), math.floor(self.lo[1] / t)
            i1, j1 = math.ceil(self.hi[0] / t) - 1, math.ceil(self.hi[1] / t) - 1
            if (i1 - i0 + 1 + 2 * h) * (j1 - j0 + 1 + 2 * h) > MAX_TILE_SUBSCRIPTIONS:
                return None
            base = {(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)}
        else:
            return None
        out = {(i + di, j + dj) for i, j in base for di in range(-h, h + 1) for dj in range(-h, h + 1)}
        return out if len(out) <= MAX_TILE_SUBSCRIPTIONS else None

    def accepts(self, robot: str, pose_world: np.ndarray) -> bool:
        """True when this shard maps a frame of ``robot`` taken at ``pose_world`` (4×4, map frame)."""
        return self.region.accepts(robot, np.asarray(pose_world, np.float64)[:3, 3])
