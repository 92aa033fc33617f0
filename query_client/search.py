"""Planner calls of ``query_client.Client`` (mixed into it): :meth:`PlannerCalls.search`,
:meth:`PlannerCalls.watch_search` and the occupancy read-outs.

World frame, metres, z up; yaw in radians counter-clockwise from +x. Occupancy states:
0 free, 1 occupied, -1 unknown. Errors from the mapper raise ``QueryError``; no mapper
answering raises ``MapperUnavailable``. No torch: this runs on a client-only install.
"""
from __future__ import annotations

import dataclasses
import logging
import uuid
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from common.messages import MessageError
from common.search_messages import (
    OccupancyReply,
    OccupancyRequest,
    SearchReply,
    SearchRequest,
    decode_occupancy_reply,
    decode_search_reply,
    encode_occupancy_request,
    encode_search_request,
)
from query_client.standing import ShardLatest, StandingHandle

if TYPE_CHECKING:
    from common.keys import KeySpace

log = logging.getLogger("rayfronts.query_client")


def _area(area) -> tuple[list | None, list | None]:
    """``(polygon, box)`` of an ``area``: a polygon [[x, y], ...] or a box [x0, y0, x1, y1]."""
    if area is None:
        return None, None
    a = list(area)
    if len(a) == 4 and all(isinstance(v, (int, float, np.floating, np.integer)) for v in a):
        return None, [float(v) for v in a]
    return [[float(p[0]), float(p[1])] for p in a], None


class SearchHandle(StandingHandle):
    """A standing search; ``cancel()`` (or leaving the ``with`` block) stops it."""

    def __init__(self, client, sid: str, sub):
        super().__init__(client, sid, sub, client._search_key(),
                         encode_search_request(SearchRequest(cancel=True, id=sid)), "standing search")


