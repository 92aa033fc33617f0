"""``rayfronts eval search``: closed-loop search episodes for every policy on the same worlds,
starts and targets, and their summary (success, SPL, path, false finds, CPU per step).

Worlds (``world``): ``synthetic`` (the procedural town, ``synthetic_world``) or ``pybullet``
(scenes of pybullet_data assets: :mod:`synthetic_world.pybullet_world`). Defaults are the
conditions a robot has (docs/pybullet_world.md): the realistic depth sensor, the simulated
ViT-like encoder, a PCA basis fitted on the robot's first views and the generic background
phrases; ``--sensor exact``, ``--encoder label``, ``--pca-fit classes`` and ``--background
world`` give the exact ablations. The JSON's ``meta`` block says which commit, command line,
machine and load it ran with (:mod:`apps.bench.meta`), ``seeds`` which seeds and whether they
are development or held-out seeds (:mod:`apps.closed_loop.seeds`).

Episodes: for each seed (a world) and each mission kind, ``episodes`` missions are drawn
(targets cycle through the kind's classes; starts random in the town, seeded by the seed and
the episode index), and every policy runs each mission at each depth limit. Outputs:
``--json FILE`` ``{"policies": {NAME: {"success", "spl", "path_m", "false_finds",
"episodes", "steps", "cpu_ms_per_step", "by_depth": {...}, "by_kind": {...}}}, "settings":
{...}, "episodes": [rows]}``; next to it a Markdown table (``.md``), a CSV of episode rows
(``.csv``) and plots (``_spl.png``: SPL per policy and depth limit; ``_success_path.png``:
success against path length).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import logging
import os
import platform as _platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from apps.closed_loop.episode import BACKGROUNDS, GENERIC_BACKGROUND, LoopSettings, Trace, run_episode
from apps.closed_loop.fleet_episode import FLEET_POLICIES, FleetSettings, run_fleet_episode
from apps.closed_loop.metrics import summarize
from apps.closed_loop.missions import LANDMARK_TARGETS, OBJECT_TARGETS, TARGETS, make_mission
from apps.closed_loop.policies import MIN_RAY_Z, POLICIES
from apps.closed_loop.robot import Platform
from apps.closed_loop.sensing import PCA_FITS, SENSORS, EdgeChain, SensorConfig

log = logging.getLogger("rayfronts.eval.search")

#: mission kind -> (default targets, step budget, k)
MISSIONS = {"object": (OBJECT_TARGETS, 40, 1), "landmark": (LANDMARK_TARGETS, 120, 1), "all": (["car"], 60, 3)}
#: mission kind -> the budget is at least this many times the oracle's steps. A landmark
#: 200 m away leaves a fixed 120-step budget no room to look (the oracle itself needs ~100);
#: at twice the oracle's steps RayFronts ended 49-61 m short of the tower on all three
#: development seeds (frontier exploration 190-309 m away), so the budget is three times.
BUDGET_VS_ORACLE = {"landmark": 3.0}


#: the world families of ``--world``
WORLDS = ("synthetic", "pybullet")


def make_world(world: str, seed: int):
    """The world of family ``world`` (:data:`WORLDS`) for ``seed``."""
    if world == "pybullet":
        from synthetic_world.pybullet_world import PybulletWorld

        return PybulletWorld.generate(seed)
    if world == "synthetic":
        from synthetic_world import World

        return World.generate(seed)
    raise ValueError(f"unknown world {world!r}; one of {', '.join(WORLDS)}")


def budget_steps(kind: str, shortest_m: float, step_m: float, scale: float = 1.0) -> int:
    """A mission's step budget: the kind's budget, at least :data:`BUDGET_VS_ORACLE` times
    the oracle tour's steps (``shortest_m / step_m``), times ``scale``."""
    base = float(MISSIONS[kind][1])
    f = BUDGET_VS_ORACLE.get(kind, 0.0)
    if f > 0 and np.isfinite(shortest_m):
        base = max(base, float(np.ceil(f * shortest_m / step_m)))
    return int(round(base * scale))


