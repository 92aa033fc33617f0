"""The console's HTTP API and page (FastAPI): JSON over the mapper's Zenoh calls through one
``query_client.Client`` (docs/commands.md, ``rayfronts console``; replies as docs/messages.md).

Errors are one JSON line ``{"error": "..."}`` with a 4xx status (503 when no mapper answers);
a standing search or query streams as server-sent events until the browser disconnects (at most
``max_streams_per_client`` per address and ``max_streams`` in all). With a token, a page opened
as ``/?token=TOKEN`` sets an HttpOnly cookie and is redirected to the clean URL, so the page's
own requests (assets, API calls, event streams) carry the token without it in the URL."""
from __future__ import annotations

import asyncio
import json
import logging
import threading
from collections import Counter
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlencode

import numpy as np
from fastapi import FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, StreamingResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from apps.console.models import (
    ConfigReply,
    ErrorReply,
    FleetSearchReplyModel,
    ImageQueryForm,
    OccupancyReply,
    QueryBody,
    QueryReply,
    SearchReplyModel,
    SnapshotReply,
    StatsReply,
)
from apps.console.security import (
    COOKIE,
    MAX_BODY_BYTES,
    TOKEN_HELP,
    BodyCap,
    RateLimiter,
    StreamSlots,
    token_cookie,
    token_ok,
)
from query_client.vocabulary import fleet_reply_json, query_fields, search_reply_json

log = logging.getLogger("rayfronts.console")
STATIC = Path(__file__).with_name("static")


Targets = Annotated[list[str], Query(description="targets: ?q=vehicle&q=car")]
Background = Annotated[list[str] | None, Query(description="background phrases")]


class SearchBody(BaseModel):
    """POST /api/search: the fields of ``rayfronts search`` (world frame, metres, z up)."""
    q: list[str] = Field(..., description="targets (one or more phrases)")
    background: list[str] | None = None
    threshold: float = 0.5
    max_instances: int = 10
    max_goals: int = 5
    from_xyz: list[float] | None = Field(None, alias="from", description="robot position x,y,z")
    area: list[float] | None = Field(None, description="box x0,y0,x1,y1 or polygon x0,y0,x1,y1,x2,y2,...")
    z_band: list[float] | None = None
    model_config = {"populate_by_name": True}


class FleetSearchBody(BaseModel):
    """POST /api/fleet_search: the fields of ``rayfronts search --fleet`` (world frame, metres, z up)."""
    q: list[str] = Field(..., description="targets (one or more phrases)")
    fleet: list[str] = Field(..., description="robot ids, or [\"all\"] for every robot present")
    background: list[str] | None = None
    threshold: float = 0.5
    max_instances: int = 10
    max_goals: int = Field(20, description="look-next candidates shared out")
    target_count: int = 1
    footprint_m: float = Field(0.0, description="least distance between two goals, m (0: the mapper's)")
    area: list[float] | None = Field(None, description="box x0,y0,x1,y1 or polygon x0,y0,x1,y1,x2,y2,...")
    z_band: list[float] | None = None


class PointsBody(BaseModel):
    """POST /api/occupancy/points: points (N, 3) in metres and the distance search radius."""
    points: list[list[float]]
    radius: float = 1.0


