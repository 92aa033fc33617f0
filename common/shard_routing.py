"""What a mapper shard owns, shared by the three roles: the mapper (which frames it maps), the
edge (which shards it sends a frame to) and the client (which shard's occupancy answers a
cell, whether any shard owns a requested area).

A shard owns a box ``region`` (half-open ``[min, max)``, metres, the map's world frame), a set
of square tiles (``tile_m`` + ``tiles``, tile ``(i, j)`` = ``floor(x / tile_m), floor(y / tile_m)``),
both, or neither (everything); and optionally a list of ``robots`` (frames only). A frame is
the shard's when its robot is one of the shard's (or the list is empty) and its camera centre
lies in what the shard owns (docs/key_space.md#shards).

**Routing announcement** (``rayfronts.shard_routing`` v1, the reply of the queryable
``<p>/mapper/shards/<name>/routing``): the shard's name, region (6 numbers, unbounded sides as
±1e9), tiles, robots, ``halo_m`` (an edge also sends it the frames whose camera centre lies
within this many metres of what it owns) and the ``world_from_robot`` transforms it applies
(16 numbers row-major per robot), so that an edge routes in the map's world frame. Edges ask
every :data:`ROUTING_PERIOD_S` and address each frame to the shards that own it
(``common.keys.KeySpace.frames_routed``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from common.keys import is_valid_id
from common.wire import WireError, decode_message, encode_message

SCHEMA_SHARD_ROUTING = "rayfronts.shard_routing"
VERSION = 1
#: edges refresh the shards' announcements this often (s); an announcement unanswered for
#: three periods is forgotten
ROUTING_PERIOD_S = 2.0
#: default ``shard.halo_m``: frames this close to a shard's region (m) are sent to it as well
DEFAULT_HALO_M = 2.0
#: an unbounded side of a region, as written in announcements and shard info (JSON has no inf)
UNBOUNDED = 1e9
#: most robots' transforms one announcement carries
MAX_TRANSFORMS = 4096


class ShardRoutingError(ValueError):
    """A region or announcement that does not validate (one line)."""


def _region6(region: Sequence[float] | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(lo, hi)`` of a 4- or 6-number region (±inf for a missing z range, ±UNBOUNDED read as inf)."""
    if region is None or len(region) == 0:
        return None
    try:
        r = [float(v) for v in region]
    except (TypeError, ValueError):
        raise ShardRoutingError(f"region must be numbers, got {region!r}") from None
    if len(r) == 4:
        r = [r[0], r[1], -math.inf, r[2], r[3], math.inf]
    if len(r) != 6 or any(math.isnan(v) for v in r) or not all(lo < hi for lo, hi in zip(r[:3], r[3:], strict=True)):
        raise ShardRoutingError(f"region must be [xmin, ymin, xmax, ymax] or 6 values with min < max, "
                                f"got {list(region)}")
    a = np.array(r, np.float64)
    a[a >= UNBOUNDED] = math.inf
    a[a <= -UNBOUNDED] = -math.inf
    return a[:3], a[3:]


