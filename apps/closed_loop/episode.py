"""One closed-loop search episode: sense → map → search → decide → plan → move.

Per step the robot's views are rendered and sent through the edge chain
(:class:`apps.closed_loop.sensing.EdgeChain`), fused by the policy's map
(:class:`apps.closed_loop.world_model.LocalMapper`, or real edge and mapper processes over Zenoh:
:class:`apps.closed_loop.distributed.LiveMapper`, whose edge renders the views), searched for
the mission's target; the policy (:mod:`apps.closed_loop.policies`) picks a goal or declares
a found instance; the robot moves at most ``step_m`` along the shortest path through the
map's traversable known-free cells (:class:`apps.closed_loop.navigation.NavField`) and the
move is checked against the TRUE world (a collision ends the episode as failed). A
declaration counts when the declared instance's centroid lies within ``declare_m`` of an
uncounted true instance of the target and the robot is within ``reach_m`` (+ one voxel) of
it; otherwise it is a false find. World frame z up, metres; CPU times from
``time.process_time`` (this process: edge chain, map and planner together); wall times per
stage (``step_ms_p50``: sense = render + encode + wire, map, search, plan, and the whole step;
in process also ``render``, the simulated camera's share of sense, and ``robot_step`` = step −
render, what a robot whose camera delivers the images computes per step; 0 when not measured,
as with ``--distributed``, whose edge renders).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from apps.closed_loop.metrics import spl
from apps.closed_loop.missions import Mission, box_distance, xy_box_distance
from apps.closed_loop.navigation import NavField
from apps.closed_loop.planner import follow
from apps.closed_loop.policies import POLICIES, PolicyState, decide, is_set_aside
from apps.closed_loop.robot import Platform
from apps.closed_loop.sensing import EdgeChain
from synthetic_world import World

#: the values of :attr:`LoopSettings.background`
BACKGROUNDS = ("generic", "vocabulary", "world", "default")
#: ``background="generic"``: a fixed list of things found anywhere outdoors, the same for every
#: world (never the world's class list); docs/pybullet_world.md#semantics
GENERIC_BACKGROUND = ("ground", "road", "grass", "wall", "building", "tree", "sky")
#: ``background="vocabulary"``: ray evidence against the target's this many nearest phrases
VOCABULARY_NEAREST = 8


@dataclass
class LoopSettings:
    """Settings shared by all episodes of a run (lengths in metres)."""

    platform: str = "ground"
    depth_limit_m: float = 20.0
    vox_m: float = 0.5
    step_m: float = 2.0
    window_m: float = 30.0
    preset: str = "online"
    min_score: float = 0.3
    #: sem-poses: a pose's target margin must stand out this much (modified z-score among the
    #: episode's poses) to lead when no pose's probability reaches ``min_score``
    #: (:data:`apps.closed_loop.policies.SEM_POSES_MIN_Z`; chosen on development seeds by
    #: ``rayfronts eval tune-sem-poses``)
    sem_poses_min_z: float | None = None
    #: the searches' background phrases: "generic" = :data:`GENERIC_BACKGROUND` (what
    #: ``rayfronts eval search`` uses by default), "vocabulary" = the generic vocabulary less
    #: every class name of the world (:func:`~apps.closed_loop.generic_vocabulary.vocabulary_without`:
    #: a target then competes with the nearest common noun — "tower" for a radio tower read as a
    #: water tower — never with the name of the class it is confused with), "world" = every
    #: class of the world but the target
    #: (what the paper's querying softmaxes over: all class names), "default" = the mapper's
    #: ``search.background`` (building, road, ground, tree, sky: a radio tower then reads as a
    #: water tower, nothing else in the softmax being closer)
    background: str = "world"
    #: what the ray policies' ``ray_z`` z-scores (``search.ray_evidence``): "distinct" or "margin"
    ray_evidence: str = "distinct"
    #: the ray policies' ray angle bin psi (degrees; ``MapConfig.angle_bin_size``); None: the
    #: preset's (30 in ``online``, the paper's). Finer bins keep a far, narrow target's few
    #: rays from being averaged with the sky around it (docs/results/closed_loop_robot.md)
    angle_bin_deg: float | None = None

    def policy_state(self) -> PolicyState:
        """A new episode's policy memory in these settings."""
        state = PolicyState()
        if self.sem_poses_min_z is not None:
            state.pose_min_z = float(self.sem_poses_min_z)
        return state

    def map_config(self, method: str, world: World, width_px: int):
        """The mapper config of ``method``'s map in these settings
        (:func:`apps.closed_loop.world_model.mapper_config`)."""
        from apps.closed_loop.world_model import mapper_config

        return mapper_config(method, self.depth_limit_m, self.vox_m, width_px, self.preset,
                             self.background_phrases(world), self.ray_evidence, self.distinct_phrases(),
                             self.angle_bin_deg)

    def distinct_phrases(self) -> int:
        """``search.distinct_phrases`` of the searches: the target's 8 nearest phrases with the
        vocabulary background (a hundred phrases would explain every target), else all."""
        return VOCABULARY_NEAREST if self.background == "vocabulary" else 0

    def background_phrases(self, world: World) -> list[str] | None:
        """The phrases :attr:`background` names for ``world`` (None: the mapper's default)."""
        if self.background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}, not {self.background!r}")
        if self.background == "generic":
            return list(GENERIC_BACKGROUND)
        if self.background == "vocabulary":
            from apps.closed_loop.generic_vocabulary import vocabulary_without

            return vocabulary_without(list(world.classes))
        return list(world.classes) if self.background == "world" else None


