#!/usr/bin/env python3
"""Generate the Zenoh ``access_control`` block of a RayFronts site (Zenoh 1.10 ACL).

    python3 deploy/acl/make_acl.py --robot r1 --robot r2 --operator alice --operator console -o acl.json5

Default deny. Subjects are identified by TLS certificate common names (the names
``deploy/certs/make_certs.sh`` issues: ``robot-<id>``, ``operator-<name>``, ``mapper``), or by
usernames of user/password authentication (``--auth usrpwd``), or both (``--auth both``:
separate subjects, either identification grants the rights). The router (``rayfronts router``
or the mapper in router mode) applies it to every transport; its own local entities are
not filtered. "ingress" = messages a subject sends to the router, "egress" = messages the
router forwards to the subject. A rule matches a message when one of its key expressions
*includes* the message's key expression (Zenoh's ACL looks the key up with "nodes including
it"), so a declaration or a query with a wider key than allowed (``rayfronts/**``, or
``.../robots/*/...`` where one robot is allowed) is refused whole: ask on the exact keys.
Keys: docs/key_space.md. ``<p>`` is the prefix (``--prefix``).

* ``robot-<id>`` — an edge, and the robot's onboard planner (``Client(robot="<id>")``):

  - publishes only its own data: put ``<p>/robots/<id>/frames`` (and its tile keys
    ``frames/*``) and ``<p>/robots/<id>/edge_status``; the liveliness token
    ``<p>/robots/<id>/alive``; serves (declare_queryable + reply) its ``feature_space`` and
    ``edge_status``. It receives the mapper's queries of those and the subscriptions to its
    frames and status (egress query / declare_subscriber: the mapper declares
    ``<p>/robots/*/frames``, ``.../frames/<tile>`` and ``.../edge_status`` for all robots at
    once; a declaration carries no data, and without it the edge's wait for a subscriber
    (Zenoh matching status) would never end and its frames would be replaced unsent).
  - asks the mapper for its OWN searches and occupancy: query
    ``<p>/mapper/robots/<id>/search`` and ``<p>/mapper/robots/<id>/occupancy`` (and gets the
    replies), and reports its own unreachable fleet goals on ``<p>/mapper/robots/<id>/unreachable``;
    subscribes to its standing searches' results ``<p>/mapper/robots/<id>/searches/*``, to its
    goal in the fleet searches ``<p>/mapper/robots/<id>/fleet_goal`` and to the mapper's status of
    it, ``<p>/mapper/robots/<id>/status``. Another robot's searches and goals, and the operators'
    ``<p>/mapper/search`` / ``fleet_search`` / ``query`` / ``stats``, are refused.
  - reads ``<p>/mapper/feature_space`` (an edge adopting the map's PCA basis) and the
    shards' routing announcements ``<p>/mapper/shards/*/routing`` (an edge sends each frame
    only to the shards that own it, on ``<p>/robots/<id>/frames/s.<a>.<b>.``, covered by
    ``frames/*``; docs/key_space.md#shards).
  - watches (liveliness subscriber / query) ``<p>/mapper/alive`` and the shards'
    ``<p>/mapper/shards/*``.
  - nothing else: no put under another robot's prefix or under ``<p>/mapper/**``.
* ``operator-<name>`` — a laptop, a planner off the robot, the console's process
  (``rayfronts console`` runs with an operator certificate, e.g. ``operator-console``):

  - query ``<p>/mapper/{query,stats,snapshot,search,occupancy,feature_space,fleet_search}`` and
    the layers ``<p>/mapper/layers/*`` (``Client.layer``), and get the replies;
  - subscribe to standing query results ``<p>/mapper/queries/**``, standing search results
    ``<p>/mapper/searches/**``, standing fleet search results ``<p>/mapper/fleet_searches/**``
    and the layers ``<p>/mapper/layers/**``;
  - watch and query the liveliness of robots ``<p>/robots/*/alive``, the mapper
    ``<p>/mapper/alive`` and the shards ``<p>/mapper/shards/*``.
  - It cannot publish or serve anything, so it cannot inject frames or pose as the mapper.
    Setting a robot's ``world_from_robot`` is left to the mapper identity (an admin task).
* ``mapper``: everything under ``<p>/**`` (it is the only one that serves/publishes
  ``<p>/mapper/**``).

The output is JSON (valid JSON5). Use it with ``rayfronts router --acl FILE`` /
``zenoh.acl_file`` (or paste it as ``access_control`` into a router config). Standard
library only: runs on any machine with Python 3.
"""
from __future__ import annotations

