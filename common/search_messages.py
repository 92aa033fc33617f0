"""Search and occupancy schemas for planners: ``rayfronts.search_request`` /
``rayfronts.search_reply`` (on ``<p>/mapper/search``) and ``rayfronts.occupancy_request`` /
``rayfronts.occupancy_reply`` (on ``<p>/mapper/occupancy``).

Kept apart from :mod:`common.messages` (same envelope, same :class:`MessageError`). Units:
world frame, metres, z up; yaw in radians counter-clockwise from +x; volumes in m³;
timings in milliseconds; probabilities in (0, 1). Every validation error is one line.

Occupancy states (int8): 0 free, 1 occupied, -1 unknown (``planning.occupancy_queries``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.messages import VERSION, MessageError, StandingControl, _decode
from common.wire import WireLimits, encode_message

SCHEMA_SEARCH_REQUEST = "rayfronts.search_request"
SCHEMA_SEARCH_REPLY = "rayfronts.search_reply"
SCHEMA_OCCUPANCY_REQUEST = "rayfronts.occupancy_request"
SCHEMA_OCCUPANCY_REPLY = "rayfronts.occupancy_reply"

MAX_TARGETS = 16
MAX_BACKGROUND = 64
MAX_PHRASE_CHARS = 200
MAX_POLYGON_VERTICES = 256
#: largest search area (bounding box of the polygon / box), m²: 4 km²
MAX_AREA_M2 = 4.0e6
MAX_INSTANCES = 1000
MAX_GOALS = 100
#: occupancy: output cells per request, points per request
MAX_OCC_CELLS = 4_000_000
MAX_OCC_POINTS = 100_000
OCC_KINDS = ("box", "slice", "points")

SEARCH_REQUEST_LIMITS = WireLimits(max_message_bytes=4 << 20, max_header_bytes=1 << 20, max_container_len=4096,
                                   max_nesting=5, max_containers=1024, max_str_bytes=64 << 10)
REQUEST_FIELDS = {"targets", "embeddings", "background", "area", "box", "z_band", "threshold", "max_instances",
                   "max_goals", "from_xyz", "standing", "cancel", "id", "lease_s", "renew", "client", "owner"}
_OCC_FIELDS = {"kind", "box_min", "box_max", "z_band", "points", "stride", "radius"}


def _finite_list(v, n: int | None, what: str) -> list[float]:
    try:
        a = [float(x) for x in v]
    except (TypeError, ValueError):
        raise MessageError(f"{what} must be a list of numbers, got {v!r}") from None
    if n is not None and len(a) != n:
        raise MessageError(f"{what} must have {n} numbers, got {len(a)}")
    if not all(math.isfinite(x) for x in a):
        raise MessageError(f"{what} must be finite numbers")
    return a


def _phrases(v, what: str, lo: int, hi: int) -> list[str]:
    if not isinstance(v, (list, tuple)) or not lo <= len(v) <= hi:
        raise MessageError(f"{what} must be a list of {lo}..{hi} phrases")
    for t in v:
        if not isinstance(t, str) or not t.strip() or len(t) > MAX_PHRASE_CHARS:
            raise MessageError(f"{what}: each phrase must be a non-empty string of at most {MAX_PHRASE_CHARS} chars")
    return [str(t) for t in v]


def _int_in(v, lo: int, hi: int, what: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise MessageError(f"{what} must be an integer in [{lo}, {hi}], got {v!r}")
    return int(v)


@dataclass
class SearchRequest(StandingControl):
    """Find ``targets`` (text phrases; or ``embeddings`` (T, D) in the map's language space,
    one row per target, the phrases then only name them) against ``background`` phrases
    (None: the mapper's ``search.background``). Scores are softmax probabilities over
    targets + background. ``area``: polygon [[x, y], ...] (>= 3 vertices) or ``box``
    [x0, y0, x1, y1]; ``z_band`` [z0, z1]; ``threshold`` in (0, 1); ``from_xyz`` the asker's
    position (distances of look-next goals). ``standing`` registers it under ``id`` (its
    instance tracker is kept); ``cancel`` drops the standing search ``id``; a standing search
    lives ``lease_s`` seconds (0 = the mapper's ``search.lease_s``) unless renewed (``renew`` +
    ``id``); ``client`` names the asker (per-client cap). ``owner`` is set by the mapper: the
    robot whose key (``<p>/mapper/robots/<robot>/search``) registered it, "" otherwise."""

    targets: list[str] = field(default_factory=list)
    embeddings: np.ndarray | None = None
    background: list[str] | None = None
    area: list[list[float]] | None = None
    box: list[float] | None = None
    z_band: list[float] | None = None
    threshold: float = 0.5
    max_instances: int = 10
    max_goals: int = 5
    from_xyz: list[float] | None = None
    owner: str = ""

    def validate(self) -> "SearchRequest":  # noqa: C901 - one check per field
        import re

        for k in ("id", "owner"):
            if not isinstance(getattr(self, k), str) or not re.match(r"^[A-Za-z0-9_-]{0,64}$", getattr(self, k)):
                raise MessageError(f"search {k} {getattr(self, k)!r} must match [A-Za-z0-9_-]{{0,64}}")
        if self.check_control("search"):
            return self
        self.targets = _phrases(self.targets, "targets", 1, MAX_TARGETS)
        if self.background is not None:
            self.background = _phrases(self.background, "background", 0, MAX_BACKGROUND)
        if self.embeddings is not None:
            e = np.asarray(self.embeddings)
            if (e.ndim != 2 or e.shape[0] != len(self.targets) or e.shape[1] == 0
                    or not np.issubdtype(e.dtype, np.floating) or not np.all(np.isfinite(e))):
                raise MessageError(f"embeddings must be finite floats of shape ({len(self.targets)}, dim), "
                                   f"one row per target")
            self.embeddings = e.astype(np.float32)
        if self.area is not None and self.box is not None:
            raise MessageError("give either area (polygon) or box, not both")
        if self.area is not None:
            if not isinstance(self.area, (list, tuple)) or not 3 <= len(self.area) <= MAX_POLYGON_VERTICES:
                raise MessageError(f"area must be a polygon of 3..{MAX_POLYGON_VERTICES} [x, y] vertices "
                                   f"(got {len(self.area) if isinstance(self.area, (list, tuple)) else self.area!r})")
            self.area = [_finite_list(p, 2, "area vertex") for p in self.area]
            a = np.asarray(self.area)
            x, y = a[:, 0], a[:, 1]
            if abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))) < 1e-9:
                raise MessageError("area polygon is degenerate (zero area)")
            self._check_extent(a.min(0), a.max(0))
        if self.box is not None:
            self.box = _finite_list(self.box, 4, "box [x0, y0, x1, y1]")
            if self.box[2] <= self.box[0] or self.box[3] <= self.box[1]:
                raise MessageError(f"box [x0, y0, x1, y1] needs x0 < x1 and y0 < y1, got {self.box}")
            self._check_extent(np.array(self.box[:2]), np.array(self.box[2:]))
        if self.z_band is not None:
            self.z_band = _finite_list(self.z_band, 2, "z_band [z0, z1]")
            if self.z_band[1] < self.z_band[0]:
                raise MessageError(f"z_band [z0, z1] needs z0 <= z1, got {self.z_band}")
        if isinstance(self.threshold, bool) or not isinstance(self.threshold, (int, float)) \
                or not 0.0 < float(self.threshold) < 1.0:
            raise MessageError(f"threshold must be a probability in (0, 1), got {self.threshold!r}")
        self.threshold = float(self.threshold)
        self.max_instances = _int_in(self.max_instances, 0, MAX_INSTANCES, "max_instances")
        self.max_goals = _int_in(self.max_goals, 0, MAX_GOALS, "max_goals")
        if self.from_xyz is not None:
            self.from_xyz = _finite_list(self.from_xyz, 3, "from_xyz [x, y, z]")
        for k in ("standing", "cancel"):
            if not isinstance(getattr(self, k), bool):
                raise MessageError(f"{k!r} must be true/false")
        if self.standing and not self.id:
            raise MessageError("a standing search needs an id")
        return self

    @staticmethod
    def _check_extent(lo: np.ndarray, hi: np.ndarray) -> None:
        area = float(np.prod(hi - lo))
        if area > MAX_AREA_M2:
            raise MessageError(f"search area of {area:,.0f} m² exceeds the limit of {MAX_AREA_M2:,.0f} m²")

    def polygon(self) -> list[list[float]] | None:
        """The area as a polygon (the box as its 4 corners), or None."""
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
        return self.area


def request_body(req: SearchRequest, fields: set[str]) -> dict[str, Any]:
    """The wire body of a validated search request (or a subclass's, with its ``fields``)."""
    req.validate()
    body: dict[str, Any] = {k: getattr(req, k) for k in fields if k != "embeddings"}
    body = {k: v for k, v in body.items() if v is not None}
    if req.embeddings is not None:
        body["embeddings"] = np.ascontiguousarray(req.embeddings, np.float32)
    return body


def request_fields(data: bytes | bytearray | memoryview, schema: str, fields: set[str],
                   limits: WireLimits | None = None) -> dict[str, Any]:
    """The keyword arguments of a search request (or a subclass's) read from the wire: unknown
    fields and a non-array ``embeddings`` are one-line :class:`MessageError`."""
    body = _decode(data, schema, limits or SEARCH_REQUEST_LIMITS)
    unknown = set(body) - fields
    if unknown:
        raise MessageError(f"{schema}: unknown fields {sorted(unknown)}")
    emb = body.get("embeddings")
    if emb is not None and not isinstance(emb, np.ndarray):
        raise MessageError("embeddings must be a float32 array")
    return {k: body[k] for k in fields if k in body}


def encode_search_request(req: SearchRequest) -> bytes:
    return encode_message(SCHEMA_SEARCH_REQUEST, VERSION, request_body(req, REQUEST_FIELDS))


def decode_search_request(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> SearchRequest:
    return SearchRequest(**request_fields(data, SCHEMA_SEARCH_REQUEST, REQUEST_FIELDS, limits)).validate()


@dataclass
class SearchReply:
    """What the mapper answers to a search (lists of plain dicts, see README "For planners"):

    * ``found``: instances ``{id, target, centroid, box_min, box_max, confidence, voxels,
      observations, first_seen, last_seen}`` (ids stable across searches of the same target
      set), best confidence first;
    * ``look_next``: goals ``{position, heading_rad, score, ray_z, gain_m3, distance_m, target,
      frontier, rays}``, best first;
    * ``beyond``: ``{rays: [{origin, direction, score, target}], estimates: [{position,
      radius_m, score, target}], search_volume_m3}``;
    * ``events``: tracker events of this update ``{kind, id, target, frame, parent?, merged?}``;
    * ``missing_shards``: set by the client on an answer merged from several mapper shards
      (``query_client.search_merge``): shards it saw that did not answer. Merged, instance ids
      are ``"<shard>:<n>"`` strings, instances / goals / events name their ``shard`` and an
      instance seen by two shards lists both ids in ``parts``.
    """

    id: str = ""
    found: list = field(default_factory=list)
    look_next: list = field(default_factory=list)
    beyond: dict = field(default_factory=lambda: {"rays": [], "estimates": [], "search_volume_m3": 0.0})
    events: list = field(default_factory=list)
    frames_mapped: int = 0
    map_version: int = 0
    timings_ms: dict = field(default_factory=dict)
    missing_shards: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready dict (the reply's fields)."""
        return dict(found=self.found, look_next=self.look_next, beyond=self.beyond, frames_mapped=self.frames_mapped,
                    map_version=self.map_version, timings_ms=self.timings_ms, events=self.events, id=self.id,
                    missing_shards=[str(v) for v in self.missing_shards])


def encode_search_reply(rep: SearchReply) -> bytes:
    return encode_message(SCHEMA_SEARCH_REPLY, VERSION, rep.to_dict())


def decode_search_reply(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> SearchReply:
    body = _decode(data, SCHEMA_SEARCH_REPLY, limits)
    for k, t in (("found", list), ("look_next", list), ("beyond", dict), ("events", list), ("timings_ms", dict),
                 ("missing_shards", list)):
        if not isinstance(body.get(k, t()), t):
            raise MessageError(f"{SCHEMA_SEARCH_REPLY}: {k!r} must be a {t.__name__}")
    return SearchReply(id=str(body.get("id", "")), found=body.get("found", []), look_next=body.get("look_next", []),
                       beyond=body.get("beyond", {}), events=body.get("events", []),
                       frames_mapped=int(body.get("frames_mapped", 0)), map_version=int(body.get("map_version", 0)),
                       timings_ms=body.get("timings_ms", {}),
                       missing_shards=[str(v) for v in body.get("missing_shards", [])])


# ------------------------------------------------------------------- occupancy
@dataclass
class OccupancyRequest:
    """``kind`` "box" (``box_min``/``box_max`` [x, y, z]), "slice" (``box_min``/``box_max``
    [x, y], ``z_band`` [z0, z1]) or "points" (``points`` (N, 3), ``radius`` for the distance
    to the nearest occupied voxel); ``stride``: cell size in map voxels (box, slice)."""

    kind: str = "box"
    box_min: list[float] | None = None
    box_max: list[float] | None = None
    z_band: list[float] | None = None
    points: np.ndarray | None = None
    stride: int = 1
    radius: float = 1.0

    def validate(self) -> "OccupancyRequest":
        if self.kind not in OCC_KINDS:
            raise MessageError(f"occupancy kind must be one of {OCC_KINDS}, got {self.kind!r}")
        self.stride = _int_in(self.stride, 1, 1024, "stride")
        if self.kind == "points":
            p = np.asarray(self.points if self.points is not None else np.zeros((0, 3)))
            if p.ndim != 2 or p.shape[1] != 3 or not np.issubdtype(p.dtype, np.number) or not np.isfinite(p).all():
                raise MessageError("points must be finite numbers of shape (N, 3)")
            if len(p) > MAX_OCC_POINTS:
                raise MessageError(f"{len(p)} points exceed the limit of {MAX_OCC_POINTS} points")
            self.points = p.astype(np.float64)
            if isinstance(self.radius, bool) or not isinstance(self.radius, (int, float)) \
                    or not 0 <= float(self.radius) <= 50.0:
                raise MessageError(f"radius must be in [0, 50] m, got {self.radius!r}")
            return self
        n = 3 if self.kind == "box" else 2
        if self.box_min is None or self.box_max is None:
            raise MessageError(f"occupancy {self.kind} needs box_min and box_max")
        self.box_min = _finite_list(self.box_min, n, "box_min")
        self.box_max = _finite_list(self.box_max, n, "box_max")
        if any(b < a for a, b in zip(self.box_min, self.box_max, strict=True)):
            raise MessageError(f"box_max must be >= box_min, got {self.box_min} .. {self.box_max}")
        if self.kind == "slice":
            if self.z_band is None:
                raise MessageError("occupancy slice needs z_band [z0, z1]")
            self.z_band = _finite_list(self.z_band, 2, "z_band [z0, z1]")
            if self.z_band[1] < self.z_band[0]:
                raise MessageError(f"z_band [z0, z1] needs z0 <= z1, got {self.z_band}")
        return self


def encode_occupancy_request(req: OccupancyRequest) -> bytes:
    req.validate()
    body: dict[str, Any] = {"kind": req.kind, "stride": req.stride, "radius": float(req.radius)}
    for k in ("box_min", "box_max", "z_band"):
        if getattr(req, k) is not None:
            body[k] = getattr(req, k)
    if req.points is not None:
        body["points"] = np.ascontiguousarray(req.points, np.float64)
    return encode_message(SCHEMA_OCCUPANCY_REQUEST, VERSION, body)


def decode_occupancy_request(data: bytes | bytearray | memoryview,
                             limits: WireLimits | None = None) -> OccupancyRequest:
    body = _decode(data, SCHEMA_OCCUPANCY_REQUEST, limits or SEARCH_REQUEST_LIMITS)
    unknown = set(body) - _OCC_FIELDS
    if unknown:
        raise MessageError(f"{SCHEMA_OCCUPANCY_REQUEST}: unknown fields {sorted(unknown)}")
    return OccupancyRequest(**{k: body[k] for k in _OCC_FIELDS if k in body}).validate()


@dataclass
class OccupancyReply:
    """``states`` int8 (0 free, 1 occupied, -1 unknown): (nx, ny, nz) for a box, (nx, ny) for
    a slice, (N,) for points; ``origin`` min corner of cell 0 (m), ``cell_m`` cell size;
    ``dist`` (N,) float64 distance to the nearest occupied voxel (inf beyond the radius);
    ``missing_shards`` set by the client on an answer merged from several mapper shards
    (``query_client.search_merge``): shards it saw that did not answer."""

    kind: str = "box"
    states: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int8))
    origin: list[float] = field(default_factory=list)
    cell_m: float = 0.0
    dist: np.ndarray | None = None
    frames_mapped: int = 0
    map_version: int = 0
    missing_shards: list = field(default_factory=list)


def encode_occupancy_reply(rep: OccupancyReply) -> bytes:
    body: dict[str, Any] = {"kind": rep.kind, "states": np.ascontiguousarray(rep.states, np.int8),
                            "shape": [int(s) for s in np.shape(rep.states)], "origin": [float(v) for v in rep.origin],
                            "cell_m": float(rep.cell_m), "frames_mapped": int(rep.frames_mapped),
                            "map_version": int(rep.map_version)}
    if rep.dist is not None:
        body["dist"] = np.ascontiguousarray(rep.dist, np.float64)
    if rep.missing_shards:
        body["missing_shards"] = [str(v) for v in rep.missing_shards]
    return encode_message(SCHEMA_OCCUPANCY_REPLY, VERSION, body)


def decode_occupancy_reply(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> OccupancyReply:
    body = _decode(data, SCHEMA_OCCUPANCY_REPLY, limits)
    st = body.get("states")
    if not isinstance(st, np.ndarray):
        raise MessageError(f"{SCHEMA_OCCUPANCY_REPLY}: missing states array")
    shape = tuple(int(s) for s in body.get("shape", tuple(st.shape)))
    if int(np.prod(shape)) != st.size:
        raise MessageError(f"{SCHEMA_OCCUPANCY_REPLY}: states size {st.size} does not match shape {shape}")
    dist = body.get("dist")
    missing = body.get("missing_shards", [])
    if not isinstance(missing, list):
        raise MessageError(f"{SCHEMA_OCCUPANCY_REPLY}: 'missing_shards' must be a list")
    return OccupancyReply(kind=str(body.get("kind", "")), states=st.astype(np.int8).reshape(shape),
                          origin=list(body.get("origin", [])), cell_m=float(body.get("cell_m", 0.0)),
                          dist=None if dist is None else np.asarray(dist, np.float64),
                          frames_mapped=int(body.get("frames_mapped", 0)),
                          map_version=int(body.get("map_version", 0)), missing_shards=[str(v) for v in missing])