#: how many of a step's look-next goals a trace keeps (the strongest rays first)
TRACE_RAYS = 5


@dataclass
class Trace:
    """What happened, step by step (for recordings and ``eval search --trace``): robot
    positions, goals, found boxes, the decision's reason, the strongest ray goals and (with
    ``keep_voxels``) a subsample of the map's voxels."""

    positions: list = field(default_factory=list)
    goals: list = field(default_factory=list)
    found: list = field(default_factory=list)
    why: list = field(default_factory=list)
    rays: list = field(default_factory=list)        # per step: up to TRACE_RAYS look-next goals with rays
    voxels: list = field(default_factory=list)      # (N, 3) map voxel centres, subsampled, per step
    driven: list = field(default_factory=list)      # every point passed: the start, then each route point
    keep_voxels: bool = True

    def steps(self) -> list[dict]:
        """One dict per step: ``step`` (0-based), ``position`` (camera centre, m, world frame
        z up, at the step's start), ``why`` (the decision), ``goal`` (xy, m; None when none),
        ``rays`` (:func:`strongest_rays`) and ``found`` (the target instances the search
        returned: id, centroid, confidence)."""
        out = []
        for i, why in enumerate(self.why):
            g = self.goals[i]
            out.append({"step": i, "position": [round(float(v), 3) for v in self.positions[i]], "why": why,
                        "goal": None if g is None else [round(float(v), 3) for v in g[:2]],
                        "rays": self.rays[i],
                        "found": [{"id": int(f["id"]), "centroid": [round(float(v), 2) for v in f["centroid"]],
                                   "confidence": f.get("confidence")}
                                  for f in self.found[i] if "id" in f and "centroid" in f]})
        return out


def strongest_rays(look_next: list[dict], state: PolicyState | None = None, n: int = TRACE_RAYS) -> list[dict]:
    """The ``n`` look-next goals with rays (``heading_rad`` set), highest ``ray_z`` first:
    ``position`` (xy, m), ``heading_deg`` (the rays' yaw, degrees counter-clockwise from +x),
    ``ray_z``, ``score`` and ``set_aside`` (after the step's decision the policy of ``state``
    has set the goal aside for the episode: it no longer leads)."""
    rays = [g for g in look_next if g.get("heading_rad") is not None]
    rays.sort(key=lambda g: -float(g.get("ray_z", 0.0)))
    return [{"position": [round(float(v), 2) for v in g["position"][:2]],
             "heading_deg": round(float(np.degrees(g["heading_rad"])), 1),
             "ray_z": round(float(g.get("ray_z", 0.0)), 2), "score": float(f"{float(g.get('score', 0.0)):.4g}"),
             "set_aside": bool(state is not None and is_set_aside(state, np.asarray(g["position"][:2])))}
            for g in rays[:n]]


