"""A search, Nav2 goals and a costmap per robot on ROS 2 (part of the ROS 2 output,
``ros.enabled``; docs/ros2.md). Answers come from the mapper's search service
(:class:`mapper.search_server.SearchServer`), ranked from the robot's own position.

A robot is an entry ``ros.robots.<id>.*`` (:class:`RosRobotSection`), or any robot of the
mapper's robot table asking on ``/<id>/rayfronts/search``. Its position is the world position
of its last mapped frame (:class:`mapper.state.RobotState` ``pose``, ``pose_stamp``: the
robot's own clock, used as every header stamp of its messages). Topics, under its namespace
``<ns>`` (default ``/<id>``), frame ``frame_id`` (default ``map``; the map's world: z up, m):

* ``<ns>/rayfronts/search`` (subscribed) — std_msgs/String: a YAML / JSON object
  (:func:`parse_search_text`: targets, background, area, box, z_band, threshold, max_goals,
  max_instances; ``{cancel: true}`` stops) or plain comma-separated targets;
* ``goal_topic`` (default ``<ns>/goal_pose``) — geometry_msgs/PoseStamped, what Nav2's
  ``bt_navigator`` takes: the approach pose of the best found object once its confidence
  reaches ``approach_confidence``, else the best look-next goal; sent only when it moved
  more than ``goal_min_move_m`` or turned more than ``goal_min_turn_deg`` (:class:`GoalGate`);
* ``<ns>/rayfronts/search/{goals, goal_scores, found, found_poses}`` — the full answer
  (:func:`mapper.outputs.ros_search.search_reply_messages`);
* feedback and result in the spirit of AirStack's SemanticSearchTask:
  ``<ns>/rayfronts/search/best_confidence`` (std_msgs/Float32, best so far),
  ``.../objects_found`` (std_msgs/UInt32, distinct instances so far), ``.../result_poses``
  (PoseArray: each instance found so far at its last centroid, best first) and ``.../status``
  (std_msgs/String, JSON of the same plus the targets and the goal's kind);
* ``<ns>/rayfronts/search/path`` (with ``path``) — nav_msgs/Path from the robot to the goal
  over the costmap (:func:`grid_path`: free cells, unknown ones at ``path_unknown_cost``;
  no poses when there is no way);
* fleet search (docs/fleet.md "Fleet search"): every answer of a standing fleet search sends
  each assigned robot its goal on its ``goal_topic`` (a robot not configured here: ``/<id>/goal_pose``,
  frame ``map``), through its own :class:`GoalGate` (:meth:`RosRobots.fleet_goals`);
* ``costmap_topic`` (default ``<ns>/rayfronts/costmap``) — nav_msgs/OccupancyGrid, reliable +
  transient-local depth 1 (Nav2's static layer): a ``costmap_window_m`` square around the robot
  whose origin moves (by whole cells) only when the robot leaves the window's middle half, or
  the fixed ``costmap_box``; -1 unknown, 0 free, 100 occupied; the z band from the platform.
"""
from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from common.config import ConfigError, field_, merge
from common.search_messages import OccupancyReply, SearchReply, SearchRequest

log = logging.getLogger("rayfronts.mapper")

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
FLOAT32 = "std_msgs/msg/Float32"
UINT32 = "std_msgs/msg/UInt32"
STRING = "std_msgs/msg/String"
PATH = "nav_msgs/msg/Path"
#: search-string keys (:func:`parse_search_text`)
SEARCH_KEYS = ("targets", "background", "area", "box", "z_band", "threshold", "max_goals", "max_instances", "cancel")
#: instances remembered per search for the feedback (the lowest confidence is dropped past it)
MAX_REMEMBERED = 1000
#: platform defaults: the search z band (world z, m; None = every height) and the costmap z
#: band (ground: world z; aerial: relative to the robot's z)
PLATFORMS: dict[str, dict[str, Any]] = {
    "ground": {"search_z": [-0.5, 3.0], "costmap_z": [0.5, 1.5], "relative": False},
    "aerial": {"search_z": None, "costmap_z": [-1.0, 1.0], "relative": True}}


