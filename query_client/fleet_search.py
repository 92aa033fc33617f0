"""Fleet search calls of ``query_client.Client`` (mixed into it): :meth:`FleetCalls.fleet_search`
(one-shot), :meth:`FleetCalls.watch_fleet_search` (standing) and
:meth:`FleetCalls.report_unreachable` (docs/fleet.md "Fleet search").

World frame, metres, z up. Errors from the mapper raise ``QueryError``; no mapper answering
raises ``MapperUnavailable``. No torch: this runs on a client-only install.

Shards (docs/key_space.md#shards): every shard answers from its own map and the robots it
knows; :func:`merge_fleet_replies` keeps ``found`` / ``candidates`` / ``events`` as a search's
merge does (``query_client.search_merge``) and gives each robot the goal of the first shard,
in shard-name order, that assigned it one whose viewpoint is at least the footprint away from
the goals already kept (the goals stay apart across shards; a robot left without one is
``idle``).
"""
from __future__ import annotations

import dataclasses
import uuid
from typing import Any, Callable, Sequence

import numpy as np

from common.fleet_messages import (
    FleetSearchReply,
    FleetSearchRequest,
    UnreachableReport,
    decode_fleet_search_reply,
    decode_unreachable_reply,
    encode_fleet_search_request,
    encode_unreachable,
)
from common.keys import KeySpace
from common.messages import MessageError
from common.search_messages import SearchReply
from query_client.search import _area
from query_client.standing import StandingHandle


def _goals(reps: list[tuple[str, FleetSearchReply]]) -> tuple[dict, dict]:
    """``(goals, robots)`` merged over shards (module docstring)."""
    goals: dict = {}
    robots: dict = {}
    kept: list[np.ndarray] = []
    for _, r in reps:
        for robot, info in r.robots.items():
            prev = robots.get(robot)
            if prev is None or (prev.get("position") is None and info.get("position") is not None):
                robots[robot] = dict(info)
            goals.setdefault(robot, None)
    for name, r in reps:
        fp = float(r.footprint_m)
        for robot, g in r.goals.items():
            if g is None or goals.get(robot) is not None:
                continue
            p = np.asarray(g["position"], np.float64)
            if any(float(np.linalg.norm(p - q)) < fp for q in kept):
                continue
            goals[robot] = dict(g, shard=name) if name else g
            kept.append(p)
    for robot, info in robots.items():
        if info.get("state") in ("assigned", "idle"):
            info["state"] = "assigned" if goals.get(robot) is not None else "idle"
    return goals, robots


def merge_fleet_replies(replies: list[tuple[FleetSearchReply, dict]], req: FleetSearchRequest) -> FleetSearchReply:
    """One fleet reply from the ``(reply, shard info)`` of several shards (module docstring);
    a lone reply of a mapper without a shard name is returned as it is."""
    from query_client.search_merge import merge_search_replies

    if not replies:
        raise ValueError("nothing to merge")
    names = [str((i or {}).get("shard", "")) for _, i in replies]
    if len(replies) == 1 and not names[0]:
        return replies[0][0]
    order = sorted(range(len(replies)), key=lambda k: names[k])
    reps = [(names[k], replies[k][0]) for k in order]
    as_search = [(SearchReply(id=r.id, found=r.found, look_next=r.candidates, events=r.events,
                              frames_mapped=r.frames_mapped, map_version=r.map_version, timings_ms=r.timings_ms),
                  replies[k][1]) for k, (_, r) in zip(order, reps, strict=True)]
    merged = merge_search_replies(as_search, req)
    goals, robots = _goals(reps)
    return FleetSearchReply(
        id=reps[0][1].id, goals=goals, robots=robots,
        waiting=sorted(r for r, i in robots.items() if i.get("state") == "waiting"),
        gone=sorted(r for r, i in robots.items() if i.get("state") == "gone"),
        found=merged.found, candidates=merged.look_next, utility=float(sum(r.utility for _, r in reps)),
        method=reps[0][1].method, footprint_m=max(float(r.footprint_m) for _, r in reps), events=merged.events,
        frames_mapped=merged.frames_mapped, map_version=merged.map_version, timings_ms=merged.timings_ms)


class FleetSearchHandle(StandingHandle):
    """A standing fleet search; ``cancel()`` (or leaving the ``with`` block) stops it."""

    def __init__(self, client, sid: str, sub):
        super().__init__(client, sid, sub, client.keys.mapper_fleet_search,
                         encode_fleet_search_request(FleetSearchRequest(cancel=True, id=sid)), "standing fleet search")