def _check_declaration(inst: dict, mission: Mission, at: np.ndarray, counted: set, vox: float) -> str:
    """'find' (a new true instance), 'again' (one already counted) or 'false'."""
    c = np.asarray(inst["centroid"], np.float64)
    for t in mission.instances:
        if box_distance(c, t.aabb_min, t.aabb_max) <= mission.declare_m \
                and xy_box_distance(at, t.aabb_min, t.aabb_max) <= mission.reach_m + vox:
            if t.id in counted:
                return "again"
            counted.add(t.id)
            return "find"
    return "false"


@dataclass
class _Run:
    """An episode's running totals."""

    pos: np.ndarray
    path_m: float = 0.0
    steps: int = 0
    false_finds: int = 0
    collided: bool = False
    finds: list = field(default_factory=list)
    declarations: list = field(default_factory=list)
    counted: set = field(default_factory=set)
    cpu: list = field(default_factory=list)
    search_ms: list = field(default_factory=list)
    stage_ms: dict = field(default_factory=lambda: {"sense": [], "map": [], "search": [], "plan": [], "step": [],
                                                    "render": [], "robot_step": []})
    driven: list = field(default_factory=list)     # every point passed, from the first move's start
    pose_z: list = field(default_factory=list)     # sem-poses: the z-scores where its cut decided

    def start_step(self, step: int, trace: Trace | None) -> float:
        """Count step ``step`` (0-based) and record the position in ``trace``; returns the
        process CPU time at the step's start (s, ``time.process_time``)."""
        self.steps = step + 1
        c0 = time.process_time()
        if trace is not None:
            trace.positions.append(self.pos.copy())
        return c0

    def move(self, robot: Platform, world: World, points: np.ndarray) -> bool:
        """Drive through ``points`` ((3,) one point, or (K, 3) a route's points in order), leg
        by leg, unless the body swept along a leg would touch the true world (then: collided,
        and the robot stays where that leg starts)."""
        for nxt in np.asarray(points, np.float64).reshape(-1, 3):
            if robot.collides(world, self.pos, nxt):
                self.collided = True
                return False
            if not self.driven:
                self.driven.append(self.pos.copy())
            self.path_m += float(np.linalg.norm(nxt - self.pos))
            self.pos = nxt
            self.driven.append(nxt.copy())
        return True


def _declaration_row(world: World, inst: dict, verdict: str, run: _Run) -> dict:
    """What a declaration was: ``step`` (1-based), ``verdict`` ('find' | 'again' | 'false'),
    the declared ``centroid`` and the TRUE world instance nearest to it (``nearest_class``,
    ``nearest_id``, ``nearest_m``: distance from the centroid to its box, ties — a point
    inside several boxes, e.g. a duck's within the whole site's building — to the smallest
    box; what a false find really was), and what the robot's map said of the instance it
    declared, where the instance carries it: ``confidence``, ``voxels``, ``observations`` and
    ``extent_m`` (its box's x, y, z sizes)."""
    c = np.asarray(inst["centroid"], np.float64)

    def volume(i) -> float:
        return float(np.prod(np.maximum(np.asarray(i.aabb_max, np.float64) - np.asarray(i.aabb_min, np.float64), 0.0)))

    near = min(world.instances, key=lambda i: (box_distance(c, i.aabb_min, i.aabb_max), volume(i)))
    row = {"step": run.steps, "verdict": verdict, "centroid": [round(float(v), 2) for v in c],
           "nearest_class": world.classes[near.class_id], "nearest_id": int(near.id),
           "nearest_m": round(float(box_distance(c, near.aabb_min, near.aabb_max)), 2)}
    for key in ("confidence", "voxels", "observations"):
        if key in inst:
            row[key] = round(float(inst[key]), 4) if key == "confidence" else int(inst[key])
    if "box_min" in inst and "box_max" in inst:
        ext = np.asarray(inst["box_max"], np.float64) - np.asarray(inst["box_min"], np.float64)
        row["extent_m"] = [round(float(v), 2) for v in ext]
    return row


