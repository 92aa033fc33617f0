"""What ``make typecheck`` (and so CI) checks: every package of ours, bodies of unannotated
functions included. Read from pyproject.toml, the Makefile and .ci/run (mypy itself runs in CI)."""
from __future__ import annotations

import re
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _our_packages() -> set[str]:
    """Top-level directories that are Python packages of ours (not the tests)."""
    return {p.parent.name for p in ROOT.glob("*/__init__.py") if p.parent.name != "tests"}


def test_mypy_config_covers_every_package_with_check_untyped_defs():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    pkgs = _our_packages()
    assert len(pkgs) >= 9, pkgs                            # common, semantic_map, planning, ... apps
    files = set(cfg["files"])
    assert files == pkgs, f"mypy files {sorted(files)} vs packages {sorted(pkgs)}"
    assert cfg.get("check_untyped_defs") is True


def test_make_typecheck_runs_the_configured_scope_and_ci_runs_it():
    make = (ROOT / "Makefile").read_text()
    recipe = re.search(r"^typecheck:.*\n((?:\t.*\n)+)", make, re.M)
    assert recipe is not None, "Makefile has no typecheck target"
    cmds = [c.strip() for c in recipe.group(1).splitlines()]
    assert len(cmds) == 1 and cmds[0].endswith("-m mypy"), cmds   # no paths: [tool.mypy] files decide
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert "make typecheck" in [line.strip() for line in ci]