@dataclass
class RosRobotSection:
    """One robot's ROS search, goals and costmap (``ros.robots.<id>.*``; metres, degrees)."""

    robot: str = field_("", "mapper robot id whose frames give the position ('' = the entry's id)")
    namespace: str = field_("", "ROS namespace of the robot's topics ('' = /<id>)")
    platform: Literal["ground", "aerial"] = field_(
        "ground", "ground: search z band [-0.5, 3] m and costmap band [0.5, 1.5] m (world z, ground at 0: the "
                  "band's voxels start above the ground's); aerial: whole height, costmap band robot z +- 1 m")
    targets: list[str] = field_([], "phrases searched from the start ([] = none until <ns>/rayfronts/search asks)")
    background: list[str] = field_([], "background phrases ([] = the mapper's search.background)")
    area: list[list[float]] = field_([], "search polygon [[x, y], ...] (>= 3 vertices; [] = everywhere)")
    box: list[float] = field_([], "search box [x0, y0, x1, y1] instead of a polygon ([] = none)")
    z_band: list[float] = field_([], "search z band [z0, z1] ([] = the platform's)")
    threshold: float = field_(0.5, "probability a voxel needs to count as a target")
    max_goals: int = field_(5, "look-next goals in the ranked list")
    max_instances: int = field_(10, "found instances published")
    search_period_s: float = field_(1.0, "the search is re-run after map changes at most this often (s); a new "
                                         "search is answered at once")
    frame_id: str = field_("map", "header.frame_id of the robot's goals, poses and costmap")
    goal_topic: str = field_("", "PoseStamped goal topic ('' = <ns>/goal_pose; Nav2's bt_navigator)")
    goal_min_move_m: float = field_(0.5, "a new goal is sent only when it moved more than this ...")
    goal_min_turn_deg: float = field_(20.0, "... or its heading turned more than this")
    approach: bool = field_(True, "a confident found object becomes the goal (its approach pose); false = only "
                                  "look-next goals")
    approach_confidence: float = field_(0.9, "confidence a found object needs to become the goal")
    approach_standoff_m: float = field_(1.0, "the approach pose stands this far outside the object's box")
    costmap: Literal["window", "site", "off"] = field_(
        "window", "window: a square around the robot; site: the fixed costmap_box; off: none")
    costmap_topic: str = field_("", "OccupancyGrid topic ('' = <ns>/rayfronts/costmap)")
    costmap_window_m: float = field_(20.0, "side of the costmap window (m)")
    costmap_box: list[float] = field_([], "site extent [x0, y0, x1, y1] (m) of costmap=site")
    costmap_resolution_m: float = field_(0.0, "costmap cell size (m), a multiple of the voxel size (0 = the voxel)")
    costmap_z_band: list[float] = field_([], "costmap z band [z0, z1] ([] = the platform's)")
    unknown_near_obstacle: Literal["unknown", "occupied"] = field_(
        "unknown", "unknown cells within unknown_near_obstacle_m of an occupied cell: kept unknown or made occupied")
    unknown_near_obstacle_m: float = field_(0.0, "radius of unknown_near_obstacle (m)")
    path: bool = field_(False, "also publish <ns>/rayfronts/search/path (nav_msgs/Path): the cheapest way from the "
                               "robot to the goal over the costmap (8-connected; no poses when there is none)")
    path_unknown_cost: float = field_(3.0, "a step into an unknown cell costs this many times one into a free cell "
                                           "(0 = unknown cells are not crossed); occupied cells never are")


def _pair(v: list[float], key: str) -> None:
    if v and (len(v) != 2 or not all(math.isfinite(x) for x in v) or v[1] < v[0]):
        raise ConfigError(f"{key}={v}: give [z0, z1] with z0 <= z1 (or [] for the platform's)")


def _box(v: list[float], key: str) -> None:
    if v and (len(v) != 4 or not all(math.isfinite(x) for x in v) or v[2] <= v[0] or v[3] <= v[1]):
        raise ConfigError(f"{key}={v}: give [x0, y0, x1, y1] with x0 < x1 and y0 < y1 (or [])")


def robot_section(rid: str, raw: Any) -> RosRobotSection:
    """``ros.robots.<rid>`` as a checked :class:`RosRobotSection` (ConfigError: one line naming the key)."""
    from common.ros2.keys import RosKeyError, normalize_topic

    p = f"ros.robots.{rid}"
    if not isinstance(raw, dict):
        raise ConfigError(f"{p} must be a mapping of its keys (e.g. {p}.targets=[chair]), got {raw!r}")
    c = merge(RosRobotSection(), raw, p + ".")
    c = replace(c, robot=c.robot or rid)
    try:
        c = replace(c, namespace=normalize_topic(c.namespace or rid))
        c = replace(c, goal_topic=normalize_topic(c.goal_topic or f"{c.namespace}/goal_pose"),
                    costmap_topic=normalize_topic(c.costmap_topic or f"{c.namespace}/rayfronts/costmap"))
    except RosKeyError as e:
        raise ConfigError(f"{p}: {e}") from None
    _pair(c.z_band, f"{p}.z_band")
    _pair(c.costmap_z_band, f"{p}.costmap_z_band")
    _box(c.box, f"{p}.box")
    _box(c.costmap_box, f"{p}.costmap_box")
    if c.costmap == "site" and not c.costmap_box:
        raise ConfigError(f"{p}.costmap=site needs {p}.costmap_box=[x0, y0, x1, y1]")
    for k in ("goal_min_move_m", "goal_min_turn_deg", "approach_standoff_m", "costmap_resolution_m",
              "unknown_near_obstacle_m", "search_period_s", "path_unknown_cost"):
        if not getattr(c, k) >= 0:
            raise ConfigError(f"{p}.{k}={getattr(c, k)}: must be >= 0")
    if not c.costmap_window_m > 0:
        raise ConfigError(f"{p}.costmap_window_m={c.costmap_window_m}: must be > 0")
    try:
        search_request(c, None)
    except ValueError as e:
        raise ConfigError(f"{p}: {e}") from None
    return c


