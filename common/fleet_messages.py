"""Fleet search schemas (issue 44: several robots searching together):
``rayfronts.fleet_search_request`` / ``rayfronts.fleet_search_reply`` on
``<p>/mapper/fleet_search`` (standing answers on ``<p>/mapper/fleet_searches/<id>``) and
``rayfronts.unreachable`` / ``rayfronts.unreachable_reply`` on
``<p>/mapper/robots/<robot>/unreachable`` (docs/fleet.md "Fleet search").

Same envelope and :class:`common.messages.MessageError` as :mod:`common.search_messages`.
World frame, metres, z up; yaw in radians counter-clockwise from +x; timings in ms. Every
validation error is one line.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from common.messages import VERSION, MessageError, _decode
from common.search_messages import (
    MAX_GOALS,
    REQUEST_FIELDS,
    SearchRequest,
    _finite_list,
    _int_in,
    request_body,
    request_fields,
)
from common.wire import WireLimits, encode_message

SCHEMA_FLEET_SEARCH_REQUEST = "rayfronts.fleet_search_request"
SCHEMA_FLEET_SEARCH_REPLY = "rayfronts.fleet_search_reply"
SCHEMA_UNREACHABLE = "rayfronts.unreachable"
SCHEMA_UNREACHABLE_REPLY = "rayfronts.unreachable_reply"

#: robots one fleet search may name
MAX_FLEET_ROBOTS = 32
#: instances per target a fleet search may ask for (``target_count``)
MAX_TARGET_COUNT = 100
#: largest footprint (m): two goals' viewpoints at least this far apart
MAX_FOOTPRINT_M = 100.0
#: look-next candidates a fleet search computes by default (shared out across the robots)
DEFAULT_CANDIDATES = 20
#: a robot's state in a fleet reply
ROBOT_STATES = ("assigned", "idle", "waiting", "gone")

FLEET_REQUEST_FIELDS = (REQUEST_FIELDS - {"from_xyz", "owner"}) | {"robots", "target_count", "footprint_m"}
_ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


@dataclass
class FleetSearchRequest(SearchRequest):
    """One search for a set of robots (the fields of :class:`SearchRequest`, whose ``from_xyz``
    has no meaning here: each robot's own position is used). ``robots``: the robot ids ([] =
    every robot the mapper knows that is present); ``target_count``: instances of each target
    after which the others stop being sent toward it (default 1); ``footprint_m``: the least
    distance between two robots' goal viewpoints (0 = the mapper's ``search.fleet_footprint_m``);
    ``max_goals``: look-next candidates computed once per map update and shared out."""

    max_goals: int = DEFAULT_CANDIDATES
    robots: list[str] = field(default_factory=list)
    target_count: int = 1
    footprint_m: float = 0.0

    def validate(self) -> "FleetSearchRequest":
        if self.from_xyz is not None:
            raise MessageError("from_xyz has no meaning in a fleet search: each robot's own position is used")
        super().validate()
        if self.cancel or self.renew:
            return self
        if not isinstance(self.robots, (list, tuple)) or len(self.robots) > MAX_FLEET_ROBOTS:
            raise MessageError(f"robots must be a list of at most {MAX_FLEET_ROBOTS} robot ids ([] = all)")
        for r in self.robots:
            if not isinstance(r, str) or not _ID_RE.match(r):
                raise MessageError(f"robot id {r!r} in the fleet must match [A-Za-z0-9_-]{{1,64}}")
        if len(set(self.robots)) != len(self.robots):
            dup = sorted({r for r in self.robots if list(self.robots).count(r) > 1})
            raise MessageError(f"robots named twice in the fleet: {', '.join(dup)}")
        self.robots = [str(r) for r in self.robots]
        self.target_count = _int_in(self.target_count, 1, MAX_TARGET_COUNT, "target_count")
        fp = self.footprint_m
        if isinstance(fp, bool) or not isinstance(fp, (int, float)) or not (math.isfinite(fp)
                                                                               and 0.0 <= fp <= MAX_FOOTPRINT_M):
            raise MessageError(f"footprint_m must be metres in [0, {MAX_FOOTPRINT_M:g}] (0 = the mapper's "
                               f"search.fleet_footprint_m), got {fp!r}")
        self.footprint_m = float(fp)
        self.max_goals = _int_in(self.max_goals, 1, MAX_GOALS, "max_goals (look-next candidates)")
        return self


def encode_fleet_search_request(req: FleetSearchRequest) -> bytes:
    return encode_message(SCHEMA_FLEET_SEARCH_REQUEST, VERSION, request_body(req, FLEET_REQUEST_FIELDS))


def decode_fleet_search_request(data: bytes | bytearray | memoryview,
                                limits: WireLimits | None = None) -> FleetSearchRequest:
    kw = request_fields(data, SCHEMA_FLEET_SEARCH_REQUEST, FLEET_REQUEST_FIELDS, limits)
    return FleetSearchRequest(**kw).validate()


@dataclass
class FleetSearchReply:
    """What the mapper answers to a fleet search (plain dicts and lists; docs/messages.md):

    * ``goals``: robot -> its goal (a look-next goal ``{position, heading_rad, score, gain_m3,
      distance_m, target, frontier, rays, ray_z}``, ``distance_m`` that robot's own path to
      it) or None (waiting, gone, or nothing left for it); every robot of the fleet is a key;
    * ``robots``: robot -> ``{state, position, unreachable}``: ``state`` one of
      :data:`ROBOT_STATES` (``assigned``; ``idle``: present, no goal left for it;
      ``waiting``: known but no pose mapped yet; ``gone``: its liveliness left), ``position``
      its last mapped position or None, ``unreachable`` how many positions it reported;
    * ``waiting``: robots without a pose yet (they get goals once a frame of theirs is mapped);
    * ``gone``: robots of the fleet whose liveliness left (their goals went to the others);
    * ``found``: the shared found instances (as :class:`common.search_messages.SearchReply`);
    * ``candidates``: the look-next goals shared out, best first (``distance_m`` 0);
    * ``utility`` / ``method``: the allocation's objective and method
      (``planning.fleet_allocation``); ``footprint_m`` the distance kept between goals;
    * ``events``, ``frames_mapped``, ``map_version``, ``timings_ms``, ``missing_shards`` as
      in a search reply.
    """

    id: str = ""
    goals: dict = field(default_factory=dict)
    robots: dict = field(default_factory=dict)
    waiting: list = field(default_factory=list)
    gone: list = field(default_factory=list)
    found: list = field(default_factory=list)
    events: list = field(default_factory=list)
    candidates: list = field(default_factory=list)
    utility: float = 0.0
    method: str = ""
    frames_mapped: int = 0
    map_version: int = 0
    footprint_m: float = 0.0
    missing_shards: list = field(default_factory=list)
    timings_ms: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict (the reply's fields)."""
        return dict(id=self.id, goals=self.goals, robots=self.robots, waiting=list(self.waiting),
                    gone=list(self.gone), found=self.found, candidates=self.candidates,
                    utility=float(self.utility), method=self.method, footprint_m=float(self.footprint_m),
                    events=self.events, frames_mapped=int(self.frames_mapped), map_version=int(self.map_version),
                    timings_ms=self.timings_ms, missing_shards=[str(v) for v in self.missing_shards])


