"""One closed-loop search episode with a fleet of N robots on one shared map (issue 44's loop).

Each step every robot senses (its views through the edge chain), the shared map fuses all
views, the fleet's policy gives each robot a goal, and each robot moves at most ``step_m``
along its own shortest path through the map's traversable cells (checked against the TRUE
world; a collision ends the episode as failed). Robots do not collide with each other (the
bodies are not modelled against one another). Starts (:func:`fleet_starts`): ``together``
(robot 0 at the mission start, the others on free ground 1.5–3 m from it) or ``spread``
(robot 0 at the start, the others ``spread_m`` out on evenly spaced bearings, pulled in to
free ground).

Policies (:data:`FLEET_POLICIES`):

* ``coordinated``: the RayFronts fleet. Found instances: the robot nearest (by path) to an
  undeclared found instance approaches and declares it as one robot does
  (:func:`apps.closed_loop.policies.confirm`); the others are no longer sent toward it (their
  goals are discounted with :func:`planning.fleet_allocation.discount_found`). Exploration,
  in two rounds of :func:`planning.fleet_allocation.allocate_goals` (greedy): (1) each robot
  bids the goal the single-robot ``rayfronts`` policy would choose for it
  (:func:`apps.closed_loop.policies.explore`, with its own memory), valued by the bid's
  evidence (:func:`planning.fleet_allocation.goal_value` with score 1 for a goal chosen by
  the rays, else the goal's own); bids closer than ``footprint_m`` (transitively) form one
  region, and each region goes to the robot with the shortest path to any of its bids, among
  the robots that bid there (a robot nearer another robot's bid takes that bid over and holds
  it as its own goal); the others lose; (2) the robots whose bids lost share the look-next
  goals of all robots that lie at least ``footprint_m`` from the kept bids, by gain per metre
  of their own path (:func:`planning.fleet_allocation.goal_value` /
  (1 + path)). With one robot its bid always stands: the single-robot ``rayfronts`` episode.
* ``uncoordinated``: each robot runs the single-robot ``rayfronts`` policy alone on the shared
  map (its own memory, no allocation, every robot may approach a found instance).
* ``frontier-only``: ``coordinated`` with the single-robot ``frontier`` policy's bids on a map
  without semantic look-next (gain per metre only): frontier exploration with the same
  allocation.

Metrics (:func:`run_fleet_episode`'s row): ``steps`` until the mission ended (the target
found: k instances counted), ``path_m`` the total path of all robots, ``paths_m`` per robot,
``finder`` the robot that made the last counting find, ``spl`` the finder's SPL against the
mission's shortest path from the mission start, ``duplicated_coverage`` the fraction of the
observed volume seen by more than one robot (observed volume: the map voxels holding a depth
return of a robot's views within the depth limit, counted on every 4th pixel).
World frame z up, metres.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from apps.closed_loop.episode import LoopSettings, _check_declaration, _declaration_row, _Run
from apps.closed_loop.metrics import spl
from apps.closed_loop.missions import Mission
from apps.closed_loop.navigation import NavField
from apps.closed_loop.policies import Decision, confirm, decide, explore
from apps.closed_loop.robot import Platform
from apps.closed_loop.sensing import EdgeChain
from apps.closed_loop.world_model import Observation
from planning.fleet_allocation import FoundInstance, RobotSlot, allocate_goals, discount_found
from planning.look_next import Goal
from synthetic_world import World

#: fleet policy -> (map method of semantic_map.config.METHODS, semantic look-next, single-robot bids, allocate)
FLEET_POLICIES: dict[str, tuple[str, bool, str, bool]] = {
    "coordinated": ("rayfronts", True, "rayfronts", True),
    "uncoordinated": ("rayfronts", True, "rayfronts", False),
    "frontier-only": ("semantic_voxels", False, "frontier", True),
}
#: the values of ``--start``
START_MODES = ("together", "spread")
#: pixels between the samples of a view counted for the observed volume
COVERAGE_STRIDE = 4


@dataclass(frozen=True)
class FleetSettings:
    """The fleet of one run: ``robots`` N, ``start`` (:data:`START_MODES`), ``footprint_m`` the
    least distance between two robots' goals (m), ``spread_m`` the ``spread`` starts' radius."""

    robots: int = 1
    start: str = "together"
    footprint_m: float = 8.0
    spread_m: float = 12.0

    def validate(self) -> "FleetSettings":
        if not (isinstance(self.robots, int) and self.robots >= 1):
            raise ValueError(f"--robots must be an integer ≥ 1, got {self.robots!r}")
        if self.start not in START_MODES:
            raise ValueError(f"--start must be one of {', '.join(START_MODES)}, not {self.start!r}")
        if not (self.footprint_m >= 0 and self.spread_m > 0):
            raise ValueError("the fleet's footprint_m must be ≥ 0 and spread_m > 0 (metres)")
        return self


def robot_name(i: int) -> str:
    """The id of the fleet's robot ``i`` (robot 0 is ``sim``, the single robot's id)."""
    return "sim" if i == 0 else f"sim{i}"


def _free(world: World, robot: Platform, a: np.ndarray, b: np.ndarray) -> bool:
    return not robot.collides(world, a, b)


def fleet_starts(world: World, robot: Platform, start: np.ndarray, n: int, mode: str = "together",
                 spread_m: float = 12.0) -> list[np.ndarray]:
    """Camera centres (m) of ``n`` robots (module docstring): robot 0 at ``start``; ``together``:
    the others at the first free spots 1.5 m then 3 m from it (8 bearings each, reachable in a
    straight line, 1.2 m or more from the robots placed); ``spread``: on bearings ``2πk/n``,
    the farthest free spot up to ``spread_m`` out (1 m steps inward). Raises ``ValueError`` when
    a robot has no free spot."""
    s = np.asarray(start, np.float64)
    out = [s.copy()]
    for k in range(1, n):
        if mode == "together":
            spots = [s + r * np.array([math.cos(a), math.sin(a), 0.0])
                     for r in (1.5, 3.0) for a in np.arange(8) * math.pi / 4]
        else:
            a = 2 * math.pi * k / n
            spots = [s + r * np.array([math.cos(a), math.sin(a), 0.0]) for r in np.arange(spread_m, 0.9, -1.0)]
        ok = [p for p in spots if _free(world, robot, p, p) and min(np.linalg.norm(p - q) for q in out) >= 1.2
              and (mode == "spread" or _free(world, robot, s, p))]
        if not ok:
            raise ValueError(f"no free start for robot {k} of {n} near {s.round(2).tolist()} ({mode})")
        out.append(ok[0])
    return out


def observed_voxels(frame, vox: float, depth_limit_m: float, stride: int = COVERAGE_STRIDE) -> set:
    """Voxel keys (i, j, k) of a frame's depth returns within ``depth_limit_m`` (every
    ``stride``-th pixel; world frame, voxels of ``vox`` m)."""
    d = np.asarray(frame.depth, np.float64)[::stride, ::stride]
    v, u = np.mgrid[0:frame.depth.shape[0]:stride, 0:frame.depth.shape[1]:stride]
    ok = np.isfinite(d) & (d > 0) & (d <= depth_limit_m)
    k = np.asarray(frame.intrinsics, np.float64)
    z = d[ok]
    cam = np.stack([(u[ok] - k[0, 2]) / k[0, 0] * z, (v[ok] - k[1, 2]) / k[1, 1] * z, z], 1)
    pose = np.asarray(frame.pose, np.float64)
    pts = cam @ pose[:3, :3].T + pose[:3, 3]
    return set(map(tuple, np.floor(pts / vox).astype(np.int64).tolist()))


def duplicated_coverage(seen: list[set]) -> tuple[float, int]:
    """(fraction of the union of ``seen`` (per robot voxel sets) in two or more of them, union size)."""
    counts: dict = {}
    for s in seen:
        for key in s:
            counts[key] = counts.get(key, 0) + 1
    if not counts:
        return 0.0, 0
    return sum(c > 1 for c in counts.values()) / len(counts), len(counts)


def _found_instances(obs: Observation, declared: set) -> list[FoundInstance]:
    return [FoundInstance(str(f["target"]), tuple(float(v) for v in f["centroid"]))  # type: ignore[arg-type]
            for f in obs.found if f["id"] in declared]


def _discounted(obs: Observation, found: list[FoundInstance], k: int) -> Observation:
    """``obs`` with the evidence off the goals aimed at ``found`` (planning.fleet_allocation)."""
    if not found:
        return obs
    conv = [Goal.from_dict(g) for g in obs.look_next]
    goals = discount_found(conv, found, target_count=k)
    look = [g if h is c else dict(g, score=0.0, ray_z=0.0, target=None)
            for g, c, h in zip(obs.look_next, conv, goals, strict=True)]
    return dataclasses.replace(obs, look_next=look)


@dataclass
class _Fleet:
    """The fleet's per-robot state over an episode."""

    runs: list
    states: list
    navs: list = field(default_factory=list)
    obs: list = field(default_factory=list)
    seen: list = field(default_factory=list)
    stuck: list = field(default_factory=list)