@dataclass
class ShardRegion:
    """What one shard owns (see module doc). ``transforms``: robot → 4×4 ``world_from_robot``
    (routing only); ``halo_m``: routing margin."""

    name: str = ""
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    tile_m: float = 0.0
    tiles: set[tuple[int, int]] = field(default_factory=set)
    robots: set[str] = field(default_factory=set)
    halo_m: float = 0.0
    transforms: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def make(cls, name: str = "", region: Sequence[float] | None = None, tile_m: float = 0.0,
             tiles: Iterable = (), robots: Iterable[str] = (), halo_m: float = 0.0) -> "ShardRegion":
        """Validated region; ``tiles`` as ``"i,j"`` strings or ``[i, j]`` pairs. Raises
        :class:`ShardRoutingError` with one line naming the bad field."""
        if name and not is_valid_id(name):
            raise ShardRoutingError(f"name {name!r}: use 1-64 characters from [A-Za-z0-9_-]")
        box = _region6(region)
        ts: set[tuple[int, int]] = set()
        for t in tiles:
            try:
                i, j = (int(v) for v in (str(t).split(",") if isinstance(t, str) else t))
            except (TypeError, ValueError):
                raise ShardRoutingError(f"tiles: {t!r} is not 'i,j' (two integers)") from None
            ts.add((i, j))
        if ts and not float(tile_m) > 0:
            raise ShardRoutingError("tiles need tile_m > 0")
        for rb in robots:
            if not is_valid_id(rb):
                raise ShardRoutingError(f"robots: invalid robot id {rb!r}")
        if not (math.isfinite(float(halo_m)) and float(halo_m) >= 0):
            raise ShardRoutingError(f"halo_m must be >= 0 m, got {halo_m!r}")
        return cls(name=name, lo=None if box is None else box[0], hi=None if box is None else box[1],
                   tile_m=float(tile_m), tiles=ts, robots=set(robots), halo_m=float(halo_m))

    @classmethod
    def from_info(cls, info: dict) -> "ShardRegion":
        """From a shard info dict (``common.robot_messages``) or a decoded announcement."""
        return cls.make(str(info.get("shard", "")), info.get("region"), float(info.get("tile_m", 0.0) or 0.0),
                        info.get("tiles") or (), info.get("robots") or (), float(info.get("halo_m", 0.0) or 0.0))

    @property
    def bounded(self) -> bool:
        """True when the shard owns less than everything (a region or tiles)."""
        return self.lo is not None or bool(self.tiles)

    def region_list(self) -> list[float] | None:
        """The region as 6 finite numbers (unbounded sides ±:data:`UNBOUNDED`), or None."""
        if self.lo is None or self.hi is None:
            return None
        return [float(np.clip(v, -UNBOUNDED, UNBOUNDED)) for v in (*self.lo, *self.hi)]

    def owns_xyz(self, xyz: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: points (N, 3) in what the shard owns, grown by ``margin`` m (Chebyshev)."""
        p = np.asarray(xyz, np.float64).reshape(-1, 3)
        ok = np.ones(len(p), bool)
        if self.lo is not None and self.hi is not None:
            ok &= np.all(p >= self.lo - margin, axis=1) & np.all(p < self.hi + margin, axis=1)
        if self.tiles:
            packed = np.array([i * (1 << 32) + j for i, j in self.tiles], np.int64)
            hit = np.zeros(len(p), bool)
            offs = (0.0,) if margin <= 0 else (-margin, 0.0, margin)
            for dx in offs:
                for dy in offs:
                    i = np.floor((p[:, 0] + dx) / self.tile_m).astype(np.int64)
                    j = np.floor((p[:, 1] + dy) / self.tile_m).astype(np.int64)
                    hit |= np.isin(i * (1 << 32) + j, packed)
            ok &= hit
        return ok

    def accepts(self, robot: str, centre_world: Sequence[float] | np.ndarray, margin: float = 0.0) -> bool:
        """True when the shard maps a frame of ``robot`` whose camera centre (world frame) is
        ``centre_world`` (with ``margin``: or lies that close to what it owns)."""
        if self.robots and robot not in self.robots:
            return False
        return bool(self.owns_xyz(np.asarray(centre_world, np.float64)[:3], margin)[0])

    def intersects_box(self, lo: Sequence[float], hi: Sequence[float]) -> bool:
        """True when the x/y box ``[lo, hi]`` (2 or 3 numbers each) meets what the shard owns."""
        lo2, hi2 = np.asarray(lo, np.float64)[:2], np.asarray(hi, np.float64)[:2]
        if self.lo is not None and self.hi is not None and (
                np.any(hi2 < self.lo[:2]) or np.any(lo2 >= self.hi[:2])):
            return False
        if self.tiles:
            t = self.tile_m
            return any(i * t <= hi2[0] and (i + 1) * t > lo2[0] and j * t <= hi2[1] and (j + 1) * t > lo2[1]
                       for i, j in self.tiles)
        return True

    def describe(self) -> str:
        """Short text of what the shard owns (error messages)."""
        parts = []
        r = self.region_list()
        if r is not None:
            parts.append("[" + ", ".join(f"{v:g}" for v in r) + "]")
        if self.tiles:
            parts.append(f"{len(self.tiles)} tiles of {self.tile_m:g} m")
        return f"{self.name or '(unnamed)'} {' '.join(parts) or 'everything'}"

    def route_targets_centre(self, robot: str, centre_robot: np.ndarray) -> bool:
        """Routing test at the edge: the camera centre in the robot's own pose frame, moved to
        the world by this shard's ``world_from_robot`` of ``robot``, within ``halo_m``."""
        T = self.transforms.get(robot)
        c = np.asarray(centre_robot, np.float64)[:3]
        if T is not None:
            c = T[:3, :3] @ c + T[:3, 3]
        return self.accepts(robot, c, self.halo_m)


# ------------------------------------------------------------------ announcement
def encode_shard_routing(region: ShardRegion) -> bytes:
    """The announcement of ``region`` (see module doc)."""
    body = {"shard": region.name, "region": region.region_list(), "tile_m": float(region.tile_m),
            "tiles": sorted([int(i), int(j)] for i, j in region.tiles), "robots": sorted(region.robots),
            "halo_m": float(region.halo_m),
            "world_from_robot": {r: [float(v) for v in np.asarray(t, np.float64).reshape(-1)]
                                 for r, t in sorted(region.transforms.items())[:MAX_TRANSFORMS]}}
    return encode_message(SCHEMA_SHARD_ROUTING, VERSION, body)


def decode_shard_routing(data: bytes | bytearray | memoryview) -> ShardRegion:
    """Inverse of :func:`encode_shard_routing` (validated; :class:`ShardRoutingError`)."""
    try:
        schema, v, body = decode_message(bytes(data))
    except WireError as e:
        raise ShardRoutingError(f"{SCHEMA_SHARD_ROUTING}: {e}") from None
    if schema != SCHEMA_SHARD_ROUTING or v != VERSION or not isinstance(body, dict):
        raise ShardRoutingError(f"expected {SCHEMA_SHARD_ROUTING} v{VERSION}, got {schema!r} v{v!r}")
    if not isinstance(body.get("shard"), str) or not is_valid_id(body["shard"]):
        raise ShardRoutingError(f"{SCHEMA_SHARD_ROUTING}: 'shard' must be a shard name")
    reg = ShardRegion.from_info(body)
    tf = body.get("world_from_robot") or {}
    if not isinstance(tf, dict) or len(tf) > MAX_TRANSFORMS:
        raise ShardRoutingError(f"{SCHEMA_SHARD_ROUTING}: 'world_from_robot' must map robot ids to 16 numbers")
    for robot, vals in tf.items():
        a = np.asarray(vals, np.float64) if isinstance(vals, list) else np.zeros(0)
        if not is_valid_id(str(robot)) or a.shape != (16,) or not np.all(np.isfinite(a)):
            raise ShardRoutingError(f"{SCHEMA_SHARD_ROUTING}: world_from_robot of {robot!r} must be 16 finite numbers")
        reg.transforms[str(robot)] = a.reshape(4, 4)
    return reg


def route_targets(regions: Iterable[ShardRegion], robot: str, centre_robot: np.ndarray) -> list[str]:
    """Names of the shards a frame of ``robot`` with camera centre ``centre_robot`` (robot's own
    pose frame) goes to, sorted; empty = none owns it (sent on the plain key)."""
    return sorted(r.name for r in regions if r.name and r.route_targets_centre(robot, centre_robot))