def robot_sections(robots: dict) -> dict[str, RosRobotSection]:
    """Every ``ros.robots.<id>`` checked; two entries may not share a namespace."""
    out = {str(rid): robot_section(str(rid), raw) for rid, raw in (robots or {}).items()}
    seen: dict[str, str] = {}
    for rid, c in out.items():
        if c.namespace in seen:
            raise ConfigError(f"ros.robots.{rid}.namespace={c.namespace} is also robot {seen[c.namespace]}'s")
        seen[c.namespace] = rid
    return out


def search_request(c: RosRobotSection, xyz: np.ndarray | None) -> SearchRequest:
    """The search of robot section ``c`` from position ``xyz`` (None: unknown yet); the z band
    is ``c.z_band`` or the platform's. A section without targets gets a placeholder (checks only)."""
    zb = c.z_band or PLATFORMS[c.platform]["search_z"]
    return SearchRequest(targets=list(c.targets) or ["-"], background=list(c.background) or None,
                         area=[list(v) for v in c.area] or None, box=list(c.box) or None,
                         z_band=list(zb) if zb else None, threshold=float(c.threshold),
                         max_goals=int(c.max_goals), max_instances=int(c.max_instances),
                         from_xyz=None if xyz is None else [float(v) for v in xyz]).validate()


def parse_search_text(text: str, base: RosRobotSection) -> RosRobotSection | None:
    """The std_msgs/String of ``<ns>/rayfronts/search`` → ``base`` with the asked search (None
    for ``{cancel: true}``). A YAML / JSON object of :data:`SEARCH_KEYS`, or plain
    comma-separated targets. ValueError (one line) on anything else."""
    import yaml

    from mapper.outputs.ros_search import parse_targets

    try:
        doc = yaml.safe_load(str(text))
    except yaml.YAMLError as e:
        raise ValueError(f"not YAML / JSON ({' '.join(str(e).split())[:160]})") from None
    if isinstance(doc, str):
        doc = {"targets": doc}
    if not isinstance(doc, dict):
        raise ValueError(f"expected an object with {', '.join(SEARCH_KEYS)} (or comma-separated targets), "
                         f"got {type(doc).__name__}")
    bad = sorted(str(k) for k in doc if k not in SEARCH_KEYS)
    if bad:
        raise ValueError(f"unknown key(s) {', '.join(bad)}; allowed: {', '.join(SEARCH_KEYS)}")
    if doc.get("cancel") is True:
        return None
    t = doc.get("targets")
    targets = parse_targets(t) if isinstance(t, str) else t
    if not isinstance(targets, list) or not targets:
        raise ValueError("targets: give a list of phrases or comma-separated phrases")
    ch: dict[str, Any] = {"targets": targets}
    for k in ("background", "area", "box", "z_band"):
        if doc.get(k) is not None:
            ch[k] = doc[k]
    for k in ("threshold", "max_goals", "max_instances"):
        if k in doc:
            ch[k] = doc[k]
    if "area" in ch or "box" in ch:            # the asked region replaces the configured one
        ch.setdefault("area", [])
        ch.setdefault("box", [])
    try:
        c = merge(base, ch)
    except ConfigError as e:
        raise ValueError(str(e).replace("config key ", "", 1)) from None
    search_request(c, None)        # MessageError (a ValueError) names the bad field
    return c


# ------------------------------------------------------------------ goals
def yaw_of(pose: np.ndarray) -> float:
    """Heading (rad, about world z) of a camera-to-world pose's forward (RDF z) axis."""
    f = np.asarray(pose, np.float64)[:3, 2]
    return float(math.atan2(f[1], f[0]))