def _cost_fn(fl: _Fleet, names: list[str]):
    """path_m(robot, position) of the allocation: the robot's path to the reachable cell
    nearest the viewpoint plus the gap beyond it; None when it gives no progress or the robot
    set it aside."""
    index = {n: i for i, n in enumerate(names)}

    def path_m(robot: str, p: np.ndarray) -> float | None:
        i = index[robot]
        nav, st = fl.navs[i], fl.states[i]
        if any(np.linalg.norm(p[:2] - a) < 1.5 for a in st.set_aside):
            return None
        cell, pl, gap = nav.nearest_reachable(p)
        return None if tuple(int(v) for v in cell) == nav.start else pl + gap
    return path_m


def _bid_clusters(points: list, footprint: float) -> list[int]:
    """Cluster label per point: points closer than ``footprint`` (m), transitively, share one
    (the connected components of the closer-than graph)."""
    from scipy.sparse.csgraph import connected_components

    if not points:
        return []
    xyz = np.asarray(points, np.float64)
    near = np.linalg.norm(xyz[:, None, :] - xyz[None], axis=2) < footprint
    return [int(c) for c in connected_components(near, directed=False)[1]]


def _allocate(bids: dict[int, tuple[Decision, bool]], fl: _Fleet, names: list[str], explorers: list[int],
              footprint: float) -> dict[int, Decision]:
    """The two allocation rounds of the module docstring; returns robot index -> decision."""
    path_m = _cost_fn(fl, names)
    pos = {i: np.asarray(fl.runs[i].pos, np.float64) for i in explorers}
    slots = [RobotSlot(names[i], (float(pos[i][0]), float(pos[i][1]), float(pos[i][2]))) for i in explorers]
    owner: dict[int, int] = {}
    props = []
    for i in explorers:
        d, evidence = bids[i]
        if d.goal_xy is None or d.goal_cell is None:
            continue
        gxy = d.goal_xy
        near = min(fl.obs[i].look_next, key=lambda g: np.linalg.norm(np.asarray(g["position"][:2]) - gxy[:2]),
                   default=None)
        z = float(near["position"][2]) if near is not None else float(fl.runs[i].pos[2])
        g = Goal(np.r_[np.asarray(d.goal_xy[:2], np.float64), z], 0.0, 1.0 if evidence else 0.0,
                 float(near.get("gain_m3", 0.0)) if near is not None else 0.0, 0.0, None, np.zeros(3))
        owner[id(g)] = i
        props.append(g)
    cluster = _bid_clusters([g.position for g in props], footprint)
    mine = {names[owner[id(g)]]: cluster[k] for k, g in enumerate(props)}
    index = {id(g): k for k, g in enumerate(props)}

    def bid_path(robot: str, p: np.ndarray) -> float | None:
        """A robot's path to a bid of its cluster: its own bid's path (explore's choice has
        progress), else its path to the reachable cell nearest that bid plus the gap."""
        i = names.index(robot)
        own = bids[i][0].goal_xy
        if own is not None and np.allclose(np.asarray(own[:2], np.float64), p[:2]):
            return float(fl.navs[i].dist_m[tuple(int(v) for v in bids[i][0].goal_cell)])  # type: ignore[union-attr]
        return path_m(robot, p)

    first = allocate_goals(slots, props, footprint_m=footprint, path_m=bid_path,
                           eligible=lambda r, g: mine.get(r) == cluster[index[id(g)]])
    out: dict[int, Decision] = {}
    kept = []
    for i in explorers:
        won = first.goals[names[i]]
        if won is None:
            continue
        kept.append(won.position)
        j = owner[id(won)]
        if j == i:
            out[i] = bids[i][0]
            continue
        cell, _, _ = fl.navs[i].nearest_reachable(won.position)     # a nearer robot takes over the bid
        d = bids[j][0]
        out[i] = Decision(goal_cell=cell, goal_xy=won.position[:2].copy(), why=f"{d.why} (from {names[j]})",
                          score=d.score)
        fl.states[i].goal = (won.position[:2].copy(), d.score, bids[j][1])
    losers = [i for i in explorers if i not in out]
    if not losers:
        return out
    pool: dict[tuple, Goal] = {}
    for i in explorers:
        for g in fl.obs[i].look_next:
            goal = Goal.from_dict(g)
            if all(np.linalg.norm(goal.position - q) >= footprint for q in kept):
                pool.setdefault(tuple(np.round(goal.position, 2)), goal)
    second = allocate_goals([s for s in slots if names.index(s.robot) in losers], list(pool.values()),
                            footprint_m=footprint, path_m=path_m)
    for i in losers:
        won = second.goals[names[i]]
        fl.states[i].goal = None          # its own bid lost: it decides afresh next step
        if won is None:
            out[i] = Decision(why="no goal left for this robot")
            continue
        cell, _, _ = fl.navs[i].nearest_reachable(won.position)
        out[i] = Decision(goal_cell=cell, goal_xy=won.position[:2].copy(), why="allocated", score=won.score)
    return out


