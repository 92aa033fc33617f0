"""The console API's reply and request shapes as pydantic models, for its OpenAPI document
(docs/commands.md, ``rayfronts console``; fields as docs/messages.md). World frame, metres,
z up; seconds. Every reply model allows fields beyond those listed (the mapper may add some),
so a newer mapper's replies still match the document."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

Vec = list[float]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


class ErrorReply(BaseModel):
    """Every refusal: one line, with a 4xx status (503 when no mapper answers)."""
    error: str


class FoundInstance(_Open):
    """An instance the search found (ids stable across searches of the same target set)."""
    id: int | str
    target: str
    centroid: Vec
    box_min: Vec | None = None
    box_max: Vec | None = None
    confidence: float
    voxels: int | None = None
    observations: int | None = None
    first_seen: float | None = None
    last_seen: float | None = None


class LookNext(_Open):
    """A goal to look next: a frontier or a ray's approach point, best first."""
    position: Vec
    heading_rad: float | None = None
    score: float
    gain_m3: float | None = None
    distance_m: float | None = None
    target: str | None = None


class Beyond(_Open):
    """Rays and estimates of targets beyond the map."""
    rays: list[dict] = Field(default_factory=list)
    estimates: list[dict] = Field(default_factory=list)
    search_volume_m3: float = 0.0


class SearchReplyModel(_Open):
    """GET/POST /api/search and each event of /api/search/stream: the object
    ``rayfronts search --json`` prints."""
    found: list[FoundInstance]
    look_next: list[LookNext]
    beyond: Beyond
    frames_mapped: int
    map_version: int
    timings_ms: dict[str, float]
    events: list[dict] = Field(default_factory=list, description="tracker events of this map version "
                                                                 "{kind, id, target, ...} (docs/messages.md)")


class FleetRobot(_Open):
    """One robot of a fleet search: ``state`` assigned / idle / waiting (no pose yet) / gone."""
    state: str
    position: Vec | None = None
    unreachable: int = 0


class FleetSearchReplyModel(_Open):
    """GET/POST /api/fleet_search and each event of /api/fleet_search/stream: the object
    ``rayfronts search --fleet ... --json`` prints (docs/fleet.md "Fleet search")."""
    id: str = ""
    goals: dict[str, LookNext | None] = Field(description="robot -> its goal (distance_m: its own path) or null")
    robots: dict[str, FleetRobot]
    waiting: list[str]
    gone: list[str]
    found: list[FoundInstance] = Field(description="found instances, shared by the fleet")
    candidates: list[LookNext]
    utility: float
    method: str
    footprint_m: float
    events: list[dict] = Field(default_factory=list)
    frames_mapped: int
    map_version: int
    timings_ms: dict[str, float]
    missing_shards: list[str] = Field(default_factory=list)


class QueryReply(_Open):
    """GET/POST /api/query and each event of /api/query/stream: clusters (voxels of high
    similarity) and rays, best first."""
    id: str = ""
    query: str
    cluster_xyz: list[Vec]
    cluster_size: list[int]
    cluster_extent: list[Vec]
    cluster_score: list[float]
    voxel_xyz: list[Vec]
    voxel_score: list[float]
    ray_origin: list[Vec]
    ray_direction: list[Vec]
    ray_score: list[float]
    search_volume_m3: float
    frames_mapped: int
    stamp: float
    timings: dict[str, float]
    missing_shards: list[str] = Field(default_factory=list)


class OccupancyReply(_Open):
    """Occupancy of a box, a slice or points: ``states`` 0 free, 1 occupied, -1 unknown;
    ``dist`` (points only) metres to the nearest occupied voxel, null when none within the radius."""
    kind: str
    shape: list[int]
    states: list
    origin: Vec
    cell_m: float
    frames_mapped: int
    map_version: int
    dist: list[float | None] | None = None


class RobotState(_Open):
    mapped: int
    rate_hz: float | None = None
    dropped: int
    edge_status: str
    edge_reason: str
    present: bool
    last_seen: float | None = None
    last_seen_s_ago: float | None = None


class ShardState(_Open):
    frames: dict
    map_version: int | None = None
    robots: dict[str, RobotState]


class Refused(BaseModel):
    """Requests the console refused since it started, by reason: 401, 429 over --rate-limit,
    413, event streams past the caps."""
    token: int
    rate: int
    body_too_large: int
    streams: int


class ConsoleState(_Open):
    open_streams: int
    refused: Refused


class StatsReply(_Open):
    """Per shard ("" for an unsharded mapper) and robot; ``raw``: each mapper's full stats."""
    shards: dict[str, ShardState]
    raw: dict[str, dict]
    robots_alive: list[str]
    console: ConsoleState


class SnapshotReply(_Open):
    """The last snapshot (``{}`` when there is none yet): path, map version, frames... as
    docs/messages.md#snapshot."""


class ConfigReply(BaseModel):
    """What the page needs: the mapper's web viewer to embed (null: none)."""
    viewer_url: str | None


class QueryBody(BaseModel):
    """POST /api/query as JSON: a text query."""
    q: str = Field(..., description="query text")
    top_k: int = Field(5, description="clusters and rays to return (>= 1)")
    softmax: bool = False


class ImageQueryForm(BaseModel):
    """POST /api/query as multipart/form-data: an image query."""
    image: bytes = Field(..., description="JPEG or PNG, at most 8 MiB")
    top_k: int = 5