@dataclass
class SearchEvalConfig:
    """A run of ``rayfronts eval search`` (lengths in metres)."""

    platform: str = "ground"
    depth_limits: list = field(default_factory=lambda: [20.0])
    seeds: list = field(default_factory=lambda: [0])
    episodes: int = 1
    policies: list = field(default_factory=lambda: list(POLICIES))
    missions: list = field(default_factory=lambda: ["object", "landmark"])
    budget_scale: float = 1.0
    resolution: int = 224
    step_m: float = 2.0
    distributed: bool = False      # real mapper and edge processes over Zenoh per episode (LiveMapper)
    work_dir: str = ""             # --distributed: the processes' config files and logs ('' = a temp dir)
    background: str = "generic"    # the searches' background phrases (LoopSettings.background)
    world: str = "synthetic"       # the world family (WORLDS)
    sensor: str = "realistic"      # the depth sensor (SensorConfig.sensor)
    encoder: str = "sim"           # the image encoder (SensorConfig.encoder)
    pca_fit: str = "first_views"   # where the PCA basis comes from (SensorConfig.pca_fit)
    ray_evidence: str = "distinct"  # what ray_z z-scores (LoopSettings.ray_evidence, search.ray_evidence)
    sem_poses_min_z: float | None = None   # sem-poses' margin z cut (None: policies.SEM_POSES_MIN_Z)
    angle_bin_deg: float | None = None     # ray angle bin (None: the preset's; LoopSettings.angle_bin_deg)
    robots: int = 1                # the fleet's size (fleet policies: apps.closed_loop.fleet_episode)
    start: str = "together"        # the fleet's starts (fleet_episode.START_MODES)
    footprint_m: float = 8.0       # least distance between two robots' goals (coordinated, frontier-only)

    def sensor_config(self, seed: int = 0) -> SensorConfig:
        """The closed loop's camera and edge settings of this run (sensor draws seeded by ``seed``)."""
        return SensorConfig(resolution=self.resolution, encoder=self.encoder, sensor=self.sensor,
                            pca_fit=self.pca_fit, sensor_seed=int(seed))

    def loop_settings(self) -> LoopSettings:
        """The settings every episode of this run shares (the depth limit set per episode)."""
        return LoopSettings(platform=self.platform, step_m=self.step_m, background=self.background,
                            ray_evidence=self.ray_evidence, sem_poses_min_z=self.sem_poses_min_z,
                            angle_bin_deg=self.angle_bin_deg)

    def fleet(self) -> FleetSettings:
        """The fleet of the run's fleet policies."""
        return FleetSettings(self.robots, self.start, self.footprint_m)

    def validate(self) -> "SearchEvalConfig":
        bad = [p for p in self.policies if p not in POLICIES and p not in FLEET_POLICIES]
        if bad:
            raise ValueError(f"unknown policies {bad}; choose from {', '.join([*POLICIES, *FLEET_POLICIES])}")
        self.fleet().validate()
        single = [p for p in self.policies if p in POLICIES]
        if self.robots > 1 and single:
            raise ValueError(f"--robots {self.robots}: {', '.join(single)} drive one robot; use the fleet policies "
                             f"{', '.join(FLEET_POLICIES)} (or --robots 1)")
        if self.distributed and any(p in FLEET_POLICIES for p in self.policies):
            raise ValueError("--distributed runs one robot per episode; leave the fleet policies out")
        bad = [m for m in self.missions if m not in MISSIONS]
        if bad:
            raise ValueError(f"unknown missions {bad}; choose from {', '.join(MISSIONS)}")
        if any(d <= 0 for d in self.depth_limits):
            raise ValueError("depth limit 0 is not supported in the closed loop yet: the robot plans on the map's "
                             "occupancy, which a zero-depth map does not have (use 10 and/or 20)")
        Platform.make(self.platform)
        if self.background not in BACKGROUNDS:
            raise ValueError(f"--background must be one of {', '.join(BACKGROUNDS)}, not {self.background!r}")
        if self.angle_bin_deg is not None and not 0 < self.angle_bin_deg <= 360:
            raise ValueError(f"--angle-bin must be in (0, 360] degrees, not {self.angle_bin_deg}")
        if self.ray_evidence not in ("distinct", "margin"):
            raise ValueError(f"--ray-evidence must be distinct or margin, not {self.ray_evidence!r}")
        if self.distributed and self.ray_evidence != "distinct":
            raise ValueError("--distributed: the mapper process keeps its own search.ray_evidence; "
                             "run --ray-evidence margin in process")
        if self.world not in WORLDS:
            raise ValueError(f"--world must be one of {', '.join(WORLDS)}, not {self.world!r}")
        if self.sensor not in SENSORS or self.pca_fit not in PCA_FITS or self.encoder not in ("sim", "label"):
            raise ValueError(f"--sensor must be one of {', '.join(SENSORS)}, --pca-fit one of {', '.join(PCA_FITS)}, "
                             f"--encoder sim or label; got {self.sensor!r}, {self.pca_fit!r}, {self.encoder!r}")
        if self.distributed and (self.world != "synthetic" or self.sensor != "exact"):
            raise ValueError("--distributed: the edge process renders the synthetic world with the exact sensor only; "
                             "add --world synthetic --sensor exact")
        if self.episodes < 1 or self.budget_scale <= 0:
            raise ValueError("--episodes must be >= 1 and the budget scale > 0")
        if self.distributed and "sem-poses" in self.policies:
            raise ValueError("--distributed: sem-poses scores the robot's camera poses in process (the mapper serves "
                             "no pose scores); leave it out with --policies")
        return self