import argparse
import json
import re
import sys

#: the message kinds Zenoh 1.10 access control filters (all of them).
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]
_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_PREFIX = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_WATCH = ["declare_liveliness_subscriber", "liveliness_query"]


def _rule(rid: str, messages: list[str], flows: list[str], keys: list[str]) -> dict:
    return {"id": rid, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": keys}


def _subjects(sid: str, names: list[str], auth: str) -> list[dict]:
    out = []
    if auth in ("tls", "both"):
        out.append({"id": sid if auth == "tls" else f"{sid}_cert", "cert_common_names": names})
    if auth in ("usrpwd", "both"):
        out.append({"id": sid if auth == "usrpwd" else f"{sid}_user", "usernames": names})
    return out


def _robot_rules(p: str, r: str) -> list[dict]:
    """The rules of robot ``r`` alone (module docstring), all confined to keys naming ``r``."""
    root, mine = f"{p}/robots/{r}", f"{p}/mapper/robots/{r}"
    frames = [f"{root}/frames", f"{root}/frames/*"]
    served = [f"{root}/feature_space", f"{root}/edge_status"]
    planner = [f"{mine}/search", f"{mine}/occupancy", f"{mine}/unreachable"]
    results = [f"{mine}/searches/*", f"{mine}/status", f"{mine}/fleet_goal"]
    return [
        _rule(f"robot_{r}_publish", ["put"], ["ingress"], [*frames, f"{root}/edge_status"]),
        _rule(f"robot_{r}_alive", ["liveliness_token"], ["ingress"], [f"{root}/alive"]),
        _rule(f"robot_{r}_serve", ["declare_queryable", "reply"], ["ingress"], served),
        _rule(f"robot_{r}_receive_query", ["query"], ["egress"], served),
        _rule(f"robot_{r}_ask", ["query"], ["ingress"], planner),
        _rule(f"robot_{r}_receive_answer", ["reply"], ["egress"], planner),
        _rule(f"robot_{r}_subscribe", ["declare_subscriber"], ["ingress"], results),
        _rule(f"robot_{r}_receive_results", ["put", "delete"], ["egress"], results),
    ]


def _robots_shared(p: str) -> list[dict]:
    """Rules every robot has: watch the mapper and its shards, read the map's feature space and
    the shards' routing announcements, learn of the subscriptions to robots' frames and status."""
    watched = [f"{p}/mapper/alive", f"{p}/mapper/shards/*"]
    space = [f"{p}/mapper/feature_space", f"{p}/mapper/shards/*/routing"]   # read-only, shared
    return [
        _rule("robots_watch_mapper_in", _WATCH, ["ingress"], watched),
        _rule("robots_watch_mapper_out", ["liveliness_token"], ["egress"], watched),
        _rule("robots_read_feature_space_in", ["query"], ["ingress"], space),
        _rule("robots_read_feature_space_out", ["reply"], ["egress"], space),
        # the mapper's (and shards') subscriptions: robots/*/frames, robots/*/frames/<tile>, robots/*/edge_status
        _rule("robots_receive_subscriptions", ["declare_subscriber"], ["egress"],
              [f"{p}/robots/*/frames", f"{p}/robots/*/frames/*", f"{p}/robots/*/edge_status"]),
    ]


def _operator_rules(p: str) -> list[dict]:
    """The operators' rules (module docstring)."""
    services = [f"{p}/mapper/{s}" for s in ("query", "stats", "snapshot", "search", "occupancy", "feature_space",
                                            "fleet_search")]
    services.append(f"{p}/mapper/layers/*")
    results = [f"{p}/mapper/queries/**", f"{p}/mapper/searches/**", f"{p}/mapper/fleet_searches/**",
               f"{p}/mapper/layers/**"]
    alive = [f"{p}/robots/*/alive", f"{p}/mapper/alive", f"{p}/mapper/shards/*"]
    return [
        _rule("operator_query", ["query"], ["ingress"], services),
        _rule("operator_receive_reply", ["reply", "declare_queryable"], ["egress"], services),
        _rule("operator_subscribe", ["declare_subscriber"], ["ingress"], results),
        _rule("operator_receive_results", ["put", "delete"], ["egress"], results),
        _rule("operator_watch", _WATCH, ["ingress"], alive),
        _rule("operator_receive_liveliness", ["liveliness_token"], ["egress"], alive),
    ]


def make_acl(robots: list[str], operators: list[str] | None = None, prefix: str = "rayfronts",
             auth: str = "tls", mapper_name: str = "mapper", enabled: bool = True) -> dict:
    """The ``access_control`` object (a dict) for ``robots`` and ``operators``.

    Identity names: ``robot-<id>``, ``operator-<name>`` and ``mapper_name``. ``auth`` is
    ``tls`` (certificate common names), ``usrpwd`` (usernames) or ``both``.
    """
    operators = list(operators or [])
    if auth not in ("tls", "usrpwd", "both"):
        raise ValueError(f"auth must be tls, usrpwd or both, got {auth!r}")
    if not _PREFIX.match(prefix):
        raise ValueError(f"invalid key prefix {prefix!r}")
    for what, names in (("robot id", robots), ("operator name", operators)):
        for n in names:
            if not isinstance(n, str) or not _ID.match(n):
                raise ValueError(f"invalid {what} {n!r}: use 1-64 characters from [A-Za-z0-9_-]")
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate {what}s in {names}")
    p = prefix
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []

    # -- mapper: the trusted service of the site
    rules.append(_rule("mapper_all", ALL_MESSAGES, ["ingress", "egress"], [f"{p}/**"]))
    subjects += _subjects("mapper", [mapper_name], auth)
    policies.append({"id": "mapper", "rules": ["mapper_all"], "subjects": [s["id"] for s in subjects]})

    # -- robots: one set of rules per robot, confined to keys that name it
    shared = _robots_shared(p) if robots else []
    rules += shared
    for r in robots:
        own = _robot_rules(p, r)
        rules += own
        subs = _subjects(f"robot_{r}", [f"robot-{r}"], auth)
        subjects += subs
        policies.append({"id": f"robot_{r}", "rules": [x["id"] for x in own + shared],
                         "subjects": [s["id"] for s in subs]})

    # -- operators (and the console): ask the mapper, watch results, layers and liveliness
    if operators:
        ops = _operator_rules(p)
        rules += ops
        subs = _subjects("operators", [f"operator-{o}" for o in operators], auth)
        subjects += subs
        policies.append({"id": "operators", "rules": [x["id"] for x in ops], "subjects": [s["id"] for s in subs]})

    return {"enabled": bool(enabled), "default_permission": "deny",
            "rules": rules, "subjects": subjects, "policies": policies}


def render(acl: dict, argv: list[str] | None = None) -> str:
    head = "// RayFronts access_control block (Zenoh 1.10), generated by deploy/acl/make_acl.py"
    if argv is not None:
        head += "\n// args: " + " ".join(argv)
    return head + "\n" + json.dumps(acl, indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", action="append", default=[], help="robot id (repeatable): CN robot-<id>")
    ap.add_argument("--operator", action="append", default=[], help="operator name (repeatable): CN operator-<name>")
    ap.add_argument("--prefix", default="rayfronts", help="key-space prefix (default rayfronts)")
    ap.add_argument("--auth", choices=["tls", "usrpwd", "both"], default="tls",
                    help="identify subjects by TLS cert common names, usrpwd usernames, or both")
    ap.add_argument("--mapper-name", default="mapper", help="identity of the mapper (CN / username)")
    ap.add_argument("-o", "--out", default="-", help="output file (default stdout)")
    a = ap.parse_args(argv)
    try:
        acl = make_acl(a.robot, a.operator, a.prefix, a.auth, a.mapper_name)
    except ValueError as e:
        print(f"make_acl.py: {e}", file=sys.stderr)
        return 2
    text = render(acl, argv)
    if a.out == "-":
        sys.stdout.write(text)
    else:
        with open(a.out, "w") as f:
            f.write(text)
        print(f"[acl] wrote {a.out} ({len(a.robot)} robots, {len(a.operator)} operators)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