def _oracle(world: World, mission: Mission, robot: Platform, settings: LoopSettings, run: _Run,
            trace: Trace | None) -> None:
    """Drive the mission's true tour; all its instances are declared on arrival."""
    total = float(np.linalg.norm(np.diff(mission.oracle_path[:, :2], axis=0), axis=1).sum())
    done = 0.0
    for step in range(mission.budget_steps):
        c0 = run.start_step(step, trace)
        xy, done = follow(mission.oracle_path[:, :2], done, settings.step_m)
        if not run.move(robot, world, np.r_[xy, run.pos[2]]):
            return
        run.cpu.append((time.process_time() - c0) * 1e3)
        if done >= total - 1e-9:
            run.finds = [(run.steps, run.path_m)] * mission.k
            run.counted = {i.id for i in mission.instances[:mission.k]}
            return


def _record(trace: Trace | None, obs, d, mapper, step: int, state: PolicyState | None = None) -> None:
    if trace is None:
        return
    trace.found.append(list(obs.found))
    trace.goals.append(None if d.goal_xy is None else np.asarray(d.goal_xy, np.float64))
    trace.why.append(d.why)
    trace.rays.append(strongest_rays(obs.look_next, state))
    m = getattr(mapper, "map", None)
    if m is not None and trace.keep_voxels:
        xyz = m.voxel_xyz().cpu().numpy()
        trace.voxels.append(xyz[np.random.default_rng(step).permutation(len(xyz))[:20000]])


def _searching(world: World, mission: Mission, policy: str, robot: Platform, settings: LoopSettings,
               chain: EdgeChain, mapper, run: _Run, trace: Trace | None) -> None:
    """The map-based loop: sense, map, search, decide, move (module docstring)."""
    semantic = POLICIES[policy][1]
    if hasattr(chain, "start_episode"):
        chain.start_episode()
    state = settings.policy_state()
    run.pose_z = state.pose_z_seen
    stuck = 0
    for step in range(mission.budget_steps):
        c0 = run.start_step(step, trace)
        t = [time.perf_counter()]
        poses = chain.view_poses(robot, run.pos)
        render_ms = None                                  # measured in process only
        if getattr(mapper, "renders_remotely", False):   # a live edge renders and sends; sense = whole trip
            mapper.sense(poses)
            t.append(time.perf_counter())
            t.append(t[-1])
        else:
            views = [chain.render(p) for p in poses]
            rendered = time.perf_counter()
            frames = [chain.encode(v, p) for v, p in zip(views, poses, strict=True)]
            t.append(time.perf_counter())
            render_ms = (rendered - t[0]) * 1e3
            mapper.integrate(frames)
            t.append(time.perf_counter())
        obs = mapper.observe([mission.target], run.pos, semantic=semantic, z_band=robot.goal_band)
        t.append(time.perf_counter())
        run.search_ms.append(obs.search_ms)
        states = robot.with_own_body_free(obs.states, obs.origin, obs.cell, run.pos)
        nav = NavField(states, obs.origin, obs.cell, run.pos, robot.radius)
        if nav.boxed_in():        # a newly seen obstacle or unknown cell within the clearance of the
            # robot's own cell: leave through free cells
            nav = NavField.free_cells_only(states, obs.origin, obs.cell, run.pos)
        d = decide(policy, obs, nav, run.pos, state, mission.reach_m)
        t.append(time.perf_counter())
        for k, a, b in zip(("sense", "map", "search", "plan"), t[:-1], t[1:], strict=True):
            run.stage_ms[k].append((b - a) * 1e3)
        run.stage_ms["step"].append((t[-1] - t[0]) * 1e3)
        if render_ms is not None:
            run.stage_ms["render"].append(render_ms)
            run.stage_ms["robot_step"].append(run.stage_ms["step"][-1] - render_ms)
        _record(trace, obs, d, mapper, step, state)
        if d.declare is not None:
            state.declared.add(d.declare["id"])
            verdict = _check_declaration(d.declare, mission, run.pos, run.counted, settings.vox_m)
            if verdict == "find":
                run.finds.append((run.steps, run.path_m))
            run.false_finds += verdict == "false"
            run.declarations.append(_declaration_row(world, d.declare, verdict, run))
        elif d.goal_cell is None:
            stuck += 1
        else:
            stuck = 0
            xy = nav.route_toward(d.goal_cell, settings.step_m, run.pos)
            if not run.move(robot, world, np.c_[xy, np.full(len(xy), run.pos[2])]):
                return
        run.cpu.append((time.process_time() - c0) * 1e3)
        if len(run.counted) >= mission.k or stuck >= 3:
            return