def _summary(rows: list[dict]) -> dict:
    s = summarize(rows)
    s["steps"] = float(np.mean([r["steps"] for r in rows])) if rows else 0.0
    s["cpu_ms_per_step"] = float(np.mean([r["cpu_ms_per_step"] for r in rows])) if rows else 0.0
    s["collisions"] = int(sum(bool(r["collided"]) for r in rows))
    fleet = [r for r in rows if "robots" in r]
    if fleet:     # fleet episodes: time to find (steps) of the successes, coverage duplicated
        s["duplicated_coverage"] = float(np.mean([r["duplicated_coverage"] for r in fleet]))
        s["robots"] = sorted({int(r["robots"]) for r in fleet})
    stages = [r["step_ms_p50"] for r in rows if r.get("step_ms_p50", {}).get("step")]
    if stages:
        s["step_ms_p50"] = {k: float(np.median([x[k] for x in stages])) for k in stages[0]}
    return s


def summarize_policies(rows: list[dict], policies: list[str]) -> dict:
    """Per policy: overall summary, ``by_depth`` and ``by_kind`` (same fields)."""
    out = {}
    for p in policies:
        mine = [r for r in rows if r["policy"] == p]
        s = _summary(mine)
        s["by_depth"] = {str(d): _summary([r for r in mine if r["depth_limit_m"] == d])
                         for d in sorted({r["depth_limit_m"] for r in mine})}
        s["by_kind"] = {k: _summary([r for r in mine if r["kind"] == k]) for k in sorted({r["kind"] for r in mine})}
        out[p] = s
    return out


def _episode(cfg: SearchEvalConfig, world, seed: int, mission, policy: str, settings: LoopSettings, chain: EdgeChain,
             trace: Trace | None) -> dict:
    """One episode, in process or (``cfg.distributed``, map-based policies) with a live mapper
    and edge started for it (:class:`apps.closed_loop.distributed.LiveMapper`)."""
    if policy in FLEET_POLICIES:
        return run_fleet_episode(world, mission, policy, settings, cfg.fleet(), chain)
    method, semantic, _ = POLICIES[policy]
    if not cfg.distributed or method is None:
        return run_episode(world, mission, policy, settings, chain=chain, trace=trace)
    import tempfile

    from apps.closed_loop.distributed import LiveMapper

    mcfg = settings.map_config(method, world, chain.cfg.resolution)
    robot = Platform.make(settings.platform)
    with tempfile.TemporaryDirectory(dir=cfg.work_dir or None) as work, \
            LiveMapper(seed, "default", chain, mcfg, robot.costmap_band(settings.vox_m), settings.window_m,
                       Path(work), semantic=semantic) as live:
        return run_episode(world, mission, policy, settings, chain=chain, mapper=live, trace=trace) | {
            "distributed": True}


