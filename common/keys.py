"""The Zenoh key space (docs/key_space.md). Pure string building and parsing; no Zenoh import.

All keys live under a configurable prefix (default ``rayfronts``), so several sites or
experiments can share one Zenoh network::

    <p>/robots/<robot>/frames          edge publishes one frame message per processed frame
    <p>/robots/<robot>/frames/<i>_<j>  the same, routed by tile (edge publish.tile_m > 0;
                                       docs/key_space.md#shards)
    <p>/robots/<robot>/frames/s.<a>.<b>.  the same, addressed to the shards a, b that own it
                                       (edges learn the shards' routing announcements)
    <p>/robots/<robot>/alive           edge liveliness token
    <p>/robots/<robot>/feature_space   edge queryable (feature-space id, PCA basis, ...)
    <p>/robots/<robot>/edge_status     edge publishes (and serves) its own state: starting /
                                       running / done / refused / failed, with the reason
    <p>/robots/<robot>/sim/views       a simulator puts the camera poses its robot's edge renders
                                       next (edge source.kind=sim_camera; the closed loop)
    <p>/mapper/alive                   mapper liveliness token
    <p>/mapper/shards/<name>           mapper shard liveliness token (shard.name set)
    <p>/mapper/shards/<name>/routing   shard queryable: what it owns (common.shard_routing)
    <p>/mapper/query                   mapper queryable: run a query now
    <p>/mapper/queries/<id>            mapper publishes results of a standing query
    <p>/mapper/layers/<layer>          mapper publishes voxels / frontiers / rays / ...
    <p>/mapper/stats                   mapper queryable: counters and timings
    <p>/mapper/snapshot                mapper queryable: save / describe snapshots
    <p>/mapper/feature_space           mapper queryable: the map's feature space (edges adopt its basis)
    <p>/mapper/search                  mapper queryable: search for planners (found / look next / beyond)
    <p>/mapper/searches/<id>           mapper publishes results of a standing search
    <p>/mapper/occupancy               mapper queryable: occupancy box / slice / points
    <p>/mapper/robots/<robot>/search   mapper queryable: search asked by robot <robot> (its
                                       onboard planner; the ACL lets a robot ask only its own)
    <p>/mapper/robots/<robot>/occupancy        the same for occupancy
    <p>/mapper/robots/<robot>/searches/<id>    results of a standing search robot <robot> registered
    <p>/mapper/fleet_search            mapper queryable: one search for several robots (goals shared out)
    <p>/mapper/fleet_searches/<id>     mapper publishes results of a standing fleet search
    <p>/mapper/robots/<robot>/unreachable  mapper queryable: robot <robot> reports a goal unreachable
    <p>/mapper/robots/<robot>/fleet_goal   mapper publishes robot <robot>'s goal of standing fleet searches

Robot ids, query ids and layer names are single key chunks: ``[A-Za-z0-9_-]{1,64}``
(no ``/``, no Zenoh wildcards ``*``/``$``, no ``?#`` which Zenoh reserves).
"""
from __future__ import annotations

import re

DEFAULT_PREFIX = "rayfronts"

#: one identifier chunk: robot ids, query ids, layer names.
ID_PATTERN = r"[A-Za-z0-9_-]{1,64}"
_ID_RE = re.compile(rf"^{ID_PATTERN}$")
# A prefix is one or more '/'-separated chunks of the same alphabet (dots allowed too).
_PREFIX_RE = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")


class InvalidKey(ValueError):
    """An invalid robot id, query id, layer name or prefix."""


def is_valid_id(name: str) -> bool:
    """True when ``name`` is a valid robot / query / layer id (``[A-Za-z0-9_-]{1,64}``)."""
    return isinstance(name, str) and _ID_RE.match(name) is not None


def check_id(name: str, what: str = "robot id") -> str:
    """Return ``name`` or raise :class:`InvalidKey` saying what is wrong with it."""
    if not isinstance(name, str):
        raise InvalidKey(f"{what} must be a string, got {type(name).__name__}")
    if not _ID_RE.match(name):
        raise InvalidKey(f"invalid {what} {name!r}: use 1-64 characters from [A-Za-z0-9_-] "
                         "(no '/', spaces or Zenoh wildcards)")
    return name