#: the fields of a fleet reply's JSON object (``rayfronts search --fleet ... --json``, the console)
FLEET_JSON_FIELDS = tuple(FleetSearchReply().to_dict())


def encode_fleet_search_reply(rep: FleetSearchReply) -> bytes:
    return encode_message(SCHEMA_FLEET_SEARCH_REPLY, VERSION, rep.to_dict())


def decode_fleet_search_reply(data: bytes | bytearray | memoryview,
                              limits: WireLimits | None = None) -> FleetSearchReply:
    body = _decode(data, SCHEMA_FLEET_SEARCH_REPLY, limits)
    kinds = {"goals": dict, "robots": dict, "waiting": list, "gone": list, "found": list, "candidates": list,
             "events": list, "timings_ms": dict, "missing_shards": list}
    for k, t in kinds.items():
        if not isinstance(body.get(k, t()), t):
            raise MessageError(f"{SCHEMA_FLEET_SEARCH_REPLY}: {k!r} must be a {t.__name__}")
    kw: dict[str, Any] = {k: body.get(k, t()) for k, t in kinds.items()}
    return FleetSearchReply(id=str(body.get("id", "")), utility=float(body.get("utility", 0.0)),
                            method=str(body.get("method", "")), footprint_m=float(body.get("footprint_m", 0.0)),
                            frames_mapped=int(body.get("frames_mapped", 0)),
                            map_version=int(body.get("map_version", 0)), **kw)


# ------------------------------------------------------------------ unreachable
@dataclass
class UnreachableReport:
    """A robot tells the mapper it cannot reach ``position`` [x, y, z] (its goal): fleet
    searches stop giving it goals within ``search.fleet_unreachable_tol_m`` of it. ``id``: the
    standing fleet search it concerns ("" = all of them); the robot is the key's."""

    position: list[float] = field(default_factory=list)
    id: str = ""

    def validate(self) -> "UnreachableReport":
        self.position = _finite_list(self.position, 3, "unreachable position [x, y, z]")
        if not isinstance(self.id, str) or not re.match(r"^[A-Za-z0-9_-]{0,64}$", self.id):
            raise MessageError(f"fleet search id {self.id!r} must match [A-Za-z0-9_-]{{0,64}}")
        return self


def encode_unreachable(rep: UnreachableReport) -> bytes:
    rep.validate()
    return encode_message(SCHEMA_UNREACHABLE, VERSION, {"position": rep.position, "id": rep.id})


def decode_unreachable(data: bytes | bytearray | memoryview) -> UnreachableReport:
    body = _decode(data, SCHEMA_UNREACHABLE, WireLimits(max_message_bytes=64 << 10))
    unknown = set(body) - {"position", "id"}
    if unknown:
        raise MessageError(f"{SCHEMA_UNREACHABLE}: unknown fields {sorted(unknown)}")
    return UnreachableReport(position=body.get("position", []), id=body.get("id", "")).validate()


def encode_unreachable_reply(body: dict) -> bytes:
    """``{robot, held, goals}``: the robot, how many unreachable positions the mapper holds for
    it, and its new goal (or None) in every standing fleet search that includes it."""
    return encode_message(SCHEMA_UNREACHABLE_REPLY, VERSION, body)


def decode_unreachable_reply(data: bytes | bytearray | memoryview) -> dict:
    body = _decode(data, SCHEMA_UNREACHABLE_REPLY)
    if not isinstance(body.get("goals", {}), dict):
        raise MessageError(f"{SCHEMA_UNREACHABLE_REPLY}: 'goals' must be a dict")
    return {"robot": str(body.get("robot", "")), "held": int(body.get("held", 0)), "goals": body.get("goals", {})}
