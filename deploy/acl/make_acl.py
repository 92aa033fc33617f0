#!/usr/bin/env python3
"""Generate the Zenoh ``access_control`` block of a RayFronts site (Zenoh 1.10 ACL).

    python3 deploy/acl/make_acl.py --robot r1 --robot r2 --operator alice -o acl.json5

Default deny. Subjects are identified by TLS certificate common names (the names
``deploy/certs/make_certs.sh`` issues: ``robot-<id>``, ``operator-<name>``, ``mapper``), or by
usernames of user/password authentication (``--auth usrpwd``), or both (``--auth both``:
separate subjects, either identification grants the rights). The router (``rayfronts router``
or the mapper in router mode) applies it to every transport; its own local entities are
not filtered. "ingress" = messages a subject sends to the router, "egress" = messages the
router forwards to the subject.

* ``robot-<id>`` may: put ``<p>/robots/<id>/frames`` (and its tile keys ``frames/*``); declare the liveliness token
  ``<p>/robots/<id>/alive``; declare a queryable on and reply to
  ``<p>/robots/<id>/feature_space``; watch ``<p>/mapper/alive``. It receives the queries for
  its feature space and the subscriptions to its frames. Nothing under another robot's
  prefix, nothing under ``<p>/mapper/**``.
* ``operator-*`` may: query ``<p>/mapper/{query,stats,snapshot}`` (and get the replies);
  subscribe to ``<p>/mapper/queries/**`` and ``<p>/mapper/layers/**``; watch and query the
  liveliness of ``<p>/robots/*/alive`` and ``<p>/mapper/alive``. It cannot publish or serve.
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


def _rule(rid: str, messages: list[str], flows: list[str], keys: list[str]) -> dict:
    return {"id": rid, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": keys}


def _subjects(sid: str, names: list[str], auth: str) -> list[dict]:
    out = []
    if auth in ("tls", "both"):
        out.append({"id": sid if auth == "tls" else f"{sid}_cert", "cert_common_names": names})
    if auth in ("usrpwd", "both"):
        out.append({"id": sid if auth == "usrpwd" else f"{sid}_user", "usernames": names})
    return out


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
    mapper_alive = f"{p}/mapper/alive"
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []

    # -- mapper: the trusted service of the site
    rules.append(_rule("mapper_all", ALL_MESSAGES, ["ingress", "egress"], [f"{p}/**"]))
    subjects += _subjects("mapper", [mapper_name], auth)
    policies.append({"id": "mapper", "rules": ["mapper_all"], "subjects": [s["id"] for s in subjects]})

    # -- robots: one set of rules per robot, confined to its own key prefix
    if robots:
        rules.append(_rule("robots_watch_mapper_in", ["declare_liveliness_subscriber", "liveliness_query"],
                           ["ingress"], [mapper_alive]))
        rules.append(_rule("robots_watch_mapper_out", ["liveliness_token"], ["egress"], [mapper_alive]))
    for r in robots:
        root = f"{p}/robots/{r}"
        ids = [f"robot_{r}_publish", f"robot_{r}_alive", f"robot_{r}_serve", f"robot_{r}_receive_query",
               f"robot_{r}_receive_subscription"]
        rules += [
            _rule(ids[0], ["put"], ["ingress"], [f"{root}/frames", f"{root}/frames/*"]),
            _rule(ids[1], ["liveliness_token"], ["ingress"], [f"{root}/alive"]),
            _rule(ids[2], ["declare_queryable", "reply"], ["ingress"], [f"{root}/feature_space"]),
            _rule(ids[3], ["query"], ["egress"], [f"{root}/feature_space"]),
            _rule(ids[4], ["declare_subscriber"], ["egress"], [f"{root}/frames", f"{root}/frames/*"]),
        ]
        subs = _subjects(f"robot_{r}", [f"robot-{r}"], auth)
        subjects += subs
        policies.append({"id": f"robot_{r}", "rules": ids + ["robots_watch_mapper_in", "robots_watch_mapper_out"],
                         "subjects": [s["id"] for s in subs]})

    # -- operators: query the mapper, watch results, layers and liveliness
    if operators:
        services = [f"{p}/mapper/query", f"{p}/mapper/stats", f"{p}/mapper/snapshot"]
        results = [f"{p}/mapper/queries/**", f"{p}/mapper/layers/**"]
        alive = [f"{p}/robots/*/alive", mapper_alive]
        ids = ["operator_query", "operator_receive_reply", "operator_subscribe", "operator_receive_results",
               "operator_watch", "operator_receive_liveliness"]
        rules += [
            _rule(ids[0], ["query"], ["ingress"], services),
            _rule(ids[1], ["reply", "declare_queryable"], ["egress"], services),
            _rule(ids[2], ["declare_subscriber"], ["ingress"], results),
            _rule(ids[3], ["put", "delete"], ["egress"], results),
            _rule(ids[4], ["declare_liveliness_subscriber", "liveliness_query"], ["ingress"], alive),
            _rule(ids[5], ["liveliness_token"], ["egress"], alive),
        ]
        subs = _subjects("operators", [f"operator-{o}" for o in operators], auth)
        subjects += subs
        policies.append({"id": "operators", "rules": ids, "subjects": [s["id"] for s in subs]})

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