def _decisions(policy: str, fl: _Fleet, names: list[str], mission: Mission, footprint: float) -> list[Decision]:
    """Each robot's decision this step (module docstring)."""
    _, _, single, coordinated = FLEET_POLICIES[policy]
    n = len(names)
    if not coordinated:
        return [decide(single, fl.obs[i], fl.navs[i], fl.runs[i].pos, fl.states[i], mission.reach_m) for i in range(n)]
    out: dict[int, Decision] = {}
    approach = []
    for i in range(n):
        d = confirm(fl.obs[i], fl.navs[i], fl.runs[i].pos, fl.states[i], mission.reach_m)
        if d is not None and d.declare is not None:
            out[i] = d
        elif d is not None:
            assert d.goal_cell is not None     # confirm() approaches a cell
            approach.append((float(fl.navs[i].dist_m[tuple(int(v) for v in d.goal_cell)]), i, d))
    if approach and not out:        # one robot at a time approaches what was found: the nearest
        _, i, d = min(approach, key=lambda x: x[:2])
        out[i] = d
    explorers = [i for i in range(n) if i not in out]
    found = []
    for i in range(n):
        if i in out:      # what robot i approaches or declares counts as found for the others
            found += [FoundInstance(str(f["target"]), tuple(float(v) for v in f["centroid"]))  # type: ignore[arg-type]
                      for f in fl.obs[i].found if f["id"] not in fl.states[i].declared]
        found += _found_instances(fl.obs[i], fl.states[i].declared)
    bids = {}
    for i in explorers:
        fl.obs[i] = _discounted(fl.obs[i], found, mission.k)
        d = explore(single, fl.obs[i], fl.navs[i], fl.states[i])
        evidence = d.goal_xy is not None and fl.states[i].goal is not None and bool(fl.states[i].goal[2])
        bids[i] = (d, evidence)
    if explorers:
        out.update(_allocate(bids, fl, names, explorers, footprint))
    return [out[i] for i in range(n)]