class PlannerCalls:
    """Search and occupancy calls (a mixin of ``query_client.Client``: uses its ``keys``,
    ``robot``, ``_get_all``, ``_collect``, ``_missing``, ``_missing_infos``, ``_standing`` and
    ``_lease``). Every call asks every mapper shard and merges their answers
    (``query_client.search_merge``); ``missing_shards`` names the shards seen that did not
    answer. A client made with ``robot=<id>`` (a robot's onboard planner, with the robot's
    certificate) asks on the robot's own keys ``<p>/mapper/robots/<id>/{search,occupancy}``
    (docs/key_space.md), the only ones the site ACL lets a robot ask."""

    _query_error: type[Exception] = RuntimeError     # Client sets its QueryError
    robot: str | None = None
    # what Client provides (query_client.client; declared here for the type checker)
    keys: KeySpace
    _get_all: Callable[[str, bytes | None, float | None], tuple[list, list[str]]]
    _collect: Callable[[str, list, list[str], Callable], list[tuple]]
    _missing: Callable[[set[str]], list[str]]
    _missing_infos: Callable[[set[str]], list[dict]]
    _standing: Callable[..., ShardLatest]
    _follow_mapper: Callable[..., Any]

    def _search_key(self) -> str:
        return self.keys.robot_search(self.robot) if self.robot else self.keys.mapper_search

    def _occupancy_key(self) -> str:
        return self.keys.robot_occupancy(self.robot) if self.robot else self.keys.mapper_occupancy

    def _searches_key(self, sid: str) -> str:
        """Where the mapper publishes this client's standing search ``sid``."""
        return self.keys.robot_searches(self.robot, sid) if self.robot else self.keys.mapper_searches(sid)

    def _ask_all(self, key: str, payload: bytes, timeout: float | None, decode) -> list[tuple]:
        """``[(answer, shard info)]`` of every shard answering ``key``."""
        oks, errs = self._get_all(key, payload, timeout)
        return self._collect(key, oks, errs, decode)

    def _merge_search(self, got: list[tuple], req: SearchRequest) -> SearchReply:
        from query_client.search_merge import merge_search_replies

        rep = dataclasses.replace(merge_search_replies(got, req))
        rep.missing_shards = self._missing({str(i.get("shard", "")) for _, i in got})
        return rep

    def _check_area(self, req: SearchRequest, got: list[tuple]) -> None:
        """A search area that no known shard's region meets: ``QueryError`` (one line)."""
        from common.shard_routing import ShardRegion
        from query_client.search_merge import NoShardOwns, check_owned

        poly = req.polygon()
        if poly is None:
            return
        infos = [i for _, i in got] + self._missing_infos({str(i.get("shard", "")) for _, i in got})
        regions = [ShardRegion.from_info(i) for i in infos]
        if not all(r.bounded for r in regions):
            return
        a = np.asarray(poly, np.float64)
        try:
            check_owned("search area", a.min(0).tolist(), a.max(0).tolist(), regions)
        except NoShardOwns as e:
            raise self._query_error(str(e)) from None

    @staticmethod
    def search_request(targets: str | Sequence[str], background: Sequence[str] | None = None, area=None,
                       z_band: Sequence[float] | None = None, threshold: float = 0.5, max_instances: int = 10,
                       from_xyz: Sequence[float] | None = None, *, max_goals: int = 5,
                       embeddings: np.ndarray | None = None, standing: bool = False, sid: str = "") -> SearchRequest:
        """The validated request of :meth:`search` (raises ``MessageError`` for bad input)."""
        poly, box = _area(area)
        return SearchRequest(targets=[targets] if isinstance(targets, str) else list(targets),
                             embeddings=embeddings, background=None if background is None else list(background),
                             area=poly, box=box, z_band=None if z_band is None else list(z_band),
                             threshold=threshold, max_instances=max_instances, max_goals=max_goals,
                             from_xyz=None if from_xyz is None else list(from_xyz), standing=standing,
                             id=sid).validate()

    def search(self, targets: str | Sequence[str], background: Sequence[str] | None = None, area=None,
               z_band: Sequence[float] | None = None, threshold: float = 0.5, max_instances: int = 10,
               from_xyz: Sequence[float] | None = None, *, max_goals: int = 5, embeddings: np.ndarray | None = None,
               timeout: float | None = None) -> SearchReply:
        """Search the map for ``targets`` (softmax probability over targets + ``background``,
        default the mapper's ``search.background``): found instances (stable ids; with shards
        ``"<shard>:<n>"``), look-next goals, rays and triangulated estimates beyond the map.
        ``area``: polygon [[x, y], ...] or box [x0, y0, x1, y1]; ``z_band`` [z0, z1];
        ``threshold`` in (0, 1); ``from_xyz`` the robot's position (goal distances)."""
        try:
            req = self.search_request(targets, background, area, z_band, threshold, max_instances, from_xyz,
                                      max_goals=max_goals, embeddings=embeddings)
        except MessageError as e:
            raise self._query_error(str(e)) from None
        got = self._ask_all(self._search_key(), encode_search_request(req), timeout, decode_search_reply)
        self._check_area(req, got)
        return self._merge_search(got, req)

    def watch_search(self, targets: str | Sequence[str], callback: Callable[[SearchReply], None], *,
                     timeout: float | None = None, **kw) -> SearchHandle:
        """Standing search: ``callback(SearchReply)`` now and after map changes (on a Zenoh
        thread); ``kw`` as :meth:`search`. Every shard runs it and publishes its own answers;
        the client keeps each shard's latest and passes on their merge."""
        from query_client.search_merge import merge_search_replies

        sid = "s" + uuid.uuid4().hex[:12]
        req = self.search_request(targets, standing=True, sid=sid, **kw)
        req.lease_s, req.client = self.lease_s, self.client_id
        latest = self._standing(sid, self._searches_key(sid), decode_search_reply,
                                lambda items: merge_search_replies(items, req) if items else SearchReply(id=sid),
                                f"standing search {sid}", callback)
        handle = SearchHandle(self, sid, latest.sub)
        try:
            got = self._ask_all(self._search_key(), encode_search_request(req), timeout, decode_search_reply)
            self._check_area(req, got)
            latest.first(got, handle)
        except Exception:
            handle.cancel()
            raise
        handle._alive_sub = self._follow_mapper(handle, self._search_key(), encode_search_request(req),
                                                f"standing search {sid}", timeout)
        self._lease(handle, encode_search_request(req), encode_search_request(SearchRequest(renew=True, id=sid)),
                    decode_search_reply)
        return handle

    # what the Client provides (query_client.client)
    lease_s: float
    client_id: str

    def _lease(self, handle, register: bytes, renew: bytes, decode) -> None:
        raise NotImplementedError

    def _occupancy(self, req: OccupancyRequest, timeout: float | None) -> OccupancyReply:
        from query_client.search_merge import NoShardOwns, merge_occupancy

        try:
            payload = encode_occupancy_request(req)
        except MessageError as e:
            raise self._query_error(str(e)) from None
        got = self._ask_all(self._occupancy_key(), payload, timeout, decode_occupancy_reply)
        answered = {str(i.get("shard", "")) for _, i in got}
        try:
            rep = merge_occupancy(got, req, self._missing_infos(answered))
        except (NoShardOwns, ValueError) as e:
            raise self._query_error(str(e)) from None
        rep.missing_shards = self._missing(answered)
        return rep

    def occupancy_box(self, box_min: Sequence[float], box_max: Sequence[float], stride: int = 1,
                      timeout: float | None = None) -> OccupancyReply:
        """Dense states (nx, ny, nz) of a box at ``stride`` map voxels per cell."""
        return self._occupancy(OccupancyRequest("box", list(box_min), list(box_max), stride=stride), timeout)

    def occupancy_slice(self, xy_min: Sequence[float] | np.ndarray, xy_max: Sequence[float] | np.ndarray,
                        z_band: Sequence[float] | np.ndarray, stride: int = 1,
                        timeout: float | None = None) -> OccupancyReply:
        """2D costmap (nx, ny) of the z band: occupied if any, free if all free, else unknown."""
        return self._occupancy(OccupancyRequest("slice", list(xy_min), list(xy_max), list(z_band), stride=stride),
                               timeout)

    def occupancy_points(self, points, radius: float = 1.0, timeout: float | None = None) -> OccupancyReply:
        """State of each point (N,) and ``dist`` to the nearest occupied voxel within ``radius``."""
        return self._occupancy(OccupancyRequest("points", points=np.asarray(points, np.float64).reshape(-1, 3),
                                                radius=float(radius)), timeout)
