"""``rayfronts eval``: the paper's benchmarks.

    rayfronts eval srchvol --source synthetic --seed 0 --frames 300 --depth-limit 0,10,20 --out runs/sv
    rayfronts eval semseg  --source tartanair --source-path /data/tartanair --scene Factory --out runs/ss
    rayfronts eval report  runs/sv runs/ss --out results.md
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from apps.evaluation.semseg import SemsegConfig
    from apps.evaluation.srchvol import SrchvolConfig

HELP = "the paper's benchmarks (search volume; 3D semantic segmentation) and a results page"
DESCRIPTION = """Benchmarks of the paper, run on this machine:

  srchvol  online search-volume benchmark (Table I): SCV, Recall, SCVR and mIoU AUCs per
           method (RayFronts, Semantic Poses, Semantic Voxels, Spherical / Unidirectional
           Semantic Frontiers) and depth limit; writes summary.json, table.md, steps.csv/json,
           plots/*.png.
  semseg   offline zero-shot 3D semantic segmentation (Tables II/III): mIoU, f-mIoU, Acc with and
           without background classes; writes summary.json.
  report   collect run directories into one Markdown page.
  search   closed-loop search: a simulated robot finds targets guided by each policy
           (rayfronts, frontier, unidirectional, spherical, sem-poses, oracle); success,
           SPL, path, false finds; writes --json FILE plus .md, .csv and plots beside it.
  tune-sem-poses  choose sem-poses' margin z cut on the development seeds (best far-target
           SPL); writes --json FILE.
  merge    one search table (or tune-sem-poses result) from runs split by seed or policy.
  fleet-compare  fleets of N robots against one robot on the same missions (steps, path,
           the fewest steps any fleet could take, issue 44's aim); writes --json FILE.
  landmarks  where each far-landmark episode started and ended against the target and its
           look-alike (distances, bearings, finds when the look-alike was nearer).

srchvol/semseg take --config FILE and trailing key=value overrides of their config (keys
listed with 'rayfronts eval srchvol --help')."""

log = logging.getLogger("rayfronts.eval")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", default=None, help="YAML config file")
    p.add_argument("--source", default=None, help="source kind: synthetic | replica | scannet | tartanair | recording")
    p.add_argument("--source-path", default=None, help="dataset root / scene directory (source.path)")
    p.add_argument("--scene", default=None, help="dataset scene (source.scene)")
    p.add_argument("--sequence", default=None, help="TartanAir trajectory, e.g. P0000 (source.sequence)")
    p.add_argument("--seed", type=int, default=None, help="synthetic world seed (source.seed)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (synthetic n_frames / max_frames)")
    p.add_argument("--resolution", default=None, help="frame size HxW (source.resolution)")
    p.add_argument("--frame-skip", type=int, default=None, help="keep every (n+1)-th frame (source.frame_skip)")
    p.add_argument("--vox", type=float, default=None, help="voxel size in metres")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--encoder", default=None, choices=["label", "sim", "naradio"],
                   help="image encoder (encoder.kind): label = exact class embeddings, sim = simulated ViT "
                        "(patch grid, bleeding, confusion, noise), naradio = the real model")
    p.add_argument("--templates", default=None, choices=["auto", "on", "off"],
                   help="class texts: 80 prompt templates (on), raw names (off), auto = on for language "
                        "encoders (naradio), off for label/sim (default auto)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.config import describe

    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    from apps.evaluation.semseg import SemsegConfig
    from apps.evaluation.srchvol import ALL_METHODS, SrchvolConfig

    sv = sub.add_parser("srchvol", help="online search-volume benchmark (Table I)",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        epilog="config keys:\n" + describe(SrchvolConfig))
    _common(sv)
    sv.add_argument("--depth-limit", action="append", default=None, metavar="D",
                    help="depth limit(s) in metres, repeatable or comma list (default 0,10,20)")
    sv.add_argument("--methods", default=None, help=f"comma list of methods (default all: {','.join(ALL_METHODS)})")
    sv.add_argument("--every", type=int, default=None, help="evaluate every K frames (default 10)")
    sv.add_argument("--preset", default=None, help="map preset (default 'online')")
    sv.add_argument("--cone-shape", choices=["true", "reference"], default=None,
                    help="true cones (default) or the reference's hexagonal pyramids (to reproduce the paper)")

    ss = sub.add_parser("semseg", help="offline 3D semantic segmentation (Tables II/III)",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        epilog="config keys:\n" + describe(SemsegConfig))
    _common(ss)
    ss.add_argument("--k", type=int, default=None, help="kNN alignment k (0 = exact grid; default 5)")

    _search_parser(sub)

    rp = sub.add_parser("report", help="collect run directories into one Markdown page")
    rp.add_argument("runs", nargs="+", metavar="RUN_DIR", help="srchvol / semseg output directories")
    rp.add_argument("--out", required=True, metavar="FILE.md",
                    help="Markdown file to write (plots are linked relatively)")
    rp.add_argument("--title", default="RayFronts benchmark results", help="page title")


def _search_parser(sub) -> None:
    se = sub.add_parser("search", help="closed-loop search episodes per policy (success, SPL)",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        description=__import__("apps.closed_loop.evaluate", fromlist=["x"]).__doc__)
    _loop_options(se, "0", "object,landmark")
    se.add_argument("--json", required=True, metavar="FILE", help="summary + episode rows (.md/.csv/.png beside)")
    se.add_argument("--rerun", default=None, metavar="FILE.rrd", help="record the first rayfronts episode")
    se.add_argument("--trace", default=None, metavar="DIR",
                    help="write each single-robot map-based episode's steps (position, decision, goal, strongest "
                         "rays, found instances) to DIR/s<seed>_<kind><episode>_d<depth>_<policy>.json")
    se.add_argument("--distributed", action="store_true",
                    help="run each map-based episode with real mapper and edge processes over loopback Zenoh (the "
                         "edge renders the robot's views; this process plans through Client.search and the "
                         "occupancy queries); slower, same maps; needs --sensor exact (synthetic world)")
    se.add_argument("--work-dir", default="", metavar="DIR",
                    help="--distributed: where the processes' configs and logs go (default: a temp dir, removed)")
    se.add_argument("--robots", type=int, default=1, metavar="N",
                    help="robots searching together on one shared map (default 1: the single-robot loop); with N > 1 "
                         "the policies are the fleet's: coordinated, uncoordinated, frontier-only")
    se.add_argument("--start", choices=["together", "spread"], default="together",
                    help="the fleet's starts: next to each other at the mission start (default) or spread out 12 m")
    se.add_argument("--footprint", type=float, default=8.0, metavar="M",
                    help="least distance (m) between two robots' goals, coordinated and frontier-only (default 8)")
    mg = sub.add_parser("merge", help="one eval search table from runs split by seed or policy",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        description=__import__("apps.closed_loop.merge", fromlist=["x"]).__doc__)
    mg.add_argument("parts", nargs="+", metavar="PART.json",
                    help="eval search JSON files of the same settings (or tune-sem-poses files: one tuning)")
    mg.add_argument("--json", required=True, metavar="FILE", help="the merged document (.md/.csv/.png beside)")
    mg.add_argument("--allow-partial", action="store_true", help="accept FILE.partial.json parts (marked partial)")
    fc = sub.add_parser("fleet-compare", help="fleets of N robots against one robot on the same missions",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        description=__import__("apps.closed_loop.fleet_compare", fromlist=["x"]).__doc__)
    fc.add_argument("runs", nargs="+", metavar="RUN.json",
                    help="eval search JSON files: the --robots 1 rayfronts run and the fleet runs")
    fc.add_argument("--json", required=True, metavar="FILE", help="the comparison (.md beside)")
    lm = sub.add_parser("landmarks", help="landmark episodes' starts and ends against the target and its look-alike",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        description=__import__("apps.closed_loop.landmark_report", fromlist=["x"]).__doc__)
    lm.add_argument("runs", nargs="+", metavar="RUN.json", help="eval search JSON files (merged or not)")
    lm.add_argument("--near", type=float, default=30.0, metavar="M",
                    help="a failure ending within M m of a look-alike counts as ended by it (default 30)")
    lm.add_argument("--json", default=None, metavar="FILE", help="also write the report (.md beside)")
    lm.add_argument("--traces", default=None, metavar="DIR",
                    help="the runs' --trace directory: count the steps whose strongest ray points at each landmark")
    tu = sub.add_parser("tune-sem-poses", help="choose sem-poses' margin z cut on the development seeds",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        description=__import__("apps.closed_loop.tuning", fromlist=["x"]).__doc__)
    _loop_options(tu, "dev", "landmark,object")
    tu.add_argument("--cuts", default="5,4,3.5,3,2.5,2",
                    help="candidate z cuts, comma list, run in this order (default 5,4,3.5,3,2.5,2)")
    tu.add_argument("--json", required=True, metavar="FILE", help="per-cut summaries and the choice")
    tu.add_argument("--resume", default=None, metavar="PARTIAL.json",
                    help="go on from a run cut off (its FILE.partial.json, same settings): its episodes count as run")


def _loop_options(se: argparse.ArgumentParser, seeds: str, missions: str) -> None:
    """The closed loop's options shared by ``search`` and ``tune-sem-poses``."""
    from apps.closed_loop.episode import BACKGROUNDS
    from apps.closed_loop.evaluate import MISSIONS, WORLDS
    from apps.closed_loop.policies import POLICIES
    from apps.closed_loop.sensing import PCA_FITS, SENSORS

    se.add_argument("--world", choices=list(WORLDS), default="synthetic",
                    help="world family: the procedural town or scenes of pybullet_data assets (default synthetic)")
    se.add_argument("--platform", choices=["ground", "drone"], default="ground", help="robot (default ground)")
    se.add_argument("--depth-limit", action="append", default=None, metavar="D",
                    help="depth limit(s) in metres, repeatable or comma list (default 20)")
    se.add_argument("--seeds", default=seeds,
                    help=f"world seeds, comma list or A-B range, or dev / held-out (default {seeds})")
    se.add_argument("--episodes", type=int, default=1, help="missions per seed and mission kind (default 1)")
    se.add_argument("--policies", default=None,
                    help=f"comma list (default all: {','.join(POLICIES)}; with --distributed all but sem-poses)")
    se.add_argument("--missions", default=missions,
                    help=f"comma list of mission kinds: {', '.join(MISSIONS)} (default {missions})")
    se.add_argument("--budget-scale", type=float, default=1.0, help="scale the step budgets (default 1)")
    se.add_argument("--background", choices=list(BACKGROUNDS), default="generic",
                    help="the searches' background phrases: a fixed generic list (default), the generic vocabulary "
                         "less the world's class names, every class of the world but the target, or the mapper's "
                         "search.background")
    se.add_argument("--sensor", choices=list(SENSORS), default="realistic",
                    help="depth sensor: range, noise and dropouts like a real one (default) or the exact depth")
    se.add_argument("--encoder", choices=["sim", "label"], default="sim",
                    help="image encoder: simulated ViT-like features (default) or the exact labels")
    se.add_argument("--pca-fit", choices=list(PCA_FITS), default="first_views",
                    help="PCA basis: the robot's first views (default), a generic vocabulary's text embeddings "
                         "without the world's class names, or views plus one cell per world class")
    se.add_argument("--ray-evidence", choices=["distinct", "margin"], default="distinct",
                    help="what the ray policies' ray_z z-scores: a ray's cosine to what sets the target apart from "
                         "its nearest other phrases (default) or its margin over their best (search.ray_evidence)")
    se.add_argument("--sem-poses-min-z", type=float, default=None, metavar="Z",
                    help="sem-poses' margin z cut (default: policies.SEM_POSES_MIN_Z)")
    se.add_argument("--angle-bin", type=float, default=None, metavar="DEG",
                    help="the ray policies' ray angle bin in degrees (default: the online preset's 30, the paper's; "
                         "one bin per frontier stays one bin)")
    se.add_argument("--resolution", type=int, default=224, help="square image size in pixels (default 224)")
    se.add_argument("--step", type=float, default=2.0, help="metres the robot moves per step at most (default 2)")


def _seeds(text: str, world: str = "synthetic") -> list[int]:
    from apps.closed_loop.seeds import DEVELOPMENT_SEEDS, HELD_OUT_SEEDS

    if text.strip() in ("dev", "held-out"):
        return list((DEVELOPMENT_SEEDS if text.strip() == "dev" else HELD_OUT_SEEDS)[world])
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part[1:]:
            a, b = part.split("-", 1)
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def _search_config(args: argparse.Namespace):
    from apps.closed_loop.evaluate import SearchEvalConfig
    from apps.closed_loop.policies import POLICIES

    distributed = bool(getattr(args, "distributed", False))
    depths = [float(x) for a in (args.depth_limit or ["20"]) for x in a.split(",") if x.strip()]
    robots = int(getattr(args, "robots", 1))
    if args.policies is None and robots > 1:
        from apps.closed_loop.fleet_episode import FLEET_POLICIES

        policies = list(FLEET_POLICIES)
    elif args.policies is None:
        policies = [p for p in POLICIES if not (distributed and p == "sem-poses")]
    else:
        policies = [p.strip() for p in args.policies.split(",") if p.strip()]
    return SearchEvalConfig(platform=args.platform, depth_limits=depths, seeds=_seeds(args.seeds, args.world),
                            episodes=args.episodes, policies=policies,
                            missions=[m.strip() for m in args.missions.split(",") if m.strip()],
                            budget_scale=args.budget_scale, resolution=args.resolution, step_m=args.step,
                            distributed=distributed, work_dir=getattr(args, "work_dir", ""),
                            background=args.background, world=args.world, sensor=args.sensor,
                            encoder=args.encoder, pca_fit=args.pca_fit, ray_evidence=args.ray_evidence,
                            sem_poses_min_z=args.sem_poses_min_z, angle_bin_deg=args.angle_bin, robots=robots,
                            start=getattr(args, "start", "together"),
                            footprint_m=float(getattr(args, "footprint", 8.0))).validate()


def partial_json(json_path: str) -> str:
    """Where a run writes its finished episodes as it goes (``FILE.partial.json`` beside
    ``--json FILE``; removed when the run ends)."""
    return str(Path(json_path).with_suffix(".partial.json"))


def _run_search(args: argparse.Namespace) -> int:
    from apps.closed_loop.evaluate import run_search_eval, table_markdown, write_outputs

    cfg = _search_config(args)
    doc = run_search_eval(cfg, args.rerun, argv=["rayfronts", *sys.argv[1:]], partial_path=partial_json(args.json),
                          trace_dir=args.trace)
    paths = write_outputs(doc, args.json)
    print(table_markdown(doc))
    print("wrote " + ", ".join(str(p) for p in paths) + (f", {args.rerun}" if args.rerun else ""))
    return 0


def _read_documents(paths: list[str], action: str) -> list[dict] | None:
    """The JSON documents at ``paths``; None (after one line on stderr naming the file) when
    one cannot be read."""
    docs = []
    for p in paths:
        try:
            docs.append(json.loads(Path(p).read_text()))
        except (OSError, ValueError) as e:
            print(f"rayfronts eval {action}: cannot read {p}: {e}", file=sys.stderr)
            return None
    return docs


def _run_merge(args: argparse.Namespace) -> int:
    from apps.closed_loop.evaluate import table_markdown, write_outputs
    from apps.closed_loop.merge import merge_documents

    docs = _read_documents(args.parts, "merge")
    if docs is None:
        return 2
    if all(isinstance(d, dict) and "procedure" in d for d in docs):
        return _merge_tunings(docs, args.json)
    try:
        doc = merge_documents(docs, allow_partial=args.allow_partial)
    except ValueError as e:
        print(f"rayfronts eval merge: {e}", file=sys.stderr)
        return 2
    paths = write_outputs(doc, args.json)
    print(table_markdown(doc))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _merge_tunings(docs: list[dict], out: str) -> int:
    from apps.closed_loop.evaluate import _write_json
    from apps.closed_loop.tuning import far_target, merge_tunings

    try:
        doc = merge_tunings(docs)
    except ValueError as e:
        print(f"rayfronts eval merge: {e}", file=sys.stderr)
        return 2
    _write_json(out, doc)
    for c, s in doc["cuts"].items():
        far = far_target(s)
        print(f"cut {c}: far-target SPL {far['spl']:.3f}, success {far['success']:.2f}")
    print(f"seeds through every cut: {doc['seeds_complete']}; chosen cut {doc.get('chosen')}; wrote {out}")
    return 0


def _run_fleet_compare(args: argparse.Namespace) -> int:
    from apps.closed_loop.fleet_compare import compare_fleets, compare_markdown

    docs = _read_documents(args.runs, "fleet-compare")
    if docs is None:
        return 2
    try:
        doc = compare_fleets(docs)
    except (ValueError, KeyError, TypeError) as e:
        print(f"rayfronts eval fleet-compare: {e}", file=sys.stderr)
        return 2
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2, default=float))
    md = compare_markdown(doc)
    out.with_suffix(".md").write_text(md)
    print(md + f"wrote {out}, {out.with_suffix('.md')}")
    return 0


def _run_landmarks(args: argparse.Namespace) -> int:
    from apps.closed_loop.landmark_report import landmark_report, report_markdown

    docs = _read_documents(args.runs, "landmarks")
    if docs is None:
        return 2
    try:
        rep = landmark_report(docs, near_m=args.near, traces=args.traces)
    except (ValueError, KeyError, TypeError) as e:
        print(f"rayfronts eval landmarks: {e}", file=sys.stderr)
        return 2
    md = report_markdown(rep)
    print(md, end="")
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rep, indent=2))
        out.with_suffix(".md").write_text(md)
        print(f"wrote {out}, {out.with_suffix('.md')}")
    return 0


def _run_tune(args: argparse.Namespace) -> int:
    from apps.closed_loop.evaluate import _write_json
    from apps.closed_loop.tuning import tune_sem_poses

    cfg = _search_config(args)
    cuts = [float(x) for x in args.cuts.split(",") if x.strip()]
    resume = None
    if args.resume:
        try:
            resume = json.loads(Path(args.resume).read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"--resume {args.resume}: not JSON ({e})") from None
    doc = tune_sem_poses(cfg, cuts, argv=["rayfronts", *sys.argv[1:]], partial_path=partial_json(args.json),
                         resume=resume)
    _write_json(args.json, doc)
    print(f"chosen sem-poses cut: {doc['chosen']} (far-target SPL {doc['chosen_spl']:.3f}); wrote {args.json}")
    return 0


#: command-line option -> SourceConfig key
_SOURCE_OPTIONS = {"source": "kind", "source_path": "path", "scene": "scene", "sequence": "sequence",
                   "seed": "seed", "resolution": "resolution", "frame_skip": "frame_skip"}


def _source_overrides(args) -> dict:
    s = {key: getattr(args, opt) for opt, key in _SOURCE_OPTIONS.items() if getattr(args, opt) is not None}
    if args.frames is not None:
        kind = args.source or "synthetic"
        s["n_frames" if kind == "synthetic" else "max_frames"] = args.frames
    return s


def build_config(args: argparse.Namespace) -> SrchvolConfig | SemsegConfig:
    """The action's config from --config, the options and the key=value overrides."""
    from apps.evaluation.semseg import SemsegConfig
    from apps.evaluation.srchvol import SrchvolConfig
    from common.config import load_config, merge

    schema: type[SrchvolConfig | SemsegConfig] = SrchvolConfig if args.action == "srchvol" else SemsegConfig
    cfg = load_config(schema, args.config, ())
    data: dict = {}
    src = _source_overrides(args)
    if src:
        data["source"] = src
    if args.vox is not None:
        data["vox"] = args.vox
    if args.encoder is not None:
        data["encoder"] = {"kind": args.encoder}
    if args.templates is not None:
        data["templates"] = {"on": True, "off": False}.get(args.templates, args.templates)
    if args.no_progress:
        data["progress"] = False
    if args.action == "srchvol":
        if args.depth_limit:
            data["depth_limits"] = [float(x) for a in args.depth_limit for x in a.split(",") if x.strip()]
        if args.methods:
            data["methods"] = [m.strip() for m in args.methods.split(",") if m.strip()]
        if args.every is not None:
            data["every"] = args.every
        if args.preset is not None:
            data["preset"] = args.preset
        if args.cone_shape is not None:
            data["cone_shape"] = args.cone_shape
    else:
        if args.k is not None:
            data["k"] = args.k
    cfg = merge(cfg, data)
    from common.config import parse_override
    for item in args.overrides or ():
        cfg = merge(cfg, parse_override(item))
    return cfg.validate()


def run(args: argparse.Namespace) -> int:
    from common.config import ConfigError

    try:
        if args.action == "report":
            from apps.evaluation.report import write_report
            path = write_report(args.runs, args.out, title=args.title)
            print(f"wrote {path}")
            return 0
        if args.action == "search":
            return _run_search(args)
        if args.action == "merge":
            return _run_merge(args)
        if args.action == "fleet-compare":
            return _run_fleet_compare(args)
        if args.action == "tune-sem-poses":
            return _run_tune(args)
        if args.action == "landmarks":
            return _run_landmarks(args)
        cfg = build_config(args)
        if args.action == "srchvol":
            from apps.evaluation.srchvol import SrchvolConfig, run_srchvol
            assert isinstance(cfg, SrchvolConfig)
            run_srchvol(cfg, args.out)
            print((__import__("pathlib").Path(args.out) / "table.md").read_text())
        else:
            from apps.evaluation.semseg import SemsegConfig, run_semseg
            assert isinstance(cfg, SemsegConfig)
            s = run_semseg(cfg, args.out)
            print(json.dumps({k: v for k, v in s.items() if k != "per_class"}, indent=2))
        return 0
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"rayfronts eval {args.action}: {e}", file=sys.stderr)
        return 2
