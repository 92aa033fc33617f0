"""Import layers (ARCHITECTURE.md, ``ALLOWED`` below): ``common`` imports only itself; the
libraries ``semantic_map``, ``synthetic_world`` and ``encoders`` import ``common`` (``encoders``
also ``synthetic_world``); ``planning`` imports ``common`` and ``semantic_map``; the roles
``edge``, ``mapper`` and ``query_client`` import ``common``, the libraries they need and
themselves, never another role; ``apps`` may import anything. And no import cycles between our modules.

Every import statement counts: module level, inside functions (lazy imports), under
``if TYPE_CHECKING``, and ``importlib.import_module("literal")``. Read from the source with
``ast`` (nothing is imported), so a forbidden lazy import fails here even if no test runs it.
"""
from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "semantic_map", "planning", "synthetic_world", "encoders", "edge", "mapper", "query_client",
            "apps")
ALLOWED = {
    "common": {"common"},
    "semantic_map": {"common", "semantic_map"},
    "planning": {"common", "semantic_map", "planning"},
    "synthetic_world": {"common", "synthetic_world"},
    "encoders": {"common", "synthetic_world", "encoders"},
    "edge": {"common", "synthetic_world", "encoders", "edge"},
    "mapper": {"common", "semantic_map", "planning", "encoders", "mapper"},
    "query_client": {"common", "query_client"},
    "apps": set(PACKAGES),
}


#: compiled extension modules (no Python source: they import nothing of ours)
EXTENSIONS = {"semantic_map._rfkernels": "semantic_map/csrc/rfkernels.cpp",
              "semantic_map._vdbocc": "semantic_map/csrc/vdbocc.cpp"}


def _modules() -> dict[str, Path]:
    """Dotted name → file of every module of our packages."""
    out = {name: ROOT / src for name, src in EXTENSIONS.items()}
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            rel = p.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def _resolve(name: str, modules: dict) -> str | None:
    """The longest prefix of ``name`` that is one of our modules (None: not ours)."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        cand = ".".join(parts[:i])
        if cand in modules:
            return cand
    return None


def _imports(mod: str, path: Path, modules: dict) -> list[tuple[str, int, str]]:
    """``(target module, line, statement text)`` for every import of ours in one module."""
    src = path.read_text()
    tree = ast.parse(src, filename=str(path))
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            # ``from pkg import sub`` imports the submodule when there is one
            names = [f"{stem}.{a.name}" if f"{stem}.{a.name}" in modules else stem for a in node.names]
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
              and (getattr(node.func, "attr", None) or getattr(node.func, "id", None)) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            names = [node.args[0].value]
        for n in names:
            target = _resolve(n, modules)
            if target is not None and target != mod:
                out.append((target, node.lineno, ast.get_source_segment(src, node) or n))
    return out


@functools.lru_cache(maxsize=1)
def _graph() -> tuple[dict, dict]:
    modules = _modules()
    edges = {m: ([] if m in EXTENSIONS else _imports(m, p, modules)) for m, p in modules.items()}
    return modules, edges


def test_every_package_has_modules():
    modules = _modules()
    for pkg in PACKAGES:
        assert sum(1 for m in modules if m.split(".")[0] == pkg) >= 2, pkg


def test_no_forbidden_import_arrows():
    modules, edges = _graph()
    bad = []
    for mod, imps in edges.items():
        layer = mod.split(".")[0]
        for target, line, text in imps:
            if target.split(".")[0] not in ALLOWED[layer]:
                bad.append(f"{modules[mod].relative_to(ROOT)}:{line}: {layer} -> {target}: {text.splitlines()[0]}")
    assert not bad, "forbidden imports (see ARCHITECTURE.md):\n" + "\n".join(sorted(bad))


def _cycles(edges: dict) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    graph = {m: sorted({t for t, _, _ in imps}) for m, imps in edges.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(graph[root]))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(graph.get(w, ()))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on_stack.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_cycles():
    modules, edges = _graph()
    cycles = _cycles(edges)
    lines = []
    for comp in cycles:
        lines.append("cycle: " + " <-> ".join(comp))
        members = set(comp)
        for m in comp:
            for target, line, _text in edges[m]:
                if target in members:
                    lines.append(f"    {modules[m].relative_to(ROOT)}:{line}: -> {target}")
    assert not cycles, "import cycles (module-level or lazy):\n" + "\n".join(lines)


def test_planning_sees_the_map_only_through_its_package_api():
    """``planning`` imports the map as ``semantic_map`` (``RayFrontsMap``, ``MapConfig``), never
    one of the map's modules: the map's parts stay the map's business."""
    modules, edges = _graph()
    bad = [f"{modules[m].relative_to(ROOT)}:{line}: {text.splitlines()[0]}"
           for m, imps in edges.items() if m.split(".")[0] == "planning"
           for target, line, text in imps if target.startswith("semantic_map.")]
    assert not bad, "planning reaches into the map's modules:\n" + "\n".join(bad)