@dataclass
class _Tally:
    """The fleet's declarations and finds so far."""

    counted: set = field(default_factory=set)
    finds: list = field(default_factory=list)
    declarations: list = field(default_factory=list)
    false_finds: int = 0
    finder: str | None = None

    def declare(self, world: World, mission: Mission, fl: _Fleet, i: int, name: str, inst: dict, steps: int,
                vox: float) -> None:
        """Robot ``i`` declares ``inst``: for the whole fleet (no robot declares it again)."""
        for st in fl.states:
            st.declared.add(inst["id"])
        r = fl.runs[i]
        r.steps = steps
        verdict = _check_declaration(inst, mission, r.pos, self.counted, vox)
        if verdict == "find":
            self.finder = name
            self.finds.append((steps, sum(x.path_m for x in fl.runs)))
        self.false_finds += verdict == "false"
        self.declarations.append(_declaration_row(world, inst, verdict, r) | {"robot": name})


def _sense(fl: _Fleet, chain: EdgeChain, robot: Platform, mapper, names: list[str], settings: LoopSettings,
           target: str, semantic: bool) -> list[float]:
    """Every robot senses, the shared map fuses all views, each robot reads the search and its
    costmap (``fl.obs``, ``fl.navs``); returns the searches' times (ms)."""
    frames = []
    for i, r in enumerate(fl.runs):
        for pose in chain.view_poses(robot, r.pos):
            f = chain.frame(pose, names[i])
            fl.seen[i] |= observed_voxels(f, settings.vox_m, settings.depth_limit_m)
            frames.append(f)
    mapper.integrate(frames)
    fl.obs, fl.navs = [], []
    ms = []
    for r in fl.runs:
        obs = mapper.observe([target], r.pos, semantic=semantic, z_band=robot.goal_band)
        ms.append(obs.search_ms)
        states = robot.with_own_body_free(obs.states, obs.origin, obs.cell, r.pos)
        nav = NavField(states, obs.origin, obs.cell, r.pos, robot.radius)
        if nav.boxed_in():
            nav = NavField.free_cells_only(states, obs.origin, obs.cell, r.pos)
        fl.obs.append(obs)
        fl.navs.append(nav)
    return ms


