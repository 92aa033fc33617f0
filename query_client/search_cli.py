"""``rayfronts search car``: search for planners (found instances, where to look next, what
lies beyond the map). World frame, metres, z up; headings in radians from +x."""
from __future__ import annotations

import argparse

HELP = "search for planners: found instances, look-next goals, rays beyond the map"
DESCRIPTION = """Ask the mapper where TARGETs are: instances found in the map (stable ids,
centroid, box, confidence), exploration goals where the semantic rays point toward them
(position, heading, score, unknown volume gained), and rays / triangulated estimates
beyond the mapped range. Scores are softmax probabilities over targets + background.

  rayfronts search car --json
  rayfronts search car bench --area 0,0,40,40 --z-band 0,3 --from 1,2,1.5
  rayfronts search "street lamp" --background road building --threshold 0.6 --watch
  rayfronts search car --fleet r1,r2,r3 --json      (one goal per robot, shared found list)"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from common.zenoh_session import add_zenoh_arguments

    parser.add_argument("targets", nargs="+", metavar="TARGET", help="what to look for (one or more phrases)")
    parser.add_argument("--background", nargs="+", default=None, metavar="PHRASE",
                        help="phrases the targets compete with (default: the mapper's search.background)")
    parser.add_argument("--area", default=None, metavar="x0,y0,x1,y1",
                        help="search box, or a polygon x0,y0,x1,y1,x2,y2,... (>= 3 vertices)")
    parser.add_argument("--z-band", default=None, metavar="z0,z1", help="height band (m)")
    parser.add_argument("--threshold", type=float, default=0.5, help="probability a voxel needs, in (0, 1)")
    parser.add_argument("--max-instances", type=int, default=10, help="instances reported (default 10)")
    parser.add_argument("--max-goals", type=int, default=None,
                        help="look-next goals reported (default 5); with --fleet the candidates shared out "
                             "(default 20)")
    parser.add_argument("--from", dest="from_xyz", default=None, metavar="x,y,z", help="the robot's position")
    parser.add_argument("--fleet", default=None, metavar="r1,r2,...",
                        help="fleet search: one goal per robot (distinct regions), shared found list; robot ids, "
                             "or 'all' for every robot present (docs/fleet.md)")
    parser.add_argument("--target-count", type=int, default=1,
                        help="with --fleet: instances of each target after which the others stop being sent "
                             "toward it (default 1)")
    parser.add_argument("--footprint", type=float, default=0.0, metavar="M",
                        help="with --fleet: least distance between two robots' goals, m (default: the mapper's "
                             "search.fleet_footprint_m)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--watch", action="store_true", help="standing search: print each refresh until Ctrl-C")
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds to wait for the mapper (default 20)")
    parser.add_argument("--prefix", default=None, help="key-space prefix (default rayfronts)")
    add_zenoh_arguments(parser, mode_default_help="client")


def search_kwargs(args: argparse.Namespace) -> dict:
    """Client.search keyword arguments from the command line (ConfigError for bad input)."""
    from common.config import ConfigError
    from query_client.vocabulary import search_fields

    if args.timeout <= 0:
        raise ConfigError(f"--timeout must be > 0 seconds (got {args.timeout})")
    if args.fleet is not None:
        from query_client.vocabulary import fleet_fields

        return fleet_fields(args.fleet, args.targets, target_count=args.target_count, footprint_m=args.footprint,
                            from_xyz=args.from_xyz, max_goals=args.max_goals, background=args.background,
                            threshold=args.threshold, max_instances=args.max_instances, area=args.area,
                            z_band=args.z_band)
    kw = search_fields(args.targets, background=args.background, threshold=args.threshold,
                       max_instances=args.max_instances, max_goals=5 if args.max_goals is None else args.max_goals,
                       area=args.area, z_band=args.z_band, from_xyz=args.from_xyz)
    return kw


def format_reply(r) -> str:
    """Human-readable summary of a :class:`common.search_messages.SearchReply`."""
    lines = [f"search ({r.frames_mapped} frames mapped, map version {r.map_version}, "
             f"{r.timings_ms.get('total', 0.0):.0f} ms)"]
    lines.append(f"  found: {len(r.found)}")
    for i in r.found:
        c = i["centroid"]
        lines.append(f"    #{i['id']!s:<4} {i['target']:<16s} p={i['confidence']:.3f} ({c[0]:7.2f}, {c[1]:7.2f}, "
                     f"{c[2]:5.2f})  {i['voxels']} voxels, seen {i['observations']}x")
    lines.append(f"  look next: {len(r.look_next)}")
    for g in r.look_next:
        p = g["position"]
        lines.append(f"    ({p[0]:7.2f}, {p[1]:7.2f}, {p[2]:5.2f}) heading {g['heading_rad']:+.2f} rad  "
                     f"score {g['score']:.3f}  gain {g['gain_m3']:.1f} m³  {g['distance_m']:.1f} m  "
                     f"{g['target'] or '-'}")
    b = r.beyond
    lines.append(f"  beyond: {len(b.get('rays', []))} rays, {len(b.get('estimates', []))} estimates, "
                 f"search volume {b.get('search_volume_m3', 0.0):,.0f} m³")
    for e in b.get("estimates", [])[:5]:
        p = e["position"]
        lines.append(f"    estimate {e['target']}: ({p[0]:7.2f}, {p[1]:7.2f}, {p[2]:5.2f}) ± {e['radius_m']:.1f} m "
                     f"score {e['score']:.3f}")
    return "\n".join(lines)


def format_fleet_reply(r) -> str:
    """Human-readable summary of a :class:`common.fleet_messages.FleetSearchReply`."""
    lines = [f"fleet search ({r.frames_mapped} frames mapped, map version {r.map_version}, "
             f"{r.timings_ms.get('total', 0.0):.0f} ms, {r.method}, footprint {r.footprint_m:.1f} m, "
             f"{len(r.candidates)} candidates)"]
    for robot in sorted(r.goals):
        info, g = r.robots.get(robot, {}), r.goals[robot]
        if g is None:
            lines.append(f"  {robot:<12s} {info.get('state', '?')}")
            continue
        p = g["position"]
        lines.append(f"  {robot:<12s} goal ({p[0]:7.2f}, {p[1]:7.2f}, {p[2]:5.2f}) heading {g['heading_rad']:+.2f} "
                     f"rad  score {g['score']:.3f}  gain {g['gain_m3']:.1f} m³  {g['distance_m']:.1f} m  "
                     f"{g['target'] or '-'}")
    lines.append(f"  found (shared): {len(r.found)}")
    for i in r.found:
        c = i["centroid"]
        lines.append(f"    #{i['id']!s:<4} {i['target']:<16s} p={i['confidence']:.3f} ({c[0]:7.2f}, {c[1]:7.2f}, "
                     f"{c[2]:5.2f})")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from query_client.cli import with_client

    kw = search_kwargs(args)
    return with_client(args, "search", lambda client: _search(args, client, kw))


def _search(args: argparse.Namespace, client, kw: dict) -> int:
    from query_client.cli import warn_missing, watch_until_signal
    from query_client.vocabulary import search_reply_text

    if args.fleet is not None:
        return _fleet(args, client, kw)
    if args.watch:
        def show(r) -> None:
            warn_missing(r, "search")
            print(search_reply_text(r) if args.json else format_reply(r) + "\n", flush=True)

        watch_until_signal(lambda: client.watch_search(args.targets, show, timeout=args.timeout, **kw))
        return 0
    r = client.search(args.targets, timeout=args.timeout, **kw)
    warn_missing(r, "search")
    print(search_reply_text(r) if args.json else format_reply(r))
    return 0


def _fleet(args: argparse.Namespace, client, kw: dict) -> int:
    from query_client.cli import warn_missing, watch_until_signal
    from query_client.vocabulary import fleet_reply_text

    def show(r) -> None:
        warn_missing(r, "search")
        print(fleet_reply_text(r) if args.json else format_fleet_reply(r) + ("\n" if args.watch else ""), flush=True)

    if args.watch:
        watch_until_signal(lambda: client.watch_fleet_search(args.targets, show, timeout=args.timeout, **kw))
        return 0
    show(client.fleet_search(args.targets, timeout=args.timeout, **kw))
    return 0
