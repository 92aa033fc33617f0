"""Message schemas other than frames (docs/messages.md): feature-space envelope, query request and
result, map layers, stats, snapshot control.

Every message is ``common.wire.encode_message(schema, v, body)``: a msgpack header with the
schema name and version, numpy arrays carried out of band (zero-copy on decode). Every
decoder here validates what it reads (schema, version, required fields, dtypes, shapes
consistent with each other) and raises :class:`MessageError` with a message that says what
is wrong; callers in Zenoh callbacks catch it, count it and reply with an error.

Units: positions and lengths in metres in the mapper's world frame (z up), volumes in m³,
timings in milliseconds, stamps in seconds.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.wire import WireError, WireLimits, decode_message, encode_message

SCHEMA_FEATURE_SPACE = "rayfronts.feature_space"
SCHEMA_QUERY_REQUEST = "rayfronts.query_request"
SCHEMA_QUERY_RESULT = "rayfronts.query_result"
SCHEMA_LAYER = "rayfronts.layer"
SCHEMA_STATS = "rayfronts.stats"
SCHEMA_SNAPSHOT_REQUEST = "rayfronts.snapshot_request"
SCHEMA_SNAPSHOT_REPLY = "rayfronts.snapshot_reply"
SCHEMA_ERROR = "rayfronts.error"
SCHEMA_EDGE_STATUS = "rayfronts.edge_status"
SCHEMA_SIM_VIEWS = "rayfronts.sim_views"
VERSION = 1

#: limits on query requests (a request over them is rejected, not truncated)
MAX_TEXT_CHARS = 1000
MAX_IMAGE_BYTES = 20 * 1024 * 1024
#: the header profile a query request is decoded under (the mapper decodes requests from any
#: operator): an image travels as one binary (a memcpy), everything else is a few small
#: fields, so the cost of rejecting any request is bounded (containers, strings, nesting)
QUERY_REQUEST_LIMITS = WireLimits(max_message_bytes=MAX_IMAGE_BYTES + (1 << 20),
                                  max_header_bytes=MAX_IMAGE_BYTES + (64 << 10), max_container_len=64,
                                  max_nesting=4, max_containers=64, max_str_bytes=64 << 10)
MAX_TOP_K = 100_000
_ID_RE = re.compile(r"^[A-Za-z0-9_-]{0,64}$")
#: longest lease a standing query / search may ask for (s)
MAX_LEASE_S = 3600.0

LAYERS = ("voxels", "frontiers", "rays", "occupancy")


class MessageError(ValueError):
    """A message that cannot be decoded or fails validation; the text says why."""


def _decode(data: bytes | bytearray | memoryview, schema: str, limits: WireLimits | None = None) -> dict:
    try:
        got, v, body = decode_message(bytes(data) if not isinstance(data, (bytes, bytearray)) else data,
                                      limits=limits)
    except WireError as e:
        raise MessageError(f"{schema}: {e}") from None
    if got == SCHEMA_ERROR:
        raise MessageError(f"remote error: {body.get('error', '?') if isinstance(body, dict) else body}")
    if got != schema:
        raise MessageError(f"expected schema {schema!r}, got {got!r}")
    if v != VERSION:
        raise MessageError(f"{schema}: unsupported version {v!r} (this build reads v{VERSION})")
    if not isinstance(body, dict):
        raise MessageError(f"{schema}: body is not a mapping")
    return body


def _arr(body: dict, key: str, schema: str, dtype, ndim: int, last: int | None = None) -> np.ndarray:
    a = body.get(key)
    if a is None:
        raise MessageError(f"{schema}: missing field {key!r}")
    if not isinstance(a, np.ndarray):
        a = np.asarray(a)
    if a.ndim != ndim or (last is not None and a.shape[-1] != last):
        raise MessageError(f"{schema}: field {key!r} has shape {a.shape}, expected {ndim}-d"
                           + (f" with last dim {last}" if last is not None else ""))
    if a.size and not np.can_cast(a.dtype, dtype, casting="same_kind"):
        raise MessageError(f"{schema}: field {key!r} has dtype {a.dtype}, expected {np.dtype(dtype)}")
    return a.astype(dtype, copy=False)


# --------------------------------------------------------------------------- errors
def encode_error(error: str) -> bytes:
    """A reply that says a request failed (decoders raise MessageError with the text)."""
    return encode_message(SCHEMA_ERROR, VERSION, {"error": str(error)})


# ------------------------------------------------------------------ feature space
def encode_feature_space(robot: str, space_body: dict) -> bytes:
    """Envelope for ``FeatureSpace.to_body()`` served on ``robots/<robot>/feature_space``."""
    return encode_message(SCHEMA_FEATURE_SPACE, VERSION, {"robot": robot, "space": space_body})


def decode_feature_space(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> tuple[str, dict]:
    """→ ``(robot, space_body)``; feed ``space_body`` to ``FeatureSpace.from_body``."""
    body = _decode(data, SCHEMA_FEATURE_SPACE, limits)
    robot, space = body.get("robot"), body.get("space")
    if not isinstance(robot, str) or not isinstance(space, dict):
        raise MessageError(f"{SCHEMA_FEATURE_SPACE}: needs 'robot' (str) and 'space' (map)")
    return robot, space


# -------------------------------------------------------------------------- query
@dataclass(kw_only=True)
class StandingControl:
    """The standing-request fields that :class:`QueryRequest` and
    :class:`common.search_messages.SearchRequest` share (keyword-only, so each request keeps
    its own fields first in ``__init__``; the wire bodies name every field, so their bytes do
    not depend on this base): ``standing`` registers the request under ``id``; ``cancel``
    drops the standing request ``id``; it lives ``lease_s`` seconds (0 = the mapper's
    default) unless renewed (``renew`` + ``id``); ``client`` names the asker (per-client cap)."""

    standing: bool = False
    cancel: bool = False
    id: str = ""
    lease_s: float = 0.0
    renew: bool = False
    client: str = ""

    def check_control(self, noun: str) -> bool:
        """Validate ``lease_s`` / ``renew`` / ``client`` (:func:`check_lease`) and, for a cancel
        or renew, that it names the standing ``noun``'s ``id``; one-line :class:`MessageError`.
        Returns whether this is a cancel or renew (the other fields then do not matter)."""
        self.lease_s = check_lease(self.lease_s, self.renew, self.client)
        if not (self.cancel or self.renew):
            return False
        if not self.id:
            raise MessageError(f"a {'cancel' if self.cancel else 'renew'} request needs the standing {noun} id")
        return True


@dataclass
class QueryRequest(StandingControl):
    """An open-vocabulary query: exactly one of ``text``, ``image`` (JPEG/PNG bytes) or
    ``embedding`` (a vector in the map's language space, e.g. from a planner).

    ``standing=True`` registers the query to be re-run after map updates and published on
    ``mapper/queries/<id>``; ``cancel=True`` removes the standing query ``id``. A standing
    query lives ``lease_s`` seconds (0 = the mapper's ``query.lease_s``) unless renewed
    (``renew=True`` + ``id``); ``client`` names the asker for the mapper's per-client cap."""

    text: str | None = None
    image: bytes | None = None
    embedding: np.ndarray | None = None
    top_k: int = 10
    softmax: bool = False

    def validate(self) -> "QueryRequest":
        given = [n for n in ("text", "image", "embedding") if getattr(self, n) is not None]
        if not self.check_control("query") and len(given) != 1:
            raise MessageError(f"a query needs exactly one of text, image, embedding (got {given or 'none'})")
        if self.text is not None:
            if not isinstance(self.text, str) or not self.text.strip():
                raise MessageError("query text must be a non-empty string")
            if len(self.text) > MAX_TEXT_CHARS:
                raise MessageError(f"query text longer than {MAX_TEXT_CHARS} characters")
        if self.image is not None:
            if not isinstance(self.image, (bytes, bytearray)) or not self.image:
                raise MessageError("query image must be non-empty encoded image bytes")
            if len(self.image) > MAX_IMAGE_BYTES:
                raise MessageError(f"query image larger than {MAX_IMAGE_BYTES} bytes")
        if self.embedding is not None:
            e = np.asarray(self.embedding)
            if e.ndim != 1 or e.size == 0 or not np.issubdtype(e.dtype, np.floating) or not np.all(np.isfinite(e)):
                raise MessageError("query embedding must be a finite 1-d float vector")
        if isinstance(self.top_k, bool) or not isinstance(self.top_k, int) or not 1 <= self.top_k <= MAX_TOP_K:
            raise MessageError(f"top_k must be an integer in [1, {MAX_TOP_K}], got {self.top_k!r}")
        if not isinstance(self.id, str) or not _ID_RE.match(self.id):
            raise MessageError(f"query id {self.id!r} must match [A-Za-z0-9_-]{{0,64}}")
        if self.standing and not self.id:
            raise MessageError("a standing query needs an id")
        return self

    @property
    def label(self) -> str:
        if self.text is not None:
            return self.text
        return "<image>" if self.image is not None else "<embedding>"


def check_lease(lease_s: Any, renew: Any, client: Any) -> float:
    """The validated ``lease_s`` (seconds, 0 = the mapper's default) of a standing request,
    after checking ``renew`` (bool) and ``client`` (an id, may be empty); one-line errors."""
    if isinstance(lease_s, bool) or not isinstance(lease_s, (int, float)) or not 0.0 <= lease_s <= MAX_LEASE_S:
        raise MessageError(f"lease_s must be seconds in [0, {MAX_LEASE_S:g}] (0 = the mapper's default), "
                           f"got {lease_s!r}")
    if not isinstance(renew, bool):
        raise MessageError("'renew' must be true/false")
    if not isinstance(client, str) or not _ID_RE.match(client):
        raise MessageError(f"client id {client!r} must match [A-Za-z0-9_-]{{0,64}}")
    return float(lease_s)


def encode_query_request(req: QueryRequest) -> bytes:
    req.validate()
    body: dict[str, Any] = {"top_k": int(req.top_k), "softmax": bool(req.softmax), "standing": bool(req.standing),
                            "cancel": bool(req.cancel), "id": req.id, "lease_s": req.lease_s, "renew": req.renew,
                            "client": req.client}
    if req.text is not None:
        body["text"] = req.text
    if req.image is not None:
        body["image"] = bytes(req.image)
    if req.embedding is not None:
        body["embedding"] = np.ascontiguousarray(req.embedding, dtype=np.float32)
    return encode_message(SCHEMA_QUERY_REQUEST, VERSION, body)


def decode_query_request(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> QueryRequest:
    body = _decode(data, SCHEMA_QUERY_REQUEST, limits or QUERY_REQUEST_LIMITS)
    unknown = set(body) - {"text", "image", "embedding", "top_k", "softmax", "standing", "cancel", "id", "lease_s",
                           "renew", "client"}
    if unknown:
        raise MessageError(f"{SCHEMA_QUERY_REQUEST}: unknown fields {sorted(unknown)}")
    emb = body.get("embedding")
    if emb is not None:
        emb = _arr(body, "embedding", SCHEMA_QUERY_REQUEST, np.float32, 1)
    req = QueryRequest(text=body.get("text"), image=body.get("image"), embedding=emb,
                       top_k=body.get("top_k", 10), softmax=body.get("softmax", False),
                       standing=body.get("standing", False), cancel=body.get("cancel", False),
                       id=body.get("id", ""), lease_s=body.get("lease_s", 0.0), renew=body.get("renew", False),
                       client=body.get("client", ""))
    for k in ("softmax", "standing", "cancel"):
        if not isinstance(getattr(req, k), bool):
            raise MessageError(f"{SCHEMA_QUERY_REQUEST}: {k!r} must be true/false")
    return req.validate()


@dataclass
class QueryResult:
    """What the mapper answers to a query (world frame, metres).

    * voxel clusters: the top voxels grouped into connected clusters —
      ``cluster_xyz`` (K, 3) centroids, ``cluster_size`` (K,) voxel counts,
      ``cluster_extent`` (K, 3) bounding-box sizes, ``cluster_score`` (K,) best score;
      sorted by score, best first.
    * ``voxel_xyz`` (N, 3) centres and ``voxel_score`` (N,) of the top voxels, best first.
    * rays: ``ray_origin`` (R, 3), ``ray_direction`` (R, 3) unit, ``ray_score`` (R,), best first.
    * ``search_volume_m3``: volume of the cones of the top rays (beyond-range search volume).
    * ``timings``: milliseconds per stage (``encode``, ``similarity``, ``total``, ...).
    * ``missing_shards``: shards the client saw (liveliness) that did not answer this merged
      result (set by the client; empty from one mapper).
    * ``half_angle_deg``, ``score_min``: set by the mapper for the shard info of its reply (the
      search cone's half-angle, the lowest voxel score); not on the wire, None on the client
      side and then left out of :meth:`to_dict`.
    """

    id: str = ""
    query: str = ""
    cluster_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    cluster_size: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int32))
    cluster_extent: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    cluster_score: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.float32))
    voxel_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    voxel_score: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.float32))
    ray_origin: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    ray_direction: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    ray_score: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.float32))
    search_volume_m3: float = 0.0
    frames_mapped: int = 0
    stamp: float = 0.0
    timings: dict = field(default_factory=dict)
    missing_shards: list = field(default_factory=list)
    half_angle_deg: float | None = field(default=None, repr=False, compare=False)
    score_min: float | None = field(default=None, repr=False, compare=False)

    _ARRAYS = {
        "cluster_xyz": (np.float32, 2, 3), "cluster_size": (np.int32, 1, None),
        "cluster_extent": (np.float32, 2, 3), "cluster_score": (np.float32, 1, None),
        "voxel_xyz": (np.float32, 2, 3), "voxel_score": (np.float32, 1, None),
        "ray_origin": (np.float32, 2, 3), "ray_direction": (np.float32, 2, 3), "ray_score": (np.float32, 1, None),
    }

    def validate(self) -> "QueryResult":
        groups = (("cluster_xyz", "cluster_size", "cluster_extent", "cluster_score"),
                  ("voxel_xyz", "voxel_score"), ("ray_origin", "ray_direction", "ray_score"))
        for g in groups:
            n = {len(getattr(self, k)) for k in g}
            if len(n) != 1:
                raise MessageError(f"{SCHEMA_QUERY_RESULT}: fields {g} have different lengths {n}")
        return self

    def to_dict(self) -> dict:
        """JSON-ready dict (lists instead of arrays)."""
        out = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()
               if v is not None or k not in _MAPPER_ONLY}
        return out