def approach_pose(found: dict, robot_xyz: np.ndarray, standoff_m: float, platform: str) -> tuple[np.ndarray, float]:
    """``(position, yaw)`` of the approach to a found instance: on the line from its centroid
    toward the robot, ``standoff_m`` outside its box (xy), facing the centroid; at the robot's
    height for a ground robot, the centroid's for an aerial one."""
    c = np.asarray(found["centroid"], np.float64)
    lo, hi = np.asarray(found["box_min"], np.float64), np.asarray(found["box_max"], np.float64)
    d = np.asarray(robot_xyz, np.float64)[:2] - c[:2]
    n = float(np.linalg.norm(d))
    u = d / n if n > 1e-9 else np.array([1.0, 0.0])
    reach = float(np.linalg.norm((hi - lo)[:2])) / 2 + standoff_m
    xy = c[:2] + u * reach
    z = float(robot_xyz[2]) if platform == "ground" else float(c[2])
    return np.array([xy[0], xy[1], z]), float(math.atan2(-u[1], -u[0]))


class GoalGate:
    """Sends a goal only when it differs from the last one sent by more than ``move_m``
    (position) or ``turn_deg`` (heading) or changes kind (look / approach): no chatter."""

    def __init__(self, move_m: float, turn_deg: float) -> None:
        self.move_m, self.turn = float(move_m), math.radians(float(turn_deg))
        self.last: tuple[np.ndarray, float, str] | None = None

    def due(self, xyz: np.ndarray, yaw: float, kind: str) -> bool:
        """True (and remembered as sent) when the goal should be sent."""
        xyz = np.asarray(xyz, np.float64)
        if self.last is not None:
            p, y, k = self.last
            turn = abs((yaw - y + math.pi) % (2 * math.pi) - math.pi)
            if k == kind and float(np.linalg.norm(xyz - p)) <= self.move_m and turn <= self.turn:
                return False
        self.last = (xyz, float(yaw), kind)
        return True


def choose_goal(rep: SearchReply, c: RosRobotSection, robot_xyz: np.ndarray) -> tuple[np.ndarray, float, str] | None:
    """``(position, yaw, kind)`` of the goal to send: the approach to the best found instance
    at ``approach_confidence`` or above (kind ``approach``; unless ``approach`` is off), else the best look-next goal
    (``look``); None when there is neither."""
    best = [f for f in rep.found if c.approach and float(f.get("confidence", 0.0)) >= c.approach_confidence]
    if best:
        xyz, yaw = approach_pose(best[0], robot_xyz, c.approach_standoff_m, c.platform)
        return xyz, yaw, "approach"
    if rep.look_next:
        g = rep.look_next[0]
        return np.asarray(g["position"], np.float64), float(g.get("heading_rad", 0.0)), "look"
    return None


# ------------------------------------------------------------------ costmap
def window_origin(prev: np.ndarray | None, robot_xy: np.ndarray, n: int, cell: float) -> np.ndarray:
    """Min corner (m, a multiple of ``cell``) of an ``n``-cell square window: ``prev`` while the
    robot stays in its middle half, else re-centred on the robot."""
    xy = np.asarray(robot_xy, np.float64)[:2]
    side = n * cell
    if prev is not None and np.all(xy >= prev + side / 4) and np.all(xy <= prev + 3 * side / 4):
        return prev
    return np.floor((xy - side / 2) / cell) * cell


def unknown_near_obstacles(states: np.ndarray, radius_cells: float) -> np.ndarray:
    """(nx, ny) bool: unknown cells (-1) within ``radius_cells`` (centre to centre) of an
    occupied cell (1)."""
    from scipy.ndimage import binary_dilation

    st = np.asarray(states)
    r = int(math.floor(radius_cells))
    if r < 1 or not (st == 1).any():
        return np.zeros(st.shape, bool)
    g = np.arange(-r, r + 1)
    disc = (g[:, None] ** 2 + g[None, :] ** 2) <= radius_cells ** 2
    return binary_dilation(st == 1, structure=disc) & (st == -1)