def seed_missions(cfg: SearchEvalConfig, world, robot: Platform, seed: int) -> list:
    """``(kind, episode, mission)`` of ``cfg.missions`` on ``world`` (seed ``seed``). Missions are
    drawn from one generator per seed in the fixed order of :data:`MISSIONS` (object,
    landmark, all), kinds not asked for included up to the last one asked for, so a run of
    fewer kinds (``--missions landmark``) replays the same episodes as a run of all."""
    rng = np.random.default_rng(seed)
    wanted = [k for k in MISSIONS if k in cfg.missions]
    out = []
    for kind in list(MISSIONS)[:list(MISSIONS).index(wanted[-1]) + 1] if wanted else []:
        _, budget, k = MISSIONS[kind]
        targets = TARGETS[cfg.world][kind]
        for e in range(cfg.episodes):
            target = targets[e % len(targets)]
            try:
                mission = make_mission(world, robot, kind, target, rng, int(round(budget * cfg.budget_scale)), k=k)
            except ValueError as err:
                if kind in cfg.missions:
                    log.warning("seed %d %s %s: %s", seed, kind, target, err)
                continue
            if kind in cfg.missions:
                out.append((kind, e, dataclasses.replace(mission, budget_steps=budget_steps(
                    kind, mission.shortest_m, cfg.step_m, cfg.budget_scale))))
    return out


def run_search_eval(cfg: SearchEvalConfig, rerun_path: str | None = None, argv: list[str] | None = None,
                    partial_path: str | Path | None = None, trace_dir: str | Path | None = None) -> dict:
    """Run every episode (module docstring); returns the JSON document. ``argv``: the command
    line to record (``meta.argv``). ``partial_path``: after every episode the document so far
    is written there (``"partial": true``, ``meta`` of the run so far: commit, command line,
    machine, load), so a run cut off keeps its finished episodes; removed at the end.
    ``trace_dir``: every single-robot map-based episode's steps are written there as
    :func:`trace_name` (:func:`trace_document`)."""
    from apps.bench.meta import git_commit, run_meta

    cfg.validate()
    settings0 = cfg.loop_settings()
    robot = Platform.make(cfg.platform)
    rows: list[dict] = []
    t0, c0 = time.perf_counter(), time.process_time()
    load0 = os.getloadavg()
    head = git_commit()       # the code that runs, whatever is committed during a long run
    recorded = False
    with run_meta(argv) as meta:
        for seed in cfg.seeds:
            world = make_world(cfg.world, seed)
            missions = seed_missions(cfg, world, robot, seed)
            if not missions:
                continue
            chain = EdgeChain(world, cfg.sensor_config(seed), fit_at=missions[0][2].start)
            for kind, e, mission in missions:
                for depth in cfg.depth_limits:
                    settings = dataclasses.replace(settings0, depth_limit_m=float(depth))
                    for p in cfg.policies:
                        rec = bool(rerun_path) and not recorded and p == "rayfronts"
                        trace = Trace(keep_voxels=rec) if rec or trace_dir else None
                        r = _episode(cfg, world, seed, mission, p, settings, chain, trace)
                        r.update(seed=seed, episode=e, depth_limit_m=float(depth), platform=cfg.platform,
                                 world=cfg.world)
                        rows.append(r)
                        if trace_dir is not None and trace is not None and trace.why:
                            _write_json(Path(trace_dir) / trace_name(r), trace_document(r, trace), indent=None)
                        log.info("seed %d %s %-12s d=%g %-14s success=%s spl=%.2f path=%.0f m steps=%d",
                                 seed, kind, mission.target, depth, p, r["success"], r["spl"], r["path_m"],
                                 r["steps"])
                        if partial_path is not None:
                            _write_json(partial_path, {**_document(cfg, rows, settings0, load0, t0, c0),
                                                       "partial": True, "meta": _meta_so_far(head, argv, load0)})
                        if rec and trace is not None and rerun_path:
                            from apps.closed_loop.recording import record_episode

                            record_episode(rerun_path, world, mission, trace, r)
                            recorded = True
    if partial_path is not None:
        Path(partial_path).unlink(missing_ok=True)
    return {**_document(cfg, rows, settings0, load0, t0, c0), "meta": meta}


def trace_name(row: dict) -> str:
    """The file name of an episode's trace: ``s{seed}_{kind}{episode}_d{depth}_{policy}.json``."""
    return f"s{row['seed']}_{row['kind']}{row['episode']}_d{row['depth_limit_m']:g}_{row['policy']}.json"


def trace_document(row: dict, trace: Trace) -> dict:
    """An episode's trace file: the row's identity and outcome (seed, episode, kind, target,
    depth limit, platform, world, policy, start, success, SPL, path, end) and ``steps``
    (:meth:`apps.closed_loop.episode.Trace.steps`)."""
    keys = ("seed", "episode", "kind", "target", "depth_limit_m", "platform", "world", "policy", "start",
            "success", "spl", "path_m", "steps", "end")
    return {**{k: row[k] for k in keys if k in row}, "trace": trace.steps()}