class FleetCalls:
    """Fleet search calls (a mixin of ``query_client.Client``: uses its ``keys``, ``_get_all``,
    ``_collect``, ``_missing``, ``_standing``, ``_follow_mapper`` and ``_lease``)."""

    _query_error: type[Exception] = RuntimeError     # Client sets its QueryError

    @staticmethod
    def fleet_search_request(targets: str | Sequence[str], robots: Sequence[str] | None = None,
                             background: Sequence[str] | None = None, area=None,
                             z_band: Sequence[float] | None = None, threshold: float = 0.5, max_instances: int = 10,
                             *, max_goals: int = 20, target_count: int = 1, footprint_m: float = 0.0,
                             standing: bool = False, sid: str = "") -> FleetSearchRequest:
        """The validated request of :meth:`fleet_search` (raises ``MessageError`` for bad input)."""
        poly, box = _area(area)
        return FleetSearchRequest(targets=[targets] if isinstance(targets, str) else list(targets),
                                  robots=list(robots or []),
                                  background=None if background is None else list(background),
                                  area=poly, box=box, z_band=None if z_band is None else list(z_band),
                                  threshold=threshold, max_instances=max_instances, max_goals=max_goals,
                                  target_count=target_count, footprint_m=footprint_m, standing=standing,
                                  id=sid).validate()

    def _fleet_request(self, targets, kw: dict, **extra) -> FleetSearchRequest:
        try:
            return self.fleet_search_request(targets, **kw, **extra)
        except MessageError as e:
            raise self._query_error(str(e)) from None

    def fleet_search(self, targets: str | Sequence[str], robots: Sequence[str] | None = None, *,
                     timeout: float | None = None, **kw) -> FleetSearchReply:
        """One search for the robots ``robots`` (None / [] = every robot present on the mapper):
        each robot's goal (distinct regions, utility per metre of its own path), the shared
        found instances, ``waiting`` robots (no pose yet) and ``gone`` ones. ``kw``: background,
        area, z_band, threshold, max_instances, max_goals (candidates), target_count,
        footprint_m (0 = the mapper's ``search.fleet_footprint_m``)."""
        req = self._fleet_request(targets, kw, robots=robots)
        got = self._ask_all(self.keys.mapper_fleet_search, encode_fleet_search_request(req), timeout,
                            decode_fleet_search_reply)
        rep = dataclasses.replace(merge_fleet_replies(got, req))
        rep.missing_shards = self._missing({str(i.get("shard", "")) for _, i in got})
        return rep

    def watch_fleet_search(self, targets: str | Sequence[str], callback: Callable[[FleetSearchReply], None], *,
                           robots: Sequence[str] | None = None, timeout: float | None = None,
                           **kw) -> FleetSearchHandle:
        """Standing fleet search: ``callback(FleetSearchReply)`` now, after map changes and at
        once when a robot of it comes, goes or reports a goal unreachable (on a Zenoh thread);
        ``kw`` as :meth:`fleet_search`."""
        sid = "f" + uuid.uuid4().hex[:12]
        req = self._fleet_request(targets, kw, robots=robots, standing=True, sid=sid)
        req.lease_s, req.client = self.lease_s, self.client_id
        key = self.keys.mapper_fleet_search
        latest = self._standing(sid, self.keys.mapper_fleet_searches(sid), decode_fleet_search_reply,
                                lambda items: merge_fleet_replies(items, req) if items else FleetSearchReply(id=sid),
                                f"standing fleet search {sid}", callback)
        handle = FleetSearchHandle(self, sid, latest.sub)
        try:
            latest.first(self._ask_all(key, encode_fleet_search_request(req), timeout, decode_fleet_search_reply),
                         handle)
        except Exception:
            handle.cancel()
            raise
        handle._alive_sub = self._follow_mapper(handle, key, encode_fleet_search_request(req),
                                                f"standing fleet search {sid}", timeout)
        self._lease(handle, encode_fleet_search_request(req),
                    encode_fleet_search_request(FleetSearchRequest(renew=True, id=sid)), decode_fleet_search_reply)
        return handle

    def report_unreachable(self, robot: str, position: Sequence[float], sid: str = "",
                           timeout: float | None = None) -> dict:
        """Robot ``robot`` cannot reach ``position`` [x, y, z] (its goal): fleet searches give it
        goals elsewhere. ``sid``: the standing fleet search concerned ("" = all). Returns
        ``{robot, held, goals}`` (``goals``: fleet search id -> the robot's new goal or None)."""
        try:
            payload = encode_unreachable(UnreachableReport(position=[float(v) for v in position], id=sid))
            key = self.keys.robot_unreachable(robot)
        except (MessageError, ValueError) as e:
            raise self._query_error(str(e)) from None
        got = self._ask_all(key, payload, timeout, decode_unreachable_reply)
        goals: dict = {}
        for a, _ in got:
            goals.update(a["goals"])
        return {"robot": robot, "held": max(int(a["held"]) for a, _ in got), "goals": goals}

    def watch_fleet_goal(self, callback: Callable[[FleetSearchReply], None], robot: str | None = None):
        """A robot's own goal in every standing fleet search: ``callback(FleetSearchReply)`` (its
        ``goals`` and ``robots`` hold that robot only; ``id`` names the fleet search) on each answer,
        from ``<p>/mapper/robots/<robot>/fleet_goal``, which a ``robot-<id>`` certificate may read.
        ``robot``: default the client's own (``Client(robot=...)``). Returns the Zenoh subscriber
        (``undeclare()`` stops it)."""
        import logging

        rid = robot or self.robot
        if not rid:
            raise self._query_error("watch_fleet_goal needs a robot id (Client(robot=...) or robot=...)")
        key = self.keys.robot_fleet_goal(rid)

        def on_sample(sample) -> None:
            try:
                callback(decode_fleet_search_reply(sample.payload.to_bytes()))
            except Exception as e:  # never raise out of a Zenoh callback
                logging.getLogger("rayfronts.client").warning("fleet goal of %s: %s", rid, e)

        return self.session.declare_subscriber(key, on_sample)

    # what the Client provides (query_client.client / query_client.search)
    robot: str | None
    session: Any
    lease_s: float
    client_id: str
    keys: KeySpace

    def _ask_all(self, key: str, payload: bytes, timeout: float | None, decode) -> list[tuple]:
        raise NotImplementedError

    def _missing(self, answered: set[str]) -> list[str]:
        raise NotImplementedError

    def _standing(self, sid: str, key: str, decode, merge, what: str, callback):
        raise NotImplementedError

    def _follow_mapper(self, handle, key: str, payload: bytes, what: str, timeout: float | None):
        raise NotImplementedError

    def _lease(self, handle, register: bytes, renew: bytes, decode) -> None:
        raise NotImplementedError
