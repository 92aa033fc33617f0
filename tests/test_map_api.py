"""The map's methods are its only door: no code outside ``semantic_map/`` touches its parts.

The rule (issue 45): every module of ours outside ``semantic_map/`` — the packages, the apps,
``benchmarks/`` scripts and the tests — reaches a :class:`semantic_map.RayFrontsMap` through its
public methods only (``voxels``, ``frontiers``, ``rays``, ``voxel_xyz``, ``ray_geometry``,
``occupancy_view``, ``stats``, ``export_state`` / ``from_state`` ...). Its parts — the
occupancy grid, the semantic voxels, the frontier table, the ray store, the budget generator,
the schedule counters and every private attribute — are the map's own. The exceptions are the
white-box tests in :data:`WHITE_BOX_TESTS`, whose subject is a part itself (each with its
reason).

The check is by name, as the AST says it: any attribute access ``<expr>.<name>`` (and
``getattr`` / ``setattr`` / ``hasattr`` / ``delattr`` with a literal name) whose name is one of
the map's parts (:data:`PARTS`, and the private names read from ``RayFrontsMap``'s own source)
is a reach-in, whatever ``<expr>`` is — except on ``self`` / ``cls`` (a class's own attribute
of that name; no class outside ``semantic_map/`` is a map) and the unrelated attributes of
:data:`UNRELATED`, which happen to share a name with a part.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAP_SOURCE = ROOT / "semantic_map" / "map.py"

#: the map's public-named parts (instance attributes that are the map's inside)
PARTS = frozenset({"occupancy", "sem", "fronts", "ray_store", "generator", "counters", "last_fov_deg",
                   "timings_total"})
#: the map's public fields: plain values anyone may read (a new attribute must be one or the other)
PUBLIC_FIELDS = frozenset({"cfg", "feature_dim", "feature_space", "device", "occupancy_backend", "timings"})
#: (receiver as written, attribute): unrelated attributes that share a part's name
UNRELATED = {
    ("semantic_map", "occupancy"): "the subpackage semantic_map.occupancy (module attribute)",
    ("self.search", "occupancy"): "SearchServer.occupancy, the occupancy request handler",
    ("self.encoder", "generator"): "the simulated encoder's noise generator (apps/closed_loop/sensing.py)",
}
#: tests whose subject is one of the map's parts: they may reach in (file name: why)
WHITE_BOX_TESTS = {
    "test_fidelity.py": "the paper's ray rules, checked on the ray store and frontier table themselves",
    "test_mapper_incremental.py": "swaps the ray store for the reference store and compares them",
    "test_mapper_semantic.py": "drives the semantic prune with planted occupancy values and its pending keys",
    "test_query_half.py": "plants extreme feature rows in the voxel table to test the float16 copy's range",
    "test_map_api.py": "this file (its planted example)",
}
#: ``getattr``-like builtins whose literal second argument is an attribute name
_ATTR_FUNCS = frozenset({"getattr", "setattr", "hasattr", "delattr"})
_SKIP_DIRS = frozenset({"semantic_map", "build", "node_modules", "__pycache__"})


def _map_class() -> ast.ClassDef:
    tree = ast.parse(MAP_SOURCE.read_text())
    return next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "RayFrontsMap")


def _instance_attributes(cls: ast.ClassDef) -> set[str]:
    """Names assigned as ``self.<name>`` anywhere in the class."""
    out = set()
    for node in ast.walk(cls):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign)):
            targets = [node.target]
        for t in targets:
            for sub in ast.walk(t):
                if isinstance(sub, ast.Attribute) and isinstance(sub.value, ast.Name) and sub.value.id == "self":
                    out.add(sub.attr)
    return out


def private_names() -> frozenset[str]:
    """The map's private attributes and methods, read from its source."""
    cls = _map_class()
    methods = {n.name for n in cls.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    names = _instance_attributes(cls) | methods
    return frozenset(n for n in names if n.startswith("_") and not n.startswith("__"))


def reach_ins(path: Path, forbidden: frozenset[str]) -> list[str]:
    """``path:line: <expr>.<name>`` for every access of a forbidden name in one file, by line."""
    tree = ast.parse(path.read_text(), str(path))
    hits: dict[tuple[int, str], None] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr in forbidden:
            recv, name = ast.unparse(node.value), node.attr
            shown = f"{recv}.{name}"
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _ATTR_FUNCS
              and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
              and node.args[1].value in forbidden):
            recv, name = ast.unparse(node.args[0]), str(node.args[1].value)
            shown = f"{node.func.id}({recv}, {name!r})"
        else:
            continue
        if recv not in ("self", "cls") and (recv, name) not in UNRELATED:
            hits[(node.lineno, shown)] = None
    return [f"{path}:{line}: {shown}" for line, shown in sorted(hits)]