_MAPPER_ONLY = ("half_angle_deg", "score_min")     # QueryResult fields not on the wire


def encode_query_result(res: QueryResult) -> bytes:
    res.validate()
    body: dict[str, Any] = {"id": res.id, "query": res.query, "search_volume_m3": float(res.search_volume_m3),
                            "frames_mapped": int(res.frames_mapped), "stamp": float(res.stamp),
                            "timings": {str(k): float(v) for k, v in res.timings.items()}}
    if res.missing_shards:
        body["missing_shards"] = [str(v) for v in res.missing_shards]
    for k, (dt, _, _) in QueryResult._ARRAYS.items():
        body[k] = np.ascontiguousarray(getattr(res, k), dtype=dt)
    return encode_message(SCHEMA_QUERY_RESULT, VERSION, body)


def decode_query_result(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> QueryResult:
    body = _decode(data, SCHEMA_QUERY_RESULT, limits)
    kw: dict[str, Any] = {}
    for k, (dt, nd, last) in QueryResult._ARRAYS.items():
        kw[k] = _arr(body, k, SCHEMA_QUERY_RESULT, dt, nd, last)
    timings = body.get("timings", {})
    if not isinstance(timings, dict):
        raise MessageError(f"{SCHEMA_QUERY_RESULT}: 'timings' must be a map")
    missing = body.get("missing_shards", [])
    if not isinstance(missing, list):
        raise MessageError(f"{SCHEMA_QUERY_RESULT}: 'missing_shards' must be a list")
    return QueryResult(id=str(body.get("id", "")), query=str(body.get("query", "")),
                       search_volume_m3=float(body.get("search_volume_m3", 0.0)),
                       frames_mapped=int(body.get("frames_mapped", 0)), stamp=float(body.get("stamp", 0.0)),
                       timings=dict(timings), missing_shards=[str(v) for v in missing], **kw).validate()


# ------------------------------------------------------------------------- layers
#: arrays each layer carries: name -> {field: (dtype, ndim, last dim)}
LAYER_FIELDS: dict[str, dict[str, tuple[Any, int, int]]] = {
    "voxels": {"xyz": (np.float32, 2, 3), "rgb": (np.uint8, 2, 3)},
    "frontiers": {"xyz": (np.float32, 2, 3)},
    "rays": {"origin": (np.float32, 2, 3), "direction": (np.float32, 2, 3)},
    "occupancy": {},
}


def encode_layer(layer: str, arrays: dict[str, np.ndarray], meta: dict | None = None) -> bytes:
    """A map layer for viewers and planners; ``meta`` holds small scalars (counts, voxel size,
    total before subsampling, stamp)."""
    if layer not in LAYER_FIELDS:
        raise MessageError(f"unknown layer {layer!r}; one of {', '.join(LAYER_FIELDS)}")
    body: dict[str, Any] = {"layer": layer, "meta": dict(meta or {})}
    for k, (dt, _, _) in LAYER_FIELDS[layer].items():
        body[k] = np.ascontiguousarray(arrays[k], dtype=dt)
    return encode_message(SCHEMA_LAYER, VERSION, body)


def decode_layer(data: bytes | bytearray | memoryview,
                 limits: WireLimits | None = None) -> tuple[str, dict[str, np.ndarray], dict]:
    """→ ``(layer, arrays, meta)``."""
    body = _decode(data, SCHEMA_LAYER, limits)
    layer = body.get("layer")
    if layer not in LAYER_FIELDS:
        raise MessageError(f"{SCHEMA_LAYER}: unknown layer {layer!r}")
    arrays = {k: _arr(body, k, SCHEMA_LAYER, dt, nd, last) for k, (dt, nd, last) in LAYER_FIELDS[layer].items()}
    lens = {len(a) for a in arrays.values()}
    if len(lens) > 1:
        raise MessageError(f"{SCHEMA_LAYER}: layer {layer!r} arrays have different lengths {lens}")
    meta = body.get("meta", {})
    if not isinstance(meta, dict):
        raise MessageError(f"{SCHEMA_LAYER}: 'meta' must be a map")
    return layer, arrays, meta


# -------------------------------------------------------------------- stats, snapshot
def encode_stats(stats: dict) -> bytes:
    """Mapper statistics: a nested map of numbers and strings (see ``mapper.service``)."""
    return encode_message(SCHEMA_STATS, VERSION, stats)


def decode_stats(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> dict:
    return _decode(data, SCHEMA_STATS, limits)


SNAPSHOT_ACTIONS = ("save", "describe")


def encode_snapshot_request(action: str = "describe") -> bytes:
    if action not in SNAPSHOT_ACTIONS:
        raise MessageError(f"snapshot action {action!r} is not one of {SNAPSHOT_ACTIONS}")
    return encode_message(SCHEMA_SNAPSHOT_REQUEST, VERSION, {"action": action})


def decode_snapshot_request(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> str:
    body = _decode(data, SCHEMA_SNAPSHOT_REQUEST, limits)
    action = body.get("action", "describe")
    if action not in SNAPSHOT_ACTIONS:
        raise MessageError(f"snapshot action {action!r} is not one of {SNAPSHOT_ACTIONS}")
    return action


def encode_snapshot_reply(info: dict) -> bytes:
    """``{"path", "frames_mapped", "stamp", "voxels", "seconds"}``, or ``{}`` if none yet."""
    return encode_message(SCHEMA_SNAPSHOT_REPLY, VERSION, dict(info))


def decode_snapshot_reply(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> dict:
    return _decode(data, SCHEMA_SNAPSHOT_REPLY, limits)


# -------------------------------------------------------------------- edge status
#: states an edge reports on ``robots/<robot>/edge_status``. ``refused``: it could not start
#: (invalid config combination, missing model or basis file, ...); ``failed``: it died while
#: running; both carry the reason, one line.
EDGE_STATES = ("starting", "running", "done", "refused", "failed")
MAX_REASON_CHARS = 2000


def encode_edge_status(robot: str, state: str, reason: str = "", stamp: float = 0.0) -> bytes:
    """The edge's state (one of ``EDGE_STATES``), its reason (truncated) and ``stamp`` (wall clock, s)."""
    if state not in EDGE_STATES:
        raise MessageError(f"edge state must be one of {EDGE_STATES}, got {state!r}")
    return encode_message(SCHEMA_EDGE_STATUS, VERSION, {"robot": str(robot), "state": state,
                                                        "reason": str(reason)[:MAX_REASON_CHARS],
                                                        "stamp": float(stamp)})


def decode_edge_status(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> dict:
    """→ ``{"robot", "state", "reason", "stamp"}`` (validated)."""
    body = _decode(data, SCHEMA_EDGE_STATUS, limits)
    robot, state, reason = body.get("robot"), body.get("state"), body.get("reason", "")
    if not isinstance(robot, str) or not _ID_RE.match(robot) or not robot:
        raise MessageError(f"{SCHEMA_EDGE_STATUS}: bad robot id {robot!r}")
    if state not in EDGE_STATES:
        raise MessageError(f"{SCHEMA_EDGE_STATUS}: unknown state {state!r}")
    if not isinstance(reason, str) or len(reason) > MAX_REASON_CHARS:
        raise MessageError(f"{SCHEMA_EDGE_STATUS}: reason must be a string of at most {MAX_REASON_CHARS} chars")
    stamp = body.get("stamp", 0.0)
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float)):
        raise MessageError(f"{SCHEMA_EDGE_STATUS}: stamp must be a number")
    return {"robot": robot, "state": state, "reason": reason, "stamp": float(stamp)}


# ------------------------------------------------------------------ simulated camera
#: most camera poses one sim-views message may ask for
MAX_SIM_VIEWS = 64


def encode_sim_views(step: int, poses: np.ndarray) -> bytes:
    """Camera poses (N, 4, 4) camera-to-world (RDF camera axes, metres) a simulator asks its
    robot's edge to render next, as step ``step`` of an episode (``source.kind=sim_camera``)."""
    p = np.ascontiguousarray(poses, np.float64).reshape(-1, 4, 4)
    return encode_message(SCHEMA_SIM_VIEWS, VERSION, {"step": int(step), "poses": p})


def decode_sim_views(data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> tuple[int, np.ndarray]:
    """→ ``(step, poses (N, 4, 4) float64)``; 1 ≤ N ≤ :data:`MAX_SIM_VIEWS`, every pose finite."""
    body = _decode(data, SCHEMA_SIM_VIEWS, limits)
    step = body.get("step")
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise MessageError(f"{SCHEMA_SIM_VIEWS}: step must be an integer >= 0, got {step!r}")
    poses = _arr(body, "poses", SCHEMA_SIM_VIEWS, np.float64, 3)
    if poses.shape[1:] != (4, 4) or not 1 <= len(poses) <= MAX_SIM_VIEWS:
        raise MessageError(f"{SCHEMA_SIM_VIEWS}: poses must be (N, 4, 4) with 1 <= N <= {MAX_SIM_VIEWS}, "
                           f"got {poses.shape}")
    if not np.isfinite(poses).all():
        raise MessageError(f"{SCHEMA_SIM_VIEWS}: poses must be finite")
    return step, poses