def grid_path(cost: np.ndarray, start: tuple[int, ...], goal: tuple[int, ...]) -> list[tuple[int, ...]] | None:
    """Cheapest 8-connected path of cells from ``start`` to ``goal`` (both included): a step
    costs its length (1, diagonals √2) times ``cost`` (nx, ny) of the cell it enters (inf:
    not entered; the goal may be entered whatever its cost: 1). None when there is none (or
    an end lies outside the grid)."""
    import heapq

    c = np.asarray(cost, np.float64).copy()
    nx, ny = c.shape
    if not (0 <= start[0] < nx and 0 <= start[1] < ny and 0 <= goal[0] < nx and 0 <= goal[1] < ny):
        return None
    c[goal] = 1.0
    dist = np.full(c.shape, np.inf)
    prev = np.full(c.shape + (2,), -1, np.int64)
    dist[start] = 0.0
    heap = [(0.0, start)]
    steps = [(di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    while heap:
        d, (i, j) = heapq.heappop(heap)
        if (i, j) == goal:
            break
        if d > dist[i, j]:
            continue
        for di, dj, w in steps:
            a, b = i + di, j + dj
            if 0 <= a < nx and 0 <= b < ny and d + w * c[a, b] < dist[a, b]:
                dist[a, b] = d + w * c[a, b]
                prev[a, b] = (i, j)
                heapq.heappush(heap, (dist[a, b], (a, b)))
    if not np.isfinite(dist[goal]):
        return None
    out = [goal]
    while out[-1] != start:
        out.append(tuple(int(v) for v in prev[out[-1]]))
    return out[::-1]


def step_costs(states: np.ndarray, unknown_cost: float) -> np.ndarray:
    """Per-cell step cost of a costmap's states: free 1, unknown ``unknown_cost`` (0 → inf),
    occupied inf."""
    st = np.asarray(states)
    return np.where(st == 0, 1.0, np.where(st == 1, np.inf, unknown_cost if unknown_cost > 0 else np.inf))


# ------------------------------------------------------------------ the robots
class RobotSearch:
    """One robot: its section, current search, goal gate, costmap origin and feedback."""

    def __init__(self, rid: str, cfg: RosRobotSection) -> None:
        self.id, self.cfg = rid, cfg
        self.search: RosRobotSection | None = cfg if cfg.targets else None
        self.gate = GoalGate(cfg.goal_min_move_m, cfg.goal_min_turn_deg)
        self.origin: np.ndarray | None = None
        self.best_confidence = 0.0
        self.seen: dict[int, tuple[float, list[float]]] = {}   # instance id -> (confidence, centroid)
        self.goals_sent = 0
        self.last_reply: SearchReply | None = None
        self.searched_at = -math.inf          # monotonic time of the last search
        self.grid: tuple[np.ndarray, float, np.ndarray] | None = None   # last costmap: origin, cell, states

    def restart(self, search: RosRobotSection | None) -> None:
        """A new search (None: stop): feedback and the goal gate start over."""
        self.search = search
        self.gate = GoalGate(self.cfg.goal_min_move_m, self.cfg.goal_min_turn_deg)
        self.best_confidence, self.seen, self.last_reply = 0.0, {}, None
        self.searched_at = -math.inf

    def remember(self, rep: SearchReply) -> None:
        for f in rep.found:
            conf = float(f.get("confidence", 0.0))
            self.best_confidence = max(self.best_confidence, conf)
            self.seen[int(f["id"])] = (conf, [float(v) for v in f["centroid"]])
        if len(self.seen) > MAX_REMEMBERED:
            keep = sorted(self.seen.items(), key=lambda kv: -kv[1][0])[:MAX_REMEMBERED]
            self.seen = dict(keep)

    def result(self) -> tuple[np.ndarray, list[int]]:
        """Centroids (N, 3) and ids of the instances found so far, best first."""
        items = sorted(self.seen.items(), key=lambda kv: (-kv[1][0], kv[0]))
        return np.array([v[1] for _, v in items], np.float64).reshape(-1, 3), [k for k, _ in items]


class RosRobots:
    """The per-robot topics of a :class:`mapper.outputs.ros.RosOutput` (``out``), answered by
    the mapper's search service ``search`` (``run_search``, ``occupancy``)."""

    def __init__(self, out, search) -> None:
        self.out, self.search = out, search
        self.robots = {rid: RobotSearch(rid, c) for rid, c in robot_sections(out.cfg.robots).items()}
        self.rejected: Counter = Counter()     # bad input by reason (unknown_namespace, bad_search)
        self.last_error = ""
        self._lock = threading.RLock()         # one robot update at a time
        self._pending: set[str] = set()        # robots with an answer thread not yet started on it
        self._pending_lock = threading.Lock()
        self.fleet_sent: Counter = Counter()   # fleet-search goals sent, by robot
        self._fleet_gates: dict[tuple[str, str], tuple[RosRobotSection, GoalGate]] = {}   # (search id, robot)
        self._fleet_lock = threading.Lock()    # fleet answers come from the fleet thread and Zenoh callbacks

    # -------------------------------------------------------------- wiring
    def start(self) -> list:
        """Declare the subscription of every ``<ns>/rayfronts/search`` (one wildcard) and the
        configured robots' publishers; returns the Zenoh entities."""
        from common.ros2.keys import BRIDGE, RMW_ZENOH
        from mapper.outputs.ros_search import OCCUPANCY_GRID

        o = self.out
        key = "**/rayfronts/search" if o.cfg.keys == BRIDGE else f"{o.domain}/**/rayfronts/search/*/*"
        ents = [o.session.declare_subscriber(key, self._on_search)]
        for r in self.robots.values():
            if o.cfg.keys == RMW_ZENOH:
                o._token("MS", f"{r.cfg.namespace}/rayfronts/search", STRING)
            o._publisher(r.cfg.goal_topic, POSE_STAMPED)
            if r.cfg.costmap != "off":
                o._publisher(r.cfg.costmap_topic, OCCUPANCY_GRID, latched=True)
        fleet = getattr(self.search, "fleet", None)
        if fleet is not None:                  # standing fleet searches send each robot its goal
            fleet.followers.append(self.fleet_goals)
        return ents

    def fleet_goals(self, rep) -> None:
        """A standing fleet search's answer (``common.fleet_messages.FleetSearchReply``): each
        robot given a goal gets it as a PoseStamped on its goal topic (its ``ros.robots`` entry's,
        else ``/<id>/goal_pose`` in ``map``), when the :class:`GoalGate` of (search, robot) lets it
        through (a new fleet search sends its goals anew); the header stamp is the robot's last
        mapped frame's."""
        with self._fleet_lock:
            live = set(getattr(self.search.fleet, "standing", {})) | {rep.id}
            for k in [k for k in self._fleet_gates if k[0] not in live]:
                del self._fleet_gates[k]           # searches that ended
            for rid, g in rep.goals.items():
                if g is not None:
                    self._fleet_goal(rep.id, rid, g)

    def _fleet_goal(self, sid: str, rid: str, g: dict) -> None:
        """Robot ``rid``'s goal ``g`` of fleet search ``sid`` on its goal topic, if its gate lets it through."""
        from mapper.outputs.ros_markers import header_msg
        from mapper.outputs.ros_search import pose_msg

        got = self._fleet_gates.get((sid, rid))
        if got is None:
            conf = self.robots[rid].cfg if rid in self.robots else robot_section(rid, {})
            got = self._fleet_gates[(sid, rid)] = (conf, GoalGate(conf.goal_min_move_m, conf.goal_min_turn_deg))
        conf, gate = got
        xyz, yaw = np.asarray(g["position"], np.float64), float(g["heading_rad"])
        if not gate.due(xyz, yaw, "fleet"):
            return
        T = self.out.T
        _, stamp = self.position(RobotSearch(rid, conf))
        self.out._put(conf.goal_topic, POSE_STAMPED, T[POSE_STAMPED](header=header_msg(T, conf.frame_id, stamp),
                                                                     pose=pose_msg(T, xyz, yaw)))
        self.fleet_sent[rid] += 1

    def robot_of(self, namespace: str) -> RobotSearch:
        """The robot whose namespace is ``namespace``: a configured one, or a robot of the
        mapper's robot table of that name (added with default settings). ValueError otherwise."""
        for r in self.robots.values():
            if r.cfg.namespace == namespace:
                return r
        rid = namespace.strip("/")
        st = self.out.state
        with st.robots_lock:
            known = rid in st.robots
        if known and "/" not in rid and rid not in self.robots:
            self.robots[rid] = RobotSearch(rid, robot_section(rid, {}))
            return self.robots[rid]
        names = ", ".join(sorted(r.cfg.namespace for r in self.robots.values())) or "none"
        raise ValueError(f"unknown robot namespace {namespace!r} (configured: {names}); set "
                         f"ros.robots.<id>.namespace={namespace} or map a robot named {rid or '<id>'} first")

    def _reject(self, reason: str, topic: str, why: str) -> None:
        """Count a bad input and log its one line (rate-limited per reason); kept as ``last_error``."""
        self.rejected[reason] += 1
        self.out.errors += 1
        self.last_error = f"ROS 2 search on {topic} rejected: {why}"
        self.out.state.warn(f"ros-robots:{reason}", "%s", self.last_error)

    def _on_search(self, sample) -> None:
        """std_msgs/String on ``<ns>/rayfronts/search`` → that robot's search (answered in a thread)."""
        from common.ros2.keys import parse_key

        o = self.out
        topic = "?"
        try:
            topic = parse_key(str(sample.key_expr), o.cfg.keys, o.domain)[0]
            ns = topic[:-len("/rayfronts/search")] or "/"
            msg = o.cdr.deserialize(sample.payload.to_bytes(), STRING)
            r = self.robot_of(ns)
            search = parse_search_text(str(msg.data), r.cfg)
        except Exception as e:
            self._reject("unknown_namespace" if "unknown robot namespace" in str(e) else "bad_search", topic,
                         " ".join(str(e).split()))
            return
        r.restart(search)
        log.info("ROS 2 search of robot %s: %s", r.id, search.targets if search else "cancelled")
        with self._pending_lock:              # one waiting answer per robot: a flood of requests
            if r.id in self._pending:         # is answered once, with the latest search
                return
            self._pending.add(r.id)
        threading.Thread(target=self._answer, args=(r.id,), name="mapper-ros-robot", daemon=True).start()

    def _answer(self, rid: str) -> None:
        with self._lock:                      # once no update runs: later requests start a new answer
            with self._pending_lock:
                self._pending.discard(rid)
            self.update(rid)

    # -------------------------------------------------------------- updates
    def position(self, r: RobotSearch) -> tuple[np.ndarray | None, float]:
        """``(world pose (4, 4) of the robot's last mapped frame or None, its stamp s)``."""
        st = self.out.state
        with st.robots_lock:
            rs = st.robots.get(r.cfg.robot)
            if rs is None or rs.pose is None:
                return None, 0.0
            return np.array(rs.pose, np.float64), float(rs.pose_stamp)

    def update_all(self) -> None:
        """Every robot's search, goal and costmap (the output's thread, after map changes)."""
        for rid in list(self.robots):
            self.update(rid, force=False)

    def update(self, rid: str, force: bool = True) -> None:
        """One robot: run its search from its position and publish (unless ``force`` is off and
        the last search is younger than ``search_period_s``); publish its costmap."""
        from common.messages import MessageError

        r = self.robots.get(rid)
        if r is None:
            return
        with self._lock:
            pose, stamp = self.position(r)
            xyz = None if pose is None else pose[:3, 3]
            try:
                if r.cfg.costmap != "off":
                    cm = self.costmap_message(r, pose, stamp)
                    if cm is not None:
                        self.out._put(r.cfg.costmap_topic, *cm, latched=True)
                now = time.monotonic()
                if r.search is not None and (force or now - r.searched_at >= r.cfg.search_period_s):
                    r.searched_at = now
                    rep = self.search.run_search(search_request(r.search, xyz))
                    self.publish_search(r, rep, xyz, stamp)
            except MessageError as e:           # an empty map: answered once it has frames
                log.debug("ROS 2 robot %s: %s", rid, e)
            except Exception as e:
                self.out.errors += 1
                self.out.state.warn(f"ros-robot:{rid}", "ROS 2 output of robot %s failed: %s", rid, e)

    def messages(self, r: RobotSearch, rep: SearchReply, xyz: np.ndarray | None, stamp: float) -> dict:
        """{topic: (type, message)} of robot ``r``'s answer ``rep``: the ranked list, feedback,
        and the PoseStamped goal when :class:`GoalGate` lets it through."""
        from mapper.outputs.ros_markers import header_msg
        from mapper.outputs.ros_search import pose_array, pose_msg, search_reply_messages

        o, c = self.out, r.cfg
        T, fid = o.T, c.frame_id
        base = f"{c.namespace}/rayfronts/search"
        out = search_reply_messages(T, fid, stamp, rep, base)
        r.remember(rep)
        res_xyz, ids = r.result()
        out[f"{base}/best_confidence"] = (FLOAT32, T[FLOAT32](data=float(r.best_confidence)))
        out[f"{base}/objects_found"] = (UINT32, T[UINT32](data=len(r.seen)))
        out[f"{base}/result_poses"] = (POSE_ARRAY, pose_array(T, fid, stamp, res_xyz))
        goal = choose_goal(rep, c, xyz if xyz is not None else np.zeros(3))
        status = {"robot": r.id, "robot_xyz": None if xyz is None else [float(v) for v in xyz], "stamp": stamp,
                  "targets": list(r.search.targets) if r.search else [],
                  "best_confidence": r.best_confidence, "objects_found": len(r.seen), "found_ids": ids[:50],
                  "goal": None if goal is None else {"kind": goal[2], "position": [float(v) for v in goal[0]],
                                                     "yaw_rad": goal[1]},
                  "map_version": int(rep.map_version), "frames_mapped": int(rep.frames_mapped)}
        out[f"{base}/status"] = (STRING, T[STRING](data=json.dumps(status)))
        if c.path:
            out[f"{base}/path"] = (PATH, self.path_message(r, xyz, goal, stamp))
        if goal is not None and r.gate.due(*goal):
            r.goals_sent += 1
            out[c.goal_topic] = (POSE_STAMPED, T[POSE_STAMPED](header=header_msg(T, fid, stamp),
                                                               pose=pose_msg(T, goal[0], goal[1])))
        return out

    def path_message(self, r: RobotSearch, xyz: np.ndarray | None, goal, stamp: float) -> Any:
        """nav_msgs/Path from the robot's position over its last costmap (cell centres, at the
        robot's height; :func:`grid_path`) to the goal pose; no poses when there is no way."""
        from mapper.outputs.ros_markers import header_msg
        from mapper.outputs.ros_search import pose_msg

        T, fid = self.out.T, r.cfg.frame_id
        poses = []
        if goal is not None and xyz is not None and r.grid is not None:
            origin, cell, states = r.grid
            ends = [tuple(int(v) for v in np.floor((np.asarray(p[:2]) - origin) / cell)) for p in (xyz, goal[0])]
            cells = grid_path(step_costs(states, r.cfg.path_unknown_cost), ends[0], ends[1])
            if cells is not None:
                pts = [np.asarray(xyz, np.float64)]
                pts += [np.array([origin[0] + (i + 0.5) * cell, origin[1] + (j + 0.5) * cell, xyz[2]])
                        for i, j in cells[1:-1]]
                pts.append(np.asarray(goal[0], np.float64))
                yaws = [math.atan2(b[1] - a[1], b[0] - a[0]) for a, b in zip(pts[:-1], pts[1:], strict=True)]
                yaws.append(goal[1])
                poses = [T[POSE_STAMPED](header=header_msg(T, fid, stamp), pose=pose_msg(T, p, y))
                         for p, y in zip(pts, yaws, strict=True)]
        return T[PATH](header=header_msg(T, fid, stamp), poses=poses)

    def publish_search(self, r: RobotSearch, rep: SearchReply, xyz: np.ndarray | None, stamp: float) -> None:
        r.last_reply = rep
        for topic, (msgtype, msg) in self.messages(r, rep, xyz, stamp).items():
            self.out._put(topic, msgtype, msg)

    def costmap_band(self, r: RobotSearch, pose: np.ndarray | None) -> list[float] | None:
        """The costmap z band of robot ``r`` (None: relative to a position not known yet)."""
        plat = PLATFORMS[r.cfg.platform]
        if r.cfg.costmap_z_band:
            return [float(v) for v in r.cfg.costmap_z_band]
        if not plat["relative"]:
            return [float(v) for v in plat["costmap_z"]]
        if pose is None:
            return None
        return [float(pose[2, 3] + v) for v in plat["costmap_z"]]

    def costmap_cells(self, r: RobotSearch, pose: np.ndarray | None, vox: float) -> tuple[np.ndarray, int, int] | None:
        """``(origin (2,) m, stride, n cells per side or -1 for the site box)`` of the robot's
        costmap (None: a window before the robot's position is known)."""
        res = r.cfg.costmap_resolution_m
        stride = max(1, int(round(res / vox))) if res > 0 else 1
        if res > 0 and abs(stride * vox - res) > 1e-6 * res:
            raise ValueError(f"ros.robots.{r.id}.costmap_resolution_m={res} is not a multiple of the voxel "
                             f"size {vox} m")
        cell = stride * vox
        if r.cfg.costmap == "site":
            b = r.cfg.costmap_box
            return np.floor(np.array(b[:2]) / cell) * cell, stride, -1
        if pose is None:
            return None
        n = max(1, int(round(r.cfg.costmap_window_m / cell)))
        r.origin = window_origin(r.origin, pose[:2, 3], n, cell)
        return r.origin, stride, n

    def costmap_message(self, r: RobotSearch, pose: np.ndarray | None, stamp: float) -> tuple[str, Any] | None:
        """``(type, OccupancyGrid)`` of robot ``r`` through the search service's slice answer."""
        from common.search_messages import OccupancyRequest, encode_occupancy_request
        from mapper.outputs.ros_search import OCCUPANCY_GRID, occupancy_grid

        st = self.out.state
        if st.map is None:
            return None
        vox = float(st.map.cfg.vox_size)
        band = self.costmap_band(r, pose)
        cells = self.costmap_cells(r, pose, vox)
        if band is None or cells is None:
            return None
        origin, stride, n = cells
        cell = stride * vox
        if n < 0:
            b = r.cfg.costmap_box
            n_xy = np.maximum(1, np.ceil((np.array(b[2:]) - origin) / cell).astype(np.int64))
        else:
            n_xy = np.array([n, n])
        req = OccupancyRequest("slice", list(origin + vox / 2), list(origin + n_xy * cell - vox / 2), band,
                               stride=stride).validate()
        rep: OccupancyReply = self.search.occupancy(encode_occupancy_request(req))
        if r.cfg.unknown_near_obstacle == "occupied" and r.cfg.unknown_near_obstacle_m > 0:
            st_ = np.array(rep.states, np.int8)
            st_[unknown_near_obstacles(st_, r.cfg.unknown_near_obstacle_m / rep.cell_m)] = 1
            rep.states = st_
        r.grid = (np.asarray(rep.origin, np.float64), float(rep.cell_m), np.asarray(rep.states))
        return OCCUPANCY_GRID, occupancy_grid(self.out.T, r.cfg.frame_id, stamp, rep, band[0])
