#!/usr/bin/env python3
"""Fail CI when a test was skipped that tests/ci_skip_allowlist.txt does not allow.

    python .ci/check_skips.py JUNIT_XML [ALLOWLIST]

Reads pytest's JUnit XML (``--junitxml``), prints every skip with its reason, and exits 1
if any skip is not matched by an allow-list entry ``<node id glob> | <reason substring> |
<always | not-root>`` (``not-root``: allowed only when not running as root), or if the XML
holds no test at all. Standard library only."""
from __future__ import annotations

import fnmatch
import os
import sys
import xml.etree.ElementTree as ET


def load_allowlist(path: str) -> list[tuple[str, str, str]]:
    out = []
    for n, line in enumerate(open(path, encoding="utf-8"), 1):
        line = line.split("#", 1)[0].strip() if not line.lstrip().startswith("#") else ""
        if not line:
            continue
        parts = [p.strip() for p in line.split("|")]
        if len(parts) != 3 or parts[2] not in ("always", "not-root"):
            raise SystemExit(f"{path}:{n}: expected '<glob> | <reason text> | always|not-root', got {line!r}")
        out.append((parts[0], parts[1], parts[2]))
    return out


def node_id(case: ET.Element) -> str:
    """tests/test_x.py::test_name[param] from a JUnit testcase (classname tests.test_x)."""
    cls = case.get("classname", "")
    parts = cls.split(".")
    # pytest writes classname "tests.test_x" or "tests.test_x.TestClass"
    path_parts = [p for p in parts if not (p[:1].isupper())]
    klass = [p for p in parts if p[:1].isupper()]
    nid = "/".join(path_parts) + ".py"
    if klass:
        nid += "::" + "::".join(klass)
    return f"{nid}::{case.get('name', '')}"


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    xml_path = argv[1]
    allow_path = argv[2] if len(argv) > 2 else os.path.join(os.path.dirname(__file__), "..", "tests",
                                                             "ci_skip_allowlist.txt")
    allow = load_allowlist(allow_path)
    root_user = hasattr(os, "geteuid") and os.geteuid() == 0
    cases = list(ET.parse(xml_path).getroot().iter("testcase"))
    if not cases:
        print(f"check_skips: {xml_path} holds no test cases", file=sys.stderr)
        return 1
    bad, ok = [], []
    for c in cases:
        sk = c.find("skipped")
        if sk is None:
            continue
        reason = (sk.get("message") or "") + " " + (sk.text or "")
        nid = node_id(c)
        hit = any(fnmatch.fnmatch(nid, g) and r in reason and (w == "always" or not root_user) for g, r, w in allow)
        (ok if hit else bad).append((nid, reason.strip()))
    for nid, r in ok:
        print(f"allowed skip: {nid}: {r}")
    for nid, r in bad:
        print(f"NOT ALLOWED skip: {nid}: {r}", file=sys.stderr)
    print(f"check_skips: {len(cases)} tests, {len(ok)} allowed skips, {len(bad)} not allowed")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