class ApiError(Exception):
    """A request the console refuses (``status``, one-line ``message``)."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())[:500]


def _err(status: int, msg: Any) -> JSONResponse:
    return JSONResponse({"error": _one_line(msg)}, status_code=status)


def search_kwargs_from(q: list[str], background: list[str] | None, threshold: float, max_instances: int,
                       max_goals: int, from_xyz: str | list[float] | None, area: str | list[float] | None,
                       z_band: str | list[float] | None) -> dict:
    """``Client.search`` keywords from HTTP fields (``query_client.vocabulary.search_fields``: the
    checks and messages of ``rayfronts search``)."""
    from query_client.vocabulary import search_fields

    if not q or not all(t.strip() for t in q):
        raise ApiError(400, "give at least one non-empty target: ?q=vehicle")
    return search_fields(q, background=background, threshold=threshold, max_instances=max_instances,
                         max_goals=max_goals, area=area, z_band=z_band, from_xyz=from_xyz)


def fleet_kwargs_from(q: list[str], fleet: str | list[str], background: list[str] | None, threshold: float,
                      max_instances: int, max_goals: int, target_count: int, footprint_m: float,
                      area: str | list[float] | None, z_band: str | list[float] | None) -> dict:
    """``Client.fleet_search`` keywords from HTTP fields (``query_client.vocabulary.fleet_fields``:
    the checks and messages of ``rayfronts search --fleet``)."""
    from query_client.vocabulary import fleet_fields

    if not q or not all(t.strip() for t in q):
        raise ApiError(400, "give at least one non-empty target: ?q=vehicle")
    return fleet_fields(fleet, q, target_count=target_count, footprint_m=footprint_m, max_goals=max_goals,
                        background=background, threshold=threshold, max_instances=max_instances, area=area,
                        z_band=z_band)


def _occ_json(rep) -> dict:
    d = {"kind": rep.kind, "shape": list(rep.states.shape), "states": rep.states.tolist(),
         "origin": list(rep.origin), "cell_m": rep.cell_m, "frames_mapped": rep.frames_mapped,
         "map_version": rep.map_version, "missing_shards": list(rep.missing_shards)}
    if rep.dist is not None:    # metres; null: no occupied voxel within the radius
        d["dist"] = [float(v) if np.isfinite(v) else None for v in np.asarray(rep.dist, float).ravel()]
    return d


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise ApiError(400, f"{what} must be comma-separated numbers, got {text!r}") from None
    if len(v) != n:
        raise ApiError(400, f"{what} needs {n} comma-separated numbers, got {text!r}")
    return v


def robot_states(stats_by_shard: dict[str, dict], now: float | None = None) -> dict:
    """Per shard and robot (from the mappers' stats): frames mapped, mapping rate (Hz), drops,
    edge status, last seen (wall-clock s, and seconds ago); ``raw`` keeps the full stats."""
    import time

    now = time.time() if now is None else now
    shards = {}
    for shard, st in stats_by_shard.items():
        robots = {}
        for name, r in (st.get("robots") or {}).items():
            seen = float(r.get("seen_at") or 0.0)
            robots[name] = {"mapped": r.get("mapped", 0), "rate_hz": r.get("mapped_hz"),
                            "dropped": r.get("dropped", 0), "edge_status": r.get("edge_state") or "",
                            "edge_reason": r.get("edge_reason") or "", "present": bool(r.get("present")),
                            "last_seen": seen or None, "last_seen_s_ago": round(now - seen, 1) if seen else None}
        shards[shard] = {"frames": st.get("frames", {}), "map_version": st.get("map_version"), "robots": robots}
    return {"shards": shards, "raw": stats_by_shard}


def _install_errors(app: FastAPI) -> None:
    from common.config import ConfigError
    from common.messages import MessageError
    from query_client.client import MapperUnavailable, QueryError

    @app.exception_handler(ApiError)
    async def _api(_r: Request, e: ApiError) -> JSONResponse:
        return _err(e.status, e.message)

    @app.exception_handler(RequestValidationError)
    async def _val(_r: Request, e: RequestValidationError) -> JSONResponse:
        parts = [f"{'.'.join(str(p) for p in x.get('loc', ()))}: {x.get('msg', '')}" for x in e.errors()[:3]]
        return _err(422, "invalid request: " + "; ".join(parts))

    @app.exception_handler(StarletteHTTPException)
    async def _http(_r: Request, e: StarletteHTTPException) -> JSONResponse:
        return _err(e.status_code, e.detail)

    @app.exception_handler(MapperUnavailable)
    async def _unavail(_r: Request, e: Exception) -> JSONResponse:
        return _err(503, e)

    async def _bad_request(_r: Request, e: Exception) -> JSONResponse:
        return _err(400, e)

    for user_error in (QueryError, MessageError, ConfigError):   # what the client and the schemas raise
        app.add_exception_handler(user_error, _bad_request)

    @app.exception_handler(Exception)
    async def _bug(_r: Request, e: Exception) -> JSONResponse:
        log.warning("console: %s: %s", type(e).__name__, e)
        return _err(500, f"{type(e).__name__}: {e}")


def _install_guards(app: FastAPI, token: str | None, limiter: RateLimiter, secure_cookie: bool,
                    refused: Counter) -> None:
    @app.middleware("http")
    async def guard(request: Request, call_next):
        q = request.query_params
        if not token_ok(token, request.headers.get("authorization"), q.get("token"), request.cookies.get(COOKIE)):
            refused["token"] += 1
            return _err(401, TOKEN_HELP)
        addr = request.client.host if request.client else "?"
        if not limiter.allow(addr):
            refused["rate"] += 1
            return _err(429, f"too many requests from {addr} (limit {limiter.per_minute} per minute)")
        if token and "token" in q and request.method in ("GET", "HEAD") and not request.url.path.startswith("/api/"):
            # a page opened with ?token=: keep the token in an HttpOnly cookie, go to the clean URL
            rest = urlencode([(k, v) for k, v in q.multi_items() if k != "token"])
            r = RedirectResponse(request.url.path + (f"?{rest}" if rest else ""), status_code=303)
            r.headers["set-cookie"] = token_cookie(token, secure_cookie)
            r.headers["cache-control"] = "no-store"
            return r
        return await call_next(request)


def _release(handle, slots: StreamSlots, addr: str) -> None:
    """Cancel a standing search/query (the mapper drops it), then free its stream slot."""
    try:
        handle.cancel()
    finally:
        slots.release(addr)


async def _sse(request: Request, start, slots: StreamSlots) -> StreamingResponse:
    """Server-sent events of a standing call: ``start(callback)`` returns a handle with
    ``cancel()``; the handle is cancelled when the client disconnects. Refused (429 per client,
    503 in total) past the caps of ``slots``."""
    addr = request.client.host if request.client else "?"
    refusal = slots.acquire(addr)
    if refusal:
        raise ApiError(503 if "in total" in refusal else 429, refusal)
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue = asyncio.Queue(maxsize=64)

    def push(obj: dict) -> None:
        def put() -> None:
            if queue.full():
                queue.get_nowait()
            queue.put_nowait(obj)
        loop.call_soon_threadsafe(put)

    try:
        handle = await asyncio.to_thread(start, push)
    except BaseException:
        slots.release(addr)
        raise

    async def events():
        try:
            n = 0
            while True:
                if await request.is_disconnected():
                    break
                try:
                    obj = await asyncio.wait_for(queue.get(), timeout=1.0)
                except asyncio.TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                n += 1
                yield f"id: {n}\nevent: update\ndata: {json.dumps(obj)}\n\n"
        finally:
            # not awaited: a cancelled task (client gone) cannot await; the cancel runs in a thread
            threading.Thread(target=_release, args=(handle, slots, addr), daemon=True).start()

    return StreamingResponse(events(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


def _doc(model: type[BaseModel], *codes: int) -> dict:
    """``responses=`` of a route: 200 is ``model``, each of ``codes`` an :class:`ErrorReply`."""
    out: dict[int | str, dict[str, Any]] = {200: {"model": model}}
    for c in (400, 401, 429, *codes):
        out[c] = {"model": ErrorReply}
    return out


def _openapi_security(app: FastAPI, token: bool) -> None:
    """The bearer (and cookie) security schemes in the OpenAPI document; required when a token is set."""
    make = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            spec = make()          # the framework's document, cached in app.openapi_schema
            spec.setdefault("components", {})["securitySchemes"] = {
                "bearer": {"type": "http", "scheme": "bearer", "description": "Authorization: Bearer TOKEN"},
                "cookie": {"type": "apiKey", "in": "cookie", "name": COOKIE,
                           "description": "set by opening the page as /?token=TOKEN"}}
            spec["security"] = [{"bearer": []}, {"cookie": []}] + ([] if token else [{}])
        assert app.openapi_schema is not None     # set by make() above
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def create_app(client, *, token: str | None = None, viewer_url: str | None = None, rate_per_minute: int = 600,
               max_body: int = MAX_BODY_BYTES, timeout: float = 20.0, tls: bool = False, max_streams: int = 32,
               max_streams_per_client: int = 4) -> FastAPI:
    """The console app over a connected ``query_client.Client`` (not closed by the app); ``tls``:
    it is served over HTTPS (the token cookie is then Secure)."""
    app = FastAPI(title="RayFronts console", version="1", docs_url=None, redoc_url=None,
                  description="Operator console and HTTP API of a RayFronts mapper (docs/messages.md).")
    _install_errors(app)
    refused: Counter = Counter()        # requests refused, by reason (/api/stats "console")
    app.add_middleware(BodyCap, max_body=max_body, refused=refused)   # inside the guard: the token is checked first
    _install_guards(app, token, RateLimiter(rate_per_minute), tls, refused)
    _openapi_security(app, bool(token))
    _page_routes(app, viewer_url)
    slots = StreamSlots(max_streams_per_client, max_streams)  # each open stream holds one standing search/query
    _query_routes(app, client, timeout, max_body, slots)
    _search_routes(app, client, timeout, slots)
    _fleet_routes(app, client, timeout, slots)
    _map_routes(app, client, timeout, slots, refused)
    return app


def _page_routes(app: FastAPI, viewer_url: str | None) -> None:
    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    @app.get("/static/{name}", include_in_schema=False)
    def static(name: str) -> FileResponse:
        p = STATIC / name
        if "/" in name or name.startswith(".") or not p.is_file():
            raise ApiError(404, f"no static file {name!r}")
        return FileResponse(p)

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return HTMLResponse((STATIC / "docs.html").read_text())

    @app.get("/api/config", summary="console settings for the page (viewer URL)", responses=_doc(ConfigReply))
    def config() -> dict:
        return {"viewer_url": viewer_url}


_QUERY_BODY = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": QueryBody.model_json_schema()},
    "multipart/form-data": {"schema": ImageQueryForm.model_json_schema()}}}}


_QUERY_EXAMPLE = ": ?q=water+tower"    # how to give a query text, in an error line


def _query_routes(app: FastAPI, client, timeout: float, max_body: int, slots: StreamSlots) -> None:
    @app.get("/api/query", summary="one query (text)", responses=_doc(QueryReply, 503))
    def query_get(q: str = Query(..., description="query text"), top_k: int = Query(5, ge=1, le=1000),
                  softmax: bool = False) -> dict:
        kw = query_fields(q, top_k=top_k, example=_QUERY_EXAMPLE)
        return client.query(**kw, softmax=softmax, timeout=timeout).to_dict()

    @app.post("/api/query", summary="one query: JSON {q, top_k} or multipart image upload (field 'image')",
              responses=_doc(QueryReply, 413, 503), openapi_extra=_QUERY_BODY)
    async def query_post(request: Request) -> dict:
        ctype = request.headers.get("content-type", "")
        if ctype.startswith("multipart/form-data"):
            form = await request.form()
            up = form.get("image")
            if up is None or isinstance(up, str):
                raise ApiError(400, "multipart query needs a file field 'image' (JPEG/PNG)")
            data = await up.read()
            if len(data) > max_body:
                raise ApiError(413, f"image too large (limit {max_body // (1024 * 1024)} MiB)")
            top_k = int(str(form.get("top_k") or 5))
            res = await asyncio.to_thread(client.query, None, data, top_k, timeout)
            return res.to_dict()
        try:
            body = QueryBody.model_validate(await request.json())
        except (ValueError, TypeError) as e:
            raise ApiError(400, f"POST /api/query needs JSON {{\"q\": TEXT, \"top_k\": N}} or an image upload: {e}") \
                from None
        kw = query_fields(body.q, top_k=body.top_k, example=': {"q": "water tower"}')
        res = await asyncio.to_thread(client.query, kw["text"], None, kw["top_k"], timeout, softmax=body.softmax)
        return res.to_dict()

    @app.get("/api/query/stream", summary="standing query as server-sent events (event 'update', data: the "
             "/api/query reply)", responses=_doc(QueryReply, 503), response_class=StreamingResponse)
    async def query_stream(request: Request, q: str = Query(...),
                           top_k: int = Query(5, ge=1, le=1000)) -> StreamingResponse:
        kw = query_fields(q, top_k=top_k, example=_QUERY_EXAMPLE)
        return await _sse(request, lambda push: client.watch(kw["text"], lambda r: push(r.to_dict()),
                                                             top_k=kw["top_k"], timeout=timeout), slots)


def _search_routes(app: FastAPI, client, timeout: float, slots: StreamSlots) -> None:
    @app.get("/api/search", summary="search for planners: same object as `rayfronts search --json`",
             responses=_doc(SearchReplyModel, 503))
    def search_get(q: Targets, background: Background = None,
                   threshold: float = 0.5, max_instances: int = 10, max_goals: int = 5,
                   from_: str | None = Query(None, alias="from", description="x,y,z"),
                   area: str | None = Query(None, description="x0,y0,x1,y1 or polygon"),
                   z_band: str | None = Query(None, description="z0,z1")) -> dict:
        kw = search_kwargs_from(q, background, threshold, max_instances, max_goals, from_, area, z_band)
        return search_reply_json(client.search(q, timeout=timeout, **kw))

    @app.post("/api/search", summary="search for planners (JSON body with the GET fields)",
              responses=_doc(SearchReplyModel, 422, 503))
    def search_post(body: SearchBody) -> dict:
        kw = search_kwargs_from(body.q, body.background, body.threshold, body.max_instances, body.max_goals,
                                body.from_xyz, body.area, body.z_band)
        return search_reply_json(client.search(body.q, timeout=timeout, **kw))

    @app.get("/api/search/stream", summary="standing search as server-sent events (event 'update', data: the "
             "/api/search reply)", responses=_doc(SearchReplyModel, 503), response_class=StreamingResponse)
    async def search_stream(request: Request, q: Targets, background: Background = None,
                            threshold: float = 0.5, max_instances: int = 10, max_goals: int = 5,
                            from_: str | None = Query(None, alias="from"), area: str | None = None,
                            z_band: str | None = None) -> StreamingResponse:
        kw = search_kwargs_from(q, background, threshold, max_instances, max_goals, from_, area, z_band)
        return await _sse(request, lambda push: client.watch_search(
            q, lambda r: push(search_reply_json(r)), timeout=timeout, **kw), slots)



Fleet = Annotated[str, Query(description="robot ids r1,r2,r3, or 'all' (every robot present)")]


def _fleet_routes(app: FastAPI, client, timeout: float, slots: StreamSlots) -> None:
    @app.get("/api/fleet_search", summary="fleet search: one goal per robot, shared found list; same object as "
             "`rayfronts search --fleet ... --json`", responses=_doc(FleetSearchReplyModel, 503))
    def fleet_get(q: Targets, fleet: Fleet, background: Background = None, threshold: float = 0.5,
                  max_instances: int = 10, max_goals: int = 20, target_count: int = 1, footprint_m: float = 0.0,
                  area: str | None = Query(None, description="x0,y0,x1,y1 or polygon"),
                  z_band: str | None = Query(None, description="z0,z1")) -> dict:
        kw = fleet_kwargs_from(q, fleet, background, threshold, max_instances, max_goals, target_count, footprint_m,
                               area, z_band)
        return fleet_reply_json(client.fleet_search(q, timeout=timeout, **kw))

    @app.post("/api/fleet_search", summary="fleet search (JSON body with the GET fields; fleet a list)",
              responses=_doc(FleetSearchReplyModel, 422, 503))
    def fleet_post(body: FleetSearchBody) -> dict:
        kw = fleet_kwargs_from(body.q, body.fleet, body.background, body.threshold, body.max_instances,
                               body.max_goals, body.target_count, body.footprint_m, body.area, body.z_band)
        return fleet_reply_json(client.fleet_search(body.q, timeout=timeout, **kw))

    @app.get("/api/fleet_search/stream", summary="standing fleet search as server-sent events (event 'update', "
             "data: the /api/fleet_search reply)", responses=_doc(FleetSearchReplyModel, 503),
             response_class=StreamingResponse)
    async def fleet_stream(request: Request, q: Targets, fleet: Fleet, background: Background = None,
                           threshold: float = 0.5, max_instances: int = 10, max_goals: int = 20,
                           target_count: int = 1, footprint_m: float = 0.0, area: str | None = None,
                           z_band: str | None = None) -> StreamingResponse:
        kw = fleet_kwargs_from(q, fleet, background, threshold, max_instances, max_goals, target_count, footprint_m,
                               area, z_band)
        return await _sse(request, lambda push: client.watch_fleet_search(
            q, lambda r: push(fleet_reply_json(r)), timeout=timeout, **kw), slots)


def _map_routes(app: FastAPI, client, timeout: float, slots: StreamSlots, refused: Counter) -> None:
    @app.get("/api/occupancy/box", summary="dense occupancy of a box: states 0 free, 1 occupied, -1 unknown",
             responses=_doc(OccupancyReply, 503))
    def occ_box(min: str = Query(..., description="x,y,z"), max: str = Query(..., description="x,y,z"),  # noqa: A002
                stride: int = Query(1, ge=1)) -> dict:
        return _occ_json(client.occupancy_box(_floats(min, 3, "min"), _floats(max, 3, "max"), stride, timeout))

    @app.get("/api/occupancy/slice", summary="2D costmap of a z band", responses=_doc(OccupancyReply, 503))
    def occ_slice(min: str = Query(..., description="x,y"), max: str = Query(..., description="x,y"),  # noqa: A002
                  z_band: str = Query(..., description="z0,z1"), stride: int = Query(1, ge=1)) -> dict:
        return _occ_json(client.occupancy_slice(_floats(min, 2, "min"), _floats(max, 2, "max"),
                                                _floats(z_band, 2, "z_band"), stride, timeout))

    @app.post("/api/occupancy/points", summary="state and distance to the nearest occupied voxel of points",
              responses=_doc(OccupancyReply, 422, 503))
    def occ_points(body: PointsBody) -> dict:
        if not body.points or any(len(p) != 3 for p in body.points):
            raise ApiError(400, "points must be a non-empty list of [x, y, z]")
        return _occ_json(client.occupancy_points(body.points, body.radius, timeout))

    @app.get("/api/stats", summary="per shard and per robot state (frames mapped, rate, drops, edges)",
             responses=_doc(StatsReply, 503))
    def stats() -> dict:
        out = robot_states(client.stats_all(timeout=timeout))
        out["robots_alive"] = client.robots(timeout=1.0)
        out["console"] = {"open_streams": slots.open,
                          "refused": {"token": refused["token"], "rate": refused["rate"],
                                      "body_too_large": refused["body_too_large"], "streams": slots.refused}}
        return out

    @app.get("/api/snapshot", summary="describe the last snapshot", responses=_doc(SnapshotReply, 503))
    def snapshot_get() -> dict:
        return client.snapshot(save=False, timeout=timeout)

    @app.post("/api/snapshot", summary="make a snapshot now", responses=_doc(SnapshotReply, 503))
    def snapshot_post() -> dict:
        return client.snapshot(save=True, timeout=max(timeout, 60.0))