class KeySpace:
    """Builds and parses the keys of one deployment (``prefix`` default ``rayfronts``)."""

    def __init__(self, prefix: str = DEFAULT_PREFIX):
        if not isinstance(prefix, str) or not _PREFIX_RE.match(prefix):
            raise InvalidKey(f"invalid key prefix {prefix!r}: '/'-separated chunks of [A-Za-z0-9_.-], "
                             "no leading/trailing '/', no wildcards")
        self.prefix = prefix
        self._robot_re = re.compile(rf"^{re.escape(prefix)}/robots/({ID_PATTERN})/"
                                    rf"(?:[A-Za-z0-9_-]+|frames/-?[0-9]+_-?[0-9]+|frames/s(?:\.{ID_PATTERN})+\.)$")
        self._asker_re = re.compile(rf"^{re.escape(prefix)}/mapper/robots/({ID_PATTERN})/[A-Za-z0-9_-]+$")

    def __repr__(self) -> str:
        return f"KeySpace({self.prefix!r})"

    def __eq__(self, other) -> bool:
        return isinstance(other, KeySpace) and other.prefix == self.prefix

    def __hash__(self) -> int:
        return hash(("KeySpace", self.prefix))

    # ------------------------------------------------------------------ robots
    def robot_root(self, robot: str) -> str:
        """``<p>/robots/<robot>`` (the prefix every key of one robot starts with)."""
        return f"{self.prefix}/robots/{check_id(robot)}"

    def frames(self, robot: str) -> str:
        return f"{self.robot_root(robot)}/frames"

    @property
    def frames_all(self) -> str:
        return f"{self.prefix}/robots/*/frames"

    def frames_tile(self, robot: str, tile: tuple[int, int]) -> str:
        """``<p>/robots/<robot>/frames/<i>_<j>``: a frame whose camera centre lies in tile (i, j)."""
        return f"{self.robot_root(robot)}/frames/{int(tile[0])}_{int(tile[1])}"

    def frames_tile_all(self, tile: tuple[int, int]) -> str:
        """``<p>/robots/*/frames/<i>_<j>``: every robot's frames of one tile (a shard's subscription)."""
        return f"{self.prefix}/robots/*/frames/{int(tile[0])}_{int(tile[1])}"

    def frames_routed(self, robot: str, shards: list[str] | tuple[str, ...]) -> str:
        """``<p>/robots/<robot>/frames/s.<a>.<b>.``: a frame addressed to the shards ``a``, ``b``
        (those owning its camera centre, learned from their routing announcements)."""
        if not shards:
            raise InvalidKey("a routed frame key needs at least one shard")
        return f"{self.robot_root(robot)}/frames/s.{'.'.join(check_id(s, 'shard name') for s in shards)}."

    def frames_routed_all(self, shard: str) -> str:
        """``<p>/robots/*/frames/s$*.<shard>.$*``: every frame addressed to ``shard`` (its subscription)."""
        return f"{self.prefix}/robots/*/frames/s$*.{check_id(shard, 'shard name')}.$*"

    @property
    def frames_tiled_all(self) -> str:
        """``<p>/robots/*/frames/*``: every tile-routed frame (an unsharded mapper's second subscription)."""
        return f"{self.prefix}/robots/*/frames/*"

    def alive(self, robot: str) -> str:
        return f"{self.robot_root(robot)}/alive"

    @property
    def alive_all(self) -> str:
        return f"{self.prefix}/robots/*/alive"

    def feature_space(self, robot: str) -> str:
        return f"{self.robot_root(robot)}/feature_space"

    @property
    def feature_space_all(self) -> str:
        return f"{self.prefix}/robots/*/feature_space"

    def edge_status(self, robot: str) -> str:
        """The edge's own state (``common.messages.encode_edge_status``): put on every change
        and served as a queryable while the edge process lives."""
        return f"{self.robot_root(robot)}/edge_status"

    @property
    def edge_status_all(self) -> str:
        return f"{self.prefix}/robots/*/edge_status"

    def sim_views(self, robot: str) -> str:
        """Camera poses a simulator asks robot ``robot``'s edge to render next
        (``common.messages.encode_sim_views``; edge ``source.kind=sim_camera``)."""
        return f"{self.robot_root(robot)}/sim/views"

    # ------------------------------------------------------------------ mapper
    @property
    def mapper_root(self) -> str:
        return f"{self.prefix}/mapper"

    @property
    def mapper_alive(self) -> str:
        return f"{self.prefix}/mapper/alive"

    @property
    def mapper_query(self) -> str:
        return f"{self.prefix}/mapper/query"

    def mapper_queries(self, qid: str) -> str:
        return f"{self.prefix}/mapper/queries/{check_id(qid, 'query id')}"

    @property
    def mapper_queries_all(self) -> str:
        return f"{self.prefix}/mapper/queries/*"

    def layers(self, layer: str) -> str:
        return f"{self.prefix}/mapper/layers/{check_id(layer, 'layer name')}"

    @property
    def layers_all(self) -> str:
        return f"{self.prefix}/mapper/layers/*"

    @property
    def stats(self) -> str:
        return f"{self.prefix}/mapper/stats"

    @property
    def mapper_feature_space(self) -> str:
        """Mapper queryable: the map's feature space (``rayfronts.feature_space``), for edges
        that adopt the map's PCA basis (``pca.basis=map``)."""
        return f"{self.prefix}/mapper/feature_space"

    @property
    def snapshot(self) -> str:
        return f"{self.prefix}/mapper/snapshot"

    @property
    def mapper_search(self) -> str:
        """Mapper queryable: search for planners (``common.search_messages``)."""
        return f"{self.prefix}/mapper/search"

    @property
    def mapper_occupancy(self) -> str:
        """Mapper queryable: occupancy box / slice / points (``common.search_messages``)."""
        return f"{self.prefix}/mapper/occupancy"

    def mapper_searches(self, sid: str) -> str:
        """Where the mapper publishes a standing search's replies."""
        return f"{self.prefix}/mapper/searches/{check_id(sid, 'search id')}"

    # ------------------------------------------------- robot-scoped planner keys
    def robot_search(self, robot: str) -> str:
        """``<p>/mapper/robots/<robot>/search``: the search queryable as robot ``robot`` asks
        it (its certificate may ask only this one; docs/key_space.md)."""
        return f"{self.prefix}/mapper/robots/{check_id(robot)}/search"

    @property
    def robot_search_all(self) -> str:
        """``<p>/mapper/robots/*/search`` (the mapper's queryable)."""
        return f"{self.prefix}/mapper/robots/*/search"

    def robot_occupancy(self, robot: str) -> str:
        """``<p>/mapper/robots/<robot>/occupancy``: occupancy as robot ``robot`` asks it."""
        return f"{self.prefix}/mapper/robots/{check_id(robot)}/occupancy"

    @property
    def robot_occupancy_all(self) -> str:
        return f"{self.prefix}/mapper/robots/*/occupancy"

    def robot_searches(self, robot: str, sid: str) -> str:
        """Where the mapper publishes standing search ``sid`` that robot ``robot`` registered."""
        return f"{self.prefix}/mapper/robots/{check_id(robot)}/searches/{check_id(sid, 'search id')}"

    # ------------------------------------------------------------ fleet search
    @property
    def mapper_fleet_search(self) -> str:
        """Mapper queryable: one search for several robots (``common.fleet_messages``)."""
        return f"{self.prefix}/mapper/fleet_search"

    def mapper_fleet_searches(self, sid: str) -> str:
        """Where the mapper publishes a standing fleet search's replies."""
        return f"{self.prefix}/mapper/fleet_searches/{check_id(sid, 'fleet search id')}"

    def robot_unreachable(self, robot: str) -> str:
        """``<p>/mapper/robots/<robot>/unreachable``: robot ``robot`` reports a goal it cannot reach."""
        return f"{self.prefix}/mapper/robots/{check_id(robot)}/unreachable"

    @property
    def robot_unreachable_all(self) -> str:
        return f"{self.prefix}/mapper/robots/*/unreachable"

    def robot_fleet_goal(self, robot: str) -> str:
        """``<p>/mapper/robots/<robot>/fleet_goal``: robot ``robot``'s goal in each standing fleet
        search (a ``rayfronts.fleet_search_reply`` holding that robot only)."""
        return f"{self.prefix}/mapper/robots/{check_id(robot)}/fleet_goal"

    def asker_from_key(self, key: object) -> str | None:
        """Robot id of a ``<p>/mapper/robots/<robot>/<leaf>`` key (a robot-scoped planner
        key), else ``None``: also for a wildcard or an invalid id in place of the robot."""
        m = self._asker_re.match(str(key))
        return m.group(1) if m else None

    @property
    def everything(self) -> str:
        """``<p>/**`` (debug subscribers, ACL rules for the mapper)."""
        return f"{self.prefix}/**"

    # ------------------------------------------------------------------ parsers
    def robot_from_key(self, key: object) -> str | None:
        """Robot id of a ``<p>/robots/<robot>/<leaf>`` key, else ``None`` (also for invalid ids)."""
        m = self._robot_re.match(str(key))
        return m.group(1) if m else None

    def _last_chunk(self, key: object, root: str) -> str | None:
        s = str(key)
        if not s.startswith(root + "/"):
            return None
        rest = s[len(root) + 1:]
        return rest if is_valid_id(rest) else None

    def mapper_shard_alive(self, name: str) -> str:
        """``<p>/mapper/shards/<name>``: liveliness token of the mapper shard ``name``."""
        return f"{self.prefix}/mapper/shards/{check_id(name, 'shard name')}"

    @property
    def mapper_shards_all(self) -> str:
        return f"{self.prefix}/mapper/shards/*"

    def mapper_shard_routing(self, name: str) -> str:
        """``<p>/mapper/shards/<name>/routing``: queryable of shard ``name``'s routing announcement."""
        return f"{self.mapper_shard_alive(name)}/routing"

    @property
    def mapper_shard_routing_all(self) -> str:
        return f"{self.prefix}/mapper/shards/*/routing"

    def shard_from_key(self, key: object) -> str | None:
        """Shard name of a ``<p>/mapper/shards/<name>`` key, else ``None``."""
        return self._last_chunk(key, f"{self.prefix}/mapper/shards")

    def qid_from_key(self, key: object) -> str | None:
        """Query id of a ``<p>/mapper/queries/<id>`` key, else ``None``."""
        return self._last_chunk(key, f"{self.prefix}/mapper/queries")

    def layer_from_key(self, key: object) -> str | None:
        """Layer name of a ``<p>/mapper/layers/<layer>`` key, else ``None``."""
        return self._last_chunk(key, f"{self.prefix}/mapper/layers")