def run_fleet_episode(world: World, mission: Mission, policy: str, settings: LoopSettings, fleet: FleetSettings,
                      chain: EdgeChain, trace: list | None = None, routes: list | None = None) -> dict:
    """Run fleet ``policy`` (:data:`FLEET_POLICIES`) with ``fleet.robots`` robots on ``mission``;
    returns the episode row (module docstring; also ``success``, ``false_finds``, ``finds``
    [(step, total path)], ``declarations``, ``collided``, ``cpu_ms_per_step``, ``end`` per
    robot). ``trace``: a list that gets each step's robot positions ((N, 3) arrays);
    ``routes``: a list that gets, at the end, each robot's driven points ((K, 3): its start,
    then every route point passed)."""
    from apps.closed_loop.world_model import LocalMapper

    if policy not in FLEET_POLICIES:
        raise ValueError(f"unknown fleet policy {policy!r}; one of {', '.join(FLEET_POLICIES)}")
    fleet.validate()
    robot = Platform.make(settings.platform)
    method, semantic, _, _ = FLEET_POLICIES[policy]
    cfg = settings.map_config(method, world, chain.cfg.resolution)
    mapper = LocalMapper(chain.space, cfg, robot.costmap_band(settings.vox_m), settings.window_m)
    names = [robot_name(i) for i in range(fleet.robots)]
    starts = fleet_starts(world, robot, mission.start, fleet.robots, fleet.start, fleet.spread_m)
    fl = _Fleet([_Run(p.copy()) for p in starts], [settings.policy_state() for _ in names])
    fl.seen, fl.stuck = [set() for _ in names], [0] * len(names)
    chain.start_episode()
    tally = _Tally()
    cpu: list[float] = []
    search_ms: list[float] = []
    collided, steps = False, 0
    for step in range(mission.budget_steps):
        steps = step + 1
        c0 = time.process_time()
        if trace is not None:
            trace.append(np.stack([r.pos for r in fl.runs]))
        search_ms += _sense(fl, chain, robot, mapper, names, settings, mission.target, semantic)
        for i, d in enumerate(_decisions(policy, fl, names, mission, fleet.footprint_m)):
            r = fl.runs[i]
            if d.declare is not None:
                if d.declare["id"] in fl.states[i].declared:   # another robot declared it this step
                    continue                                   # (robots side by side decide at once)
                tally.declare(world, mission, fl, i, names[i], d.declare, steps, settings.vox_m)
            elif d.goal_cell is None:
                fl.stuck[i] += 1
            else:
                fl.stuck[i] = 0
                xy = fl.navs[i].route_toward(d.goal_cell, settings.step_m, r.pos)
                collided = collided or not r.move(robot, world, np.c_[xy, np.full(len(xy), r.pos[2])])
        cpu.append((time.process_time() - c0) * 1e3)
        if collided or len(tally.counted) >= mission.k or min(fl.stuck) >= 3:
            break
    if trace is not None:
        trace.append(np.stack([r.pos for r in fl.runs]))
    if routes is not None:
        routes.extend(np.asarray(r.driven or [r.pos], np.float64).reshape(-1, 3) for r in fl.runs)
    success = len(tally.counted) >= mission.k and not collided
    dup, observed = duplicated_coverage(fl.seen)
    paths = [float(r.path_m) for r in fl.runs]
    fpath = paths[names.index(tally.finder)] if tally.finder is not None else 0.0
    return {"policy": policy, "robots": fleet.robots, "start_mode": fleet.start, "success": bool(success),
            "spl": spl(success, mission.shortest_m, fpath), "path_m": float(sum(paths)), "paths_m": paths,
            "finder": tally.finder, "finder_path_m": fpath, "shortest_m": mission.shortest_m, "steps": steps,
            "false_finds": int(tally.false_finds), "finds": tally.finds, "found": len(tally.counted),
            "declarations": tally.declarations, "collided": collided, "duplicated_coverage": dup,
            "observed_voxels": observed, "cpu_ms_per_step": float(np.mean(cpu)) if cpu else 0.0,
            "search_ms_p50": float(np.median(search_ms)) if search_ms else 0.0,
            "starts": [[float(v) for v in p] for p in starts],
            "end": [[float(v) for v in r.pos] for r in fl.runs], **mission.describe()}