def _meta_so_far(head: dict, argv: list[str] | None, load0: tuple) -> dict:
    """A partial document's ``meta``: ``head`` (commit and dirty at the start), command line,
    machine, load at start and now, UTC."""
    from apps.bench.meta import loadavg, machine

    return {**head, "argv": argv, "machine": machine(), "load_before": [round(x, 2) for x in load0],
            "load_now": loadavg(), "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def _write_json(path: str | Path, doc: dict, indent: int | None = 2) -> None:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=indent, default=float))
    tmp.replace(p)


def _document(cfg: SearchEvalConfig, rows: list[dict], settings0: LoopSettings, load0: tuple, t0: float,
              c0: float) -> dict:
    """The JSON document of ``rows`` (all but ``meta``)."""
    from apps.closed_loop.seeds import seed_sets

    return {"policies": summarize_policies(rows, cfg.policies),
            "settings": run_settings(cfg, settings0),
            "episodes": rows,
            "seeds": seed_sets(cfg.world, list(cfg.seeds)),
            "machine": {"python": _platform.python_version(), "cpu": _platform.processor() or _platform.machine(),
                        "cores": os.cpu_count(), "load_avg_1_5_15_start": [round(x, 2) for x in load0],
                        "load_avg_1_5_15_end": [round(x, 2) for x in os.getloadavg()]},
            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def run_settings(cfg: SearchEvalConfig, settings0: LoopSettings | None = None) -> dict:
    """The ``settings`` of a run of ``cfg``'s JSON document (``settings0``: its
    :meth:`SearchEvalConfig.loop_settings`, made when not given)."""
    settings0 = settings0 or cfg.loop_settings()
    return {**_settings_fields(cfg), "vox_m": settings0.vox_m, "preset": settings0.preset,
            "min_ray_z": MIN_RAY_Z, "background_phrases": _phrases(settings0),
            "sensor": dataclasses.asdict(cfg.sensor_config()),
            "missions_defined": {k: {"targets": TARGETS[cfg.world][k], "budget_steps": v[1], "k": v[2],
                                     "budget_vs_oracle": BUDGET_VS_ORACLE.get(k, 0.0)}
                                 for k, v in MISSIONS.items()}}


def _settings_fields(cfg: SearchEvalConfig) -> dict:
    """The run's config for the JSON; the fleet's fields only when a fleet policy ran (a
    single-robot run's JSON stays as it was before fleets), ``angle_bin_deg`` only when set
    (a run at the preset's bin stays as it was before the option)."""
    d = dataclasses.asdict(cfg)
    if d.get("angle_bin_deg") is None:
        d.pop("angle_bin_deg", None)
    if not any(p in FLEET_POLICIES for p in cfg.policies):
        for k in ("robots", "start", "footprint_m"):
            d.pop(k)
    return d


def _phrases(settings: LoopSettings) -> list[str] | str:
    """The background phrases of the run for the JSON (``world``: they depend on the world)."""
    if settings.background == "world":
        return "every class of the world but the target"
    if settings.background == "default":
        return "the mapper's search.background"
    if settings.background == "vocabulary":
        return "the generic vocabulary less every class name of the world"
    return list(GENERIC_BACKGROUND)


def table_markdown(doc: dict) -> str:
    """Policy table: success, SPL, path, steps, false finds, CPU per step (overall and per depth)."""
    pols = doc["policies"]
    depths = sorted({d for s in pols.values() for d in s["by_depth"]}, key=float)
    head = "| policy | episodes | success | SPL | " + " | ".join(f"SPL @{d} m" for d in depths) + \
        " | path m | steps | false finds | CPU ms/step |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, s in pols.items():
        per = " | ".join(f"{s['by_depth'][d]['spl']:.2f}" if d in s["by_depth"] else "–" for d in depths)
        lines.append(f"| {name} | {s['episodes']} | {s['success']:.2f} | {s['spl']:.2f} | {per} | {s['path_m']:.0f} | "
                     f"{s['steps']:.0f} | {s['false_finds']} | {s['cpu_ms_per_step']:.0f} |")
    kinds = sorted({k for s in pols.values() for k in s["by_kind"]})
    if len(kinds) > 1:
        lines += ["", "| policy | " + " | ".join(f"{k}: success / SPL" for k in kinds) + " |",
                  "|---|" + "---|" * len(kinds)]
        for name, s in pols.items():
            lines.append(f"| {name} | " + " | ".join(
                f"{s['by_kind'][k]['success']:.2f} / {s['by_kind'][k]['spl']:.2f}" if k in s["by_kind"] else "–"
                for k in kinds) + " |")
    false = [(r, d) for r in doc["episodes"] for d in r.get("declarations", []) if d["verdict"] == "false"]
    if false:
        lines += ["", "False finds (what the declared instance really was: the true object nearest its centroid):",
                  "", "| seed | policy | target | step | declared at (m) | nearest true object | its distance (m) |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {r['seed']} | {r['policy']} | {r['target']} | {d['step']} | "
                  f"({', '.join(f'{v:.0f}' for v in d['centroid'])}) | {d['nearest_class']} #{d['nearest_id']} | "
                  f"{d['nearest_m']:.1f} |" for r, d in false]
    fleet = [r for r in doc["episodes"] if "robots" in r]
    if fleet:
        lines += ["", fleet_table_markdown(fleet)]
    return "\n".join(lines) + "\n"


def fleet_table_markdown(rows: list[dict]) -> str:
    """Per seed, policy and fleet size: found (steps), total path, the finder's SPL, duplicated
    coverage and each robot's path (fleet episode rows)."""
    lines = ["| seed | policy | robots | start | found | steps | total path m | finder SPL | duplicated coverage | "
             "paths m |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        found = "yes" if r["success"] else "no"
        lines.append(f"| {r['seed']} | {r['policy']} | {r['robots']} | {r['start_mode']} | {found} | {r['steps']} | "
                     f"{r['path_m']:.0f} | {r['spl']:.2f} | {r['duplicated_coverage']:.2f} | "
                     + ", ".join(f"{p:.0f}" for p in r["paths_m"]) + " |")
    return "\n".join(lines)


ROW_FIELDS = ["seed", "episode", "platform", "depth_limit_m", "kind", "target", "policy", "success", "spl", "path_m",
              "shortest_m", "steps", "found", "k", "false_finds", "collided", "cpu_ms_per_step", "search_ms_p50"]
#: the CSV's extra columns when the run has fleet episodes
FLEET_ROW_FIELDS = ["robots", "start_mode", "finder", "duplicated_coverage"]


def write_outputs(doc: dict, json_path: str | Path) -> list[Path]:
    """The JSON, ``.md`` table, ``.csv`` rows and two plots next to it."""
    p = Path(json_path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(doc, indent=2, default=float))
    md, cs = p.with_suffix(".md"), p.with_suffix(".csv")
    md.write_text(table_markdown(doc))
    with cs.open("w", newline="") as f:
        fleet = any("robots" in r for r in doc["episodes"])
        w = csv.DictWriter(f, fieldnames=ROW_FIELDS + (FLEET_ROW_FIELDS if fleet else []), extrasaction="ignore")
        w.writeheader()
        w.writerows(doc["episodes"])
    return [p, md, cs, *_plots(doc, p)]


def _plots(doc: dict, p: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pols = doc["policies"]
    depths = sorted({d for s in pols.values() for d in s["by_depth"]}, key=float)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    width = 0.8 / max(1, len(depths))
    for j, d in enumerate(depths):
        ax.bar(np.arange(len(pols)) + j * width, [s["by_depth"].get(d, {}).get("spl", 0.0) for s in pols.values()],
               width, label=f"depth limit {d} m")
    ax.set_xticks(np.arange(len(pols)) + width * (len(depths) - 1) / 2, list(pols))
    ax.set_ylabel("SPL")
    ax.set_ylim(0, 1)
    ax.legend()
    fig.tight_layout()
    a = p.with_name(p.stem + "_spl.png")
    fig.savefig(a, dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for i, name in enumerate(pols):       # successes at 1, failures at 0, policies offset a little
        rows = [r for r in doc["episodes"] if r["policy"] == name]
        ax.scatter([r["path_m"] for r in rows], [float(r["success"]) + 0.03 * (i - len(pols) / 2) for r in rows],
                   label=name, s=14)
    ax.set_xlabel("path length (m)")
    ax.set_ylabel("success")
    ax.legend(fontsize=7)
    fig.tight_layout()
    b = p.with_name(p.stem + "_success_path.png")
    fig.savefig(b, dpi=110)
    plt.close(fig)
    return [a, b]
