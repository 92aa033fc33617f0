"""Fleet search (docs/fleet.md "Fleet search"): one search for several robots, its look-next
goals shared out across them. Queryables ``<p>/mapper/fleet_search`` (one-shot, standing,
cancel, renew) and ``<p>/mapper/robots/<robot>/unreachable`` (a robot reports a goal it cannot
reach); standing answers are published on ``<p>/mapper/fleet_searches/<id>`` and each robot's
part on ``<p>/mapper/robots/<robot>/fleet_goal``.

Per answer: the search runs once (:meth:`mapper.search_server.SearchServer.run_search`, no
``from_xyz``: its ``max_goals`` look-next goals are the candidates, ranked by evidence and
gain), then :func:`planning.fleet_allocation.allocate_goals` gives each robot at most one of
them: viewpoints at least the footprint apart, utility the semantic gain per metre of that
robot's own straight-line path, found instances shared (``target_count``), positions the robot
reported unreachable left out. Robot positions are each robot's last mapped pose
(:class:`mapper.state.RobotState` ``pose``: world frame, after ``world_from_robot``).

The fleet: the named robots, or every robot of the mapper's table that is present. A named
robot the mapper does not know is a one-line error; a known robot without a mapped pose is
``waiting`` (it gets goals once a frame of it is mapped); a robot whose liveliness left is
``gone`` and its goal goes to the others. A standing fleet search is answered again after a
map change (at most every ``STANDING_PERIOD_S``), and at once when a robot of it comes, goes,
gets its first pose or reports a position unreachable (the candidates of the same map
generation are reused). Standing fleet searches are leased and capped like standing searches
(``search.lease_s``, ``search.max_standing``, ``search.max_standing_per_client``).
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Callable

import numpy as np

from common.fleet_messages import (
    FleetSearchReply,
    FleetSearchRequest,
    decode_fleet_search_request,
    decode_unreachable,
    encode_fleet_search_reply,
    encode_unreachable_reply,
)
from common.messages import MessageError
from common.search_messages import SearchReply, SearchRequest
from mapper.leases import Leases
from mapper.replies import reply_to
from planning.fleet_allocation import FoundInstance, RobotSlot, allocate_goals
from planning.look_next import Goal

log = logging.getLogger("rayfronts.mapper")

#: a standing fleet search is re-run at most this often (s) after map changes
STANDING_PERIOD_S = 1.0
#: how often the standing loop looks at the robots (liveliness, first poses), s
ROBOTS_PERIOD_S = 0.2


def _xyz(v) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


class Unreachable:
    """Positions each robot reported unreachable: at most ``max_per_robot`` per robot (oldest
    forgotten), each for ``ttl_s`` seconds (monotonic clock); ``generation`` bumps on a change."""

    def __init__(self, max_per_robot: int, ttl_s: float, clock: Callable[[], float] = time.monotonic):
        self.max, self.ttl_s, self.clock = int(max_per_robot), float(ttl_s), clock
        self._by_robot: dict[str, collections.deque] = {}
        self._lock = threading.Lock()
        self.generation = 0

    def add(self, robot: str, xyz: list[float]) -> int:
        """Remember ``xyz`` for ``robot``; how many it holds now."""
        with self._lock:
            q = self._by_robot.setdefault(robot, collections.deque(maxlen=self.max))
            q.append((self.clock() + self.ttl_s, _xyz(xyz)))
            self.generation += 1
            return len(q)

    def of(self, robot: str) -> tuple[tuple[float, float, float], ...]:
        with self._lock:
            now = self.clock()
            q = self._by_robot.get(robot)
            if not q:
                return ()
            while q and q[0][0] <= now:
                q.popleft()
                self.generation += 1
            return tuple(p for _, p in q)

    def counts(self) -> dict[str, int]:
        """Positions held per robot (for stats)."""
        with self._lock:
            return {r: len(q) for r, q in self._by_robot.items() if q}

    def keep_only(self, robots: set[str]) -> None:
        """Forget the robots not in ``robots`` (evicted from the robot table)."""
        with self._lock:
            for r in [r for r in self._by_robot if r not in robots]:
                del self._by_robot[r]


class FleetSearchServer:
    """Fleet searches against the shared map (``search``: the mapper's
    :class:`mapper.search_server.SearchServer`). ``followers``: callables given every
    standing answer (the ROS 2 output publishes each robot's goal)."""

    def __init__(self, state, search) -> None:
        self.state, self.search = state, search
        sc = state.cfg.search
        self.standing: dict[str, FleetSearchRequest] = {}
        self.leases = Leases("standing fleet search", "search", sc.lease_s, sc.max_standing,
                             sc.max_standing_per_client)
        self.unreachable = Unreachable(sc.fleet_unreachable_max, sc.fleet_unreachable_ttl_s)
        self.followers: list[Callable[[FleetSearchReply], None]] = []
        self.answered = 0
        self._seen: dict[str, tuple] = {}              # sid -> (map_gen, robots, unreachable gen) answered
        self._searched: dict[str, tuple[int, SearchReply, float]] = {}   # sid -> (map_gen, search, when)
        self._lock = threading.RLock()                 # one fleet answer at a time

    def stats(self) -> dict:
        """``stats["fleet_search"]``: standing fleet searches, answers given, their leases (s
        left) and the unreachable positions held per robot."""
        return {"standing": len(self.standing), "answered": self.answered, "leases_s": self.leases.describe(),
                "unreachable": self.unreachable.counts()}

    # ------------------------------------------------------------ the fleet
    def footprint(self, req: FleetSearchRequest) -> float:
        sc = self.state.cfg.search
        return float(req.footprint_m or sc.fleet_footprint_m or 2.0 * sc.sensing_radius_m)

    def fleet(self, req: FleetSearchRequest, strict: bool = True) -> tuple[list[str], dict[str, dict]]:
        """``(robot ids, robot -> {state, position})``; states "present" (with a position),
        "waiting" or "gone" here. ``strict``: a named robot the mapper does not know is a
        one-line error (else it is gone); an empty fleet is one."""
        s = self.state
        with s.robots_lock:
            table = {n: (st.present, None if st.pose is None else [float(v) for v in np.asarray(st.pose)[:3, 3]])
                     for n, st in s.robots.items()}
        if req.robots:
            unknown = [r for r in req.robots if r not in table]
            if unknown and strict:
                known = ", ".join(sorted(table)) or "none yet"
                raise MessageError(f"unknown robot{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} in the "
                                   f"fleet (robots this mapper knows: {known}): check the ids, or wait until "
                                   f"the robot's edge has announced itself")
            names = list(req.robots)
        else:
            names = sorted(n for n, (present, _) in table.items() if present)
            if not names:
                raise MessageError("the fleet is empty: no robot is present on this mapper yet (start an edge, "
                                   "or name the robots)")
        out = {}
        for n in names:
            present, pos = table.get(n, (False, None))
            out[n] = {"state": "gone" if not present else ("waiting" if pos is None else "present"),
                      "position": pos, "unreachable": len(self.unreachable.of(n))}
        return names, out

    def _answered_state(self, req: FleetSearchRequest) -> tuple:
        """What a standing answer depends on: ``(map generation, fleet signature, unreachable
        generation)``."""
        return self.state.map_gen, self._signature(req), self.unreachable.generation

    def _signature(self, req: FleetSearchRequest) -> tuple:
        try:
            names, info = self.fleet(req, strict=False)
        except MessageError:
            return ()
        return tuple((n, info[n]["state"]) for n in names)

    # ------------------------------------------------------------ answers
    def _search(self, req: FleetSearchRequest, flush: bool, reuse: bool) -> SearchReply:
        """The search part (found instances, candidates); a standing one reuses its answer of
        the same map generation when ``reuse``."""
        s = self.state
        if reuse and req.standing:
            got = self._searched.get(req.id)
            if got is not None and got[0] == s.map_gen:
                return got[1]
        gen = s.map_gen
        sreq = SearchRequest(targets=list(req.targets), embeddings=req.embeddings, background=req.background,
                             area=req.area, box=req.box, z_band=req.z_band, threshold=req.threshold,
                             max_instances=req.max_instances, max_goals=req.max_goals).validate()
        rep = self.search.run_search(sreq, flush=flush)
        if req.standing:
            self._searched[req.id] = (gen, rep, time.monotonic())
        return rep

    def answer(self, req: FleetSearchRequest, flush: bool = False, reuse: bool = False,
               strict: bool = True) -> FleetSearchReply:
        """Answer fleet search ``req`` now (module docstring); MessageError for an unknown robot,
        an empty fleet or an empty map."""
        s = self.state
        if s.map is None or s.space is None:
            raise MessageError("the map is empty (no frames mapped yet)")
        t0 = time.perf_counter()
        with self._lock:
            names, info = self.fleet(req, strict=strict)
            rep = self._search(req, flush, reuse)
            t = time.perf_counter()
            fp = self.footprint(req)
            slots = [RobotSlot(n, _xyz(info[n]["position"]), self.unreachable.of(n))
                     for n in names if info[n]["state"] == "present"]
            goals: dict[str, dict | None] = {n: None for n in names}
            utility, method = 0.0, "greedy"
            if slots:
                found = [FoundInstance(str(f["target"]), _xyz(f["centroid"])) for f in rep.found]
                a = allocate_goals(slots, [Goal.from_dict(d) for d in rep.look_next], footprint_m=fp,
                                   unreachable_tol_m=float(s.cfg.search.fleet_unreachable_tol_m), found=found,
                                   target_count=req.target_count)
                utility, method = float(a.utility), a.method
                for n, g in a.goals.items():
                    if g is not None:
                        goals[n] = dict(g.as_dict(), distance_m=float(a.paths_m.get(n, 0.0)))
            for n in names:
                if info[n]["state"] == "present":
                    info[n]["state"] = "assigned" if goals[n] is not None else "idle"
            timings = dict(rep.timings_ms, allocate=(time.perf_counter() - t) * 1e3,
                           total=(time.perf_counter() - t0) * 1e3)
            self.answered += 1
            return FleetSearchReply(
                id=req.id, goals=goals, robots=info, waiting=[n for n in names if info[n]["state"] == "waiting"],
                gone=[n for n in names if info[n]["state"] == "gone"], found=rep.found,
                candidates=[dict(d, distance_m=0.0) for d in rep.look_next], utility=utility, method=method,
                footprint_m=fp, events=rep.events, frames_mapped=rep.frames_mapped, map_version=rep.map_version,
                timings_ms=timings)

    # ------------------------------------------------------------ Zenoh
    def fleet_payload(self, data: bytes) -> bytes:
        """Answer an encoded fleet search request: an encoded reply (a cancel, a renewal, or a
        standing search registered before the map exists gets an empty one)."""
        req = decode_fleet_search_request(data)
        if req.cancel:
            self.drop(req.id)
            return encode_fleet_search_reply(FleetSearchReply(id=req.id))
        if req.renew:
            self.leases.renew(req.id, req.id in self.standing)
            return encode_fleet_search_reply(FleetSearchReply(id=req.id))
        if req.standing:
            fresh = req.id not in self.standing
            req.client = req.client or "anonymous"
            self.fleet(req)                               # unknown robots / empty fleet: refused now
            self.leases.admit(req.id, req.client, req.lease_s, len(self.standing))
            if self.state.map is None:
                self.standing[req.id] = req               # answered once the map exists
                return encode_fleet_search_reply(FleetSearchReply(id=req.id))
            try:
                rep = self.answer(req, flush=True)
            except Exception:
                if fresh:
                    self.leases.drop(req.id)
                raise
            self.standing[req.id] = req
            self._seen[req.id] = self._answered_state(req)
            self.fan_out(rep)
            return encode_fleet_search_reply(rep)
        return encode_fleet_search_reply(self.answer(req, flush=True))

    def drop(self, sid: str) -> None:
        self.standing.pop(sid, None)
        self.leases.drop(sid)
        self._seen.pop(sid, None)
        self._searched.pop(sid, None)

    def unreachable_payload(self, data: bytes, robot: str) -> bytes:
        """Robot ``robot`` reports a position it cannot reach: remembered, and every standing
        fleet search holding the robot (or the one named) is answered again at once; the reply
        names the robot's new goal in each."""
        rep = decode_unreachable(data)
        with self.state.robots_lock:
            known = robot in self.state.robots
        if not known:
            raise MessageError(f"robot {robot!r} is not known to this mapper: it reports unreachable goals once "
                               f"its edge has announced itself")
        if rep.id and rep.id not in self.standing:
            raise MessageError(f"no standing fleet search {rep.id!r} on this mapper (ended, or never registered)")
        held = self.unreachable.add(robot, rep.position)
        goals = {}
        for sid, req in list(self.standing.items()):
            if (rep.id and sid != rep.id) or (req.robots and robot not in req.robots):
                continue
            try:
                ans = self.publish(req, reuse=True)
            except MessageError as e:
                log.debug("fleet search %s: %s", sid, e)
                continue
            goals[sid] = ans.goals.get(robot)
        return encode_unreachable_reply({"robot": robot, "held": held, "goals": goals})

    def publish(self, req: FleetSearchRequest, reuse: bool = False) -> FleetSearchReply:
        """Answer standing fleet search ``req`` and publish it (its key, each robot's
        ``fleet_goal`` key, the followers)."""
        s = self.state
        sig = self._answered_state(req)
        rep = self.answer(req, reuse=reuse, strict=False)
        self._seen[req.id] = sig
        s.session.put(s.keys.mapper_fleet_searches(req.id), encode_fleet_search_reply(rep),
                      attachment=self.search.shard_info())
        self.fan_out(rep)
        return rep

    def fan_out(self, rep: FleetSearchReply) -> None:
        """Each robot's part of standing answer ``rep`` on its ``fleet_goal`` key, and ``rep``
        to the followers (the ROS 2 output)."""
        s = self.state
        att = self.search.shard_info()
        for r, g in rep.goals.items():
            one = FleetSearchReply(id=rep.id, goals={r: g}, robots={r: rep.robots[r]}, utility=rep.utility,
                                   method=rep.method, footprint_m=rep.footprint_m, frames_mapped=rep.frames_mapped,
                                   map_version=rep.map_version,
                                   waiting=[r] if r in rep.waiting else [], gone=[r] if r in rep.gone else [])
            s.session.put(s.keys.robot_fleet_goal(r), encode_fleet_search_reply(one), attachment=att)
        for f in list(self.followers):
            try:
                f(rep)
            except Exception as e:  # a follower never stops the others
                s.warn("fleet-follower", "fleet search follower failed: %s", e)

    def due(self, sid: str, req: FleetSearchRequest) -> tuple[bool, bool]:
        """``(due, reuse)``: whether standing ``sid`` is answered now, and whether its search of
        this map generation may be reused (only the robots or unreachable positions changed)."""
        seen = self._seen.get(sid)
        sig = self._answered_state(req)
        if seen == sig:
            return False, False
        if seen is not None and seen[1:] != sig[1:]:
            return True, True                 # robots / unreachable changed: at once
        got = self._searched.get(sid)
        return got is None or time.monotonic() - got[2] >= STANDING_PERIOD_S, False

    def standing_loop(self) -> None:
        """Answers standing fleet searches when due (:meth:`due`) and ends those whose lease ran out."""
        s = self.state
        while not s.stop.wait(ROBOTS_PERIOD_S):
            for sid in self.leases.expired():
                if self.standing.get(sid) is not None:
                    log.info("standing fleet search %s ended: its lease ran out (the client is gone)", sid)
                self.drop(sid)
            with s.robots_lock:
                self.unreachable.keep_only(set(s.robots))
            for sid, req in list(self.standing.items()):
                if s.map is None:
                    break
                go, reuse = self.due(sid, req)
                if not go:
                    continue
                try:
                    self.publish(req, reuse=reuse)
                except Exception as e:
                    s.warn(f"fleet:{sid}", "standing fleet search %s failed: %s", sid, e)
                    self._seen[sid] = self._answered_state(req)

    def on_fleet_search(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/fleet_search``."""
        reply_to(query, "fleet search", self.fleet_payload, self.search.shard_info)

    def on_unreachable(self, query) -> None:
        """Zenoh callback of ``<p>/mapper/robots/*/unreachable``."""
        reply_to(query, "unreachable report", lambda data: self.unreachable_payload(data, self.search.asker(query)),
                 self.search.shard_info)


def start_fleet_search(state, search, session, keys) -> tuple[FleetSearchServer, list, threading.Thread]:
    """Declare the fleet-search queryables and start its standing thread: ``(server, zenoh
    entities, thread)``."""
    srv = FleetSearchServer(state, search)
    state.fleet_search = srv
    ents = [session.declare_queryable(keys.mapper_fleet_search, srv.on_fleet_search),
            session.declare_queryable(keys.robot_unreachable_all, srv.on_unreachable)]
    t = threading.Thread(target=srv.standing_loop, name="mapper-fleet-search", daemon=True)
    t.start()
    return srv, ents, t