def _checked_files() -> list[Path]:
    out = []
    for p in sorted(ROOT.rglob("*.py")):
        rel = p.relative_to(ROOT)
        if any(part.startswith(".") or part in _SKIP_DIRS for part in rel.parts[:-1]):
            continue
        if rel.parts[0] == "tests" and len(rel.parts) == 2 and rel.name in WHITE_BOX_TESTS:
            continue
        out.append(p)
    return out


def test_nothing_outside_the_map_touches_its_parts():
    files = _checked_files()
    # there is something to check: the packages, apps, tests and the modules that use the map most
    tops = {p.relative_to(ROOT).parts[0] for p in files}
    assert {"common", "planning", "encoders", "synthetic_world", "edge", "mapper", "query_client", "apps",
            "tests"} <= tops, tops
    names = {p.relative_to(ROOT).as_posix() for p in files}
    assert {"mapper/snapshot.py", "mapper/search_answer.py", "apps/bench/mapper.py",
            "apps/export/__init__.py"} <= names
    forbidden = PARTS | private_names()
    bad = [hit for p in files for hit in reach_ins(p, forbidden)]
    assert not bad, ("the map's parts are touched outside semantic_map/ (use RayFrontsMap's methods):\n"
                     + "\n".join(bad))


def test_every_attribute_of_the_map_is_a_part_or_a_public_field():
    """A new attribute of ``RayFrontsMap`` is either one of its parts (held by the check above)
    or a public field: adding one makes its author decide."""
    attrs = _instance_attributes(_map_class())
    private = private_names()
    assert PARTS <= attrs, PARTS - attrs                 # every listed part still exists
    assert {"_buf_occ", "_buf_sem", "_buf_rays", "_pending_prune", "_rng_state_source"} <= private
    assert not attrs - PARTS - PUBLIC_FIELDS - private, attrs - PARTS - PUBLIC_FIELDS - private


def test_white_box_tests_exist_and_still_reach_in():
    """The exceptions stay few and true: each listed test exists and does reach in (one that no
    longer does leaves the list)."""
    forbidden = PARTS | private_names()
    for name in WHITE_BOX_TESTS:
        path = ROOT / "tests" / name
        assert path.is_file(), name
        assert name == "test_map_api.py" or reach_ins(path, forbidden), f"{name} no longer reaches in"


def test_the_check_catches_a_planted_reach_in(tmp_path):
    """The checker itself: reach-ins through any expression and through getattr are found; a
    class's own attribute and the listed unrelated names are not."""
    src = tmp_path / "planted.py"
    src.write_text(
        "def f(m, st, self):\n"
        "    a = m.occupancy.query(x)\n"                    # 2
        "    b = st.map.ray_store\n"                        # 3
        "    c = getattr(m, 'sem')\n"                       # 4
        "    st.map._buf_occ.append(1)\n"                   # 5
        "    m.counters['frames'] += 1\n"                   # 6
        "    self.generator = 1\n"                          # 7: its own attribute
        "    self.search.occupancy(b)\n"                    # 8: unrelated (SearchServer)
        "    m.occupancy_view().query(x)\n"                 # 9: the API
        "    other.fronts\n"                                # 10
        "    return m._tick\n")                             # 11
    hits = reach_ins(src, PARTS | private_names())
    assert [int(h.split(":")[1]) for h in hits] == [2, 3, 4, 5, 6, 10, 11], hits
    assert "_tick" in private_names() and "_buf_occ" in private_names()