def test_checker_sees_lazy_forbidden_imports_and_cycles(tmp_path):
    """The checker itself: a lazy forbidden import and a two-module lazy cycle are found."""
    modules = {"common.a": tmp_path / "a.py", "common.b": tmp_path / "b.py", "mapper.x": tmp_path / "x.py"}
    modules["common.a"].write_text("def f():\n    from mapper.x import g\n    import common.b\n")
    modules["common.b"].write_text("import importlib\n\ndef h():\n    importlib.import_module('common.a')\n")
    modules["mapper.x"].write_text("from . import y\nimport numpy\n")
    edges = {m: _imports(m, p, modules) for m, p in modules.items()}
    assert [t for t, _, _ in edges["common.a"]] == ["mapper.x", "common.b"]
    assert [t for t, _, _ in edges["common.b"]] == ["common.a"]
    assert edges["mapper.x"] == []            # ``mapper.y`` is not a module here, numpy not ours
    assert _cycles(edges) == [["common.a", "common.b"]]


# The pure map: computation only. Its own modules, and every module of ours they reach, import
# none of these (ARCHITECTURE.md, "The pure map").
PURE_PACKAGES = ("semantic_map", "planning")
PURE_MAP_FORBIDDEN = {"zenoh", "msgpack", "rerun", "threading", "concurrent", "multiprocessing", "socket",
                      "asyncio", "subprocess", "json", "pickle", "shutil", "psutil", "cv2"}


def _external_imports(path: Path) -> set[str]:
    """Top-level names of every module an ``import`` statement in ``path`` names (ours or not)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_pure_map_imports_no_io_transport_or_threads():
    modules, edges = _graph()
    reach = [m for m in modules if m.split(".")[0] in PURE_PACKAGES]
    seen = set(reach)
    while reach:  # every module of ours the pure map reaches, lazily or not
        m = reach.pop()
        for target, _, _ in edges[m]:
            if target not in seen:
                seen.add(target)
                reach.append(target)
    assert {m.split(".")[0] for m in seen} <= {*PURE_PACKAGES, "common"}
    bad = {m: sorted(_external_imports(modules[m]) & PURE_MAP_FORBIDDEN) for m in sorted(seen) if m not in EXTENSIONS}
    bad = {m: v for m, v in bad.items() if v}
    assert not bad, f"the pure map reaches I/O, transport or threads: {bad}"


def test_pure_map_loads_without_transport():
    """Importing every module of the pure map loads no Zenoh, msgpack or rerun (checked in a fresh
    interpreter: torch itself starts threads, so only our own imports are held to 'no threading')."""
    import subprocess
    import sys

    mods = [m for m in _modules() if m.split(".")[0] in PURE_PACKAGES and m not in EXTENSIONS]
    code = ("import importlib, sys\n"
            f"for m in {mods!r}: importlib.import_module(m)\n"
            "print(sorted(n for n in ('zenoh', 'msgpack', 'rerun') if n in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout
    from semantic_map import RayFrontsMap  # the package's public entry
    assert RayFrontsMap.__module__ == "semantic_map.map"