def run_episode(world: World, mission: Mission, policy: str, settings: LoopSettings,
                chain: EdgeChain | None = None, mapper=None, trace: Trace | None = None) -> dict:
    """Run ``policy`` on ``mission``; returns the episode row (``success``, ``spl``, ``path_m``,
    ``steps``, ``false_finds``, ``finds`` [(step, path_m)], ``declarations`` (one row per
    declaration: :func:`_declaration_row`), ``collided``, ``cpu_ms_per_step``,
    ``search_ms_p50``, ``pose_z`` (sem-poses: the distinct z-scores of the steps where its cut
    decided, rounded to 1e-6), ...). ``mapper``: an object with ``integrate(frames)`` (or, with
    ``renders_remotely``, ``sense(poses)``) and ``observe(targets, at, semantic=..., z_band=...)``
    (default: a new LocalMapper for the policy)."""
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r}; one of {', '.join(POLICIES)}")
    robot = Platform.make(settings.platform)
    method, _, poses = POLICIES[policy]
    run = _Run(np.asarray(mission.start, np.float64).copy())
    if method is None:
        _oracle(world, mission, robot, settings, run, trace)
    else:
        if chain is None:
            raise ValueError(f"policy {policy!r} maps what the robot sees: pass the edge chain")
        if mapper is None:
            from apps.closed_loop.world_model import LocalMapper

            cfg = settings.map_config(method, world, chain.cfg.resolution)
            mapper = LocalMapper(chain.space, cfg, robot.costmap_band(settings.vox_m), settings.window_m,
                                 score_poses=poses)
        _searching(world, mission, policy, robot, settings, chain, mapper, run, trace)
    if trace is not None:
        trace.positions.append(run.pos.copy())
        trace.driven = [p.copy() for p in (run.driven or [run.pos])]
    success = (len(run.counted) >= mission.k) and not run.collided
    return {"policy": policy, "success": bool(success), "spl": spl(success, mission.shortest_m, run.path_m),
            "path_m": run.path_m, "shortest_m": mission.shortest_m, "steps": run.steps,
            "false_finds": int(run.false_finds), "finds": run.finds, "found": len(run.counted),
            "declarations": run.declarations,
            "collided": run.collided, "cpu_ms_per_step": float(np.mean(run.cpu)) if run.cpu else 0.0,
            "search_ms_p50": float(np.median(run.search_ms)) if run.search_ms else 0.0,
            "step_ms_p50": {k: float(np.median(v)) if v else 0.0 for k, v in run.stage_ms.items()},
            "end": [float(v) for v in run.pos], **mission.describe(),
            **({"pose_z": sorted({round(z, 6) for z in run.pose_z})} if policy == "sem-poses" else {})}
