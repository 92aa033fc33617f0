"""The design documents live in ``docs/`` and every citation points there.

* No file of the repository cites a design document outside it (the old external design
  page by section, or a path under a shared work directory).
* Every ``docs/<name>.md`` a file mentions exists (anchors are not checked).
* Every relative link of README.md, ARCHITECTURE.md, CONTRIBUTING.md and ``docs/**/*.md``
  resolves to an existing path, and a link's ``#anchor`` into one of those pages names one
  of its headings (GitHub's heading ids).
* The README stays short enough to read in ten minutes (at most 400 lines).
* ARCHITECTURE.md is the complete module map: it names every folder that holds Python
  modules (``mapper/outputs/``) and every module at the top of a wheel package
  (``mapper/state.py``) by its path from the repository root.

Files: what ``git ls-files`` lists plus untracked files git does not ignore (so a new file
is checked before it is committed); without git, the source tree minus build outputs.
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# Built from pieces so that neither this file nor a grep for the names matches itself.
_NAME = "DES" + "IGN"
_EXTERNAL = re.compile("|".join([
    _NAME + r"(?:\.md)?\s*" + "\u00a7",      # the old external design page cited by section
    _NAME + r"\.md",
    "/work" + "/shared",
    "shared" + "/" + _NAME,
]))
_DOC_REF = re.compile(r"(?<![\w./-])docs/([A-Za-z0-9_-]+\.md)")
_MD_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
_SKIP_DIRS = {".git", ".venv", "build", "out", "__pycache__", ".pytest_cache", ".ruff_cache"}


def _files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                             cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
        names = sorted({n for n in out.decode().split("\0") if n})
        return [ROOT / n for n in names if (ROOT / n).is_file()]
    except (OSError, subprocess.SubprocessError):
        return [p for p in sorted(ROOT.rglob("*"))
                if p.is_file() and not _SKIP_DIRS.intersection(p.relative_to(ROOT).parts)]


def _text(p: Path) -> str | None:
    data = p.read_bytes()
    if b"\0" in data[:8192]:
        return None   # binary
    return data.decode("utf-8", errors="replace")


def _hits(pattern: re.Pattern) -> list[tuple[str, int, str]]:
    out = []
    for p in _files():
        text = _text(p)
        if text is None:
            continue
        for m in pattern.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            out.append((str(p.relative_to(ROOT)), line, m.group(0)))
    return out


def test_docs_exist():
    for name in ("README.md", "conventions.md", "key_space.md", "messages.md", "commands.md",
                 "snapshot_format.md", "synthetic_world.md", "models.md", "method.md"):
        assert (DOCS / name).is_file(), f"docs/{name} is missing"


def test_no_external_design_citations():
    hits = _hits(_EXTERNAL)
    assert not hits, "cite docs/ instead of an external document:\n" + "\n".join(
        f"  {f}:{line}: {s}" for f, line, s in hits)


def test_cited_docs_exist():
    missing = [(f, line, s) for f, line, s in _hits(_DOC_REF) if not (DOCS / s[len("docs/"):]).is_file()]
    assert not missing, "citations of docs/ pages that do not exist:\n" + "\n".join(
        f"  {f}:{line}: {s}" for f, line, s in missing)


README_MAX_LINES = 400
_FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.S | re.M)
_ANCHOR_LINK = re.compile(r"\]\(([^)\s]*)#([^)\s]+)\)")
_HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t]*#*[ \t]*$", re.M)


def _pages() -> list[Path]:
    """The markdown pages whose links are checked: the three top-level pages and docs/**."""
    return [ROOT / "README.md", ROOT / "ARCHITECTURE.md", ROOT / "CONTRIBUTING.md",
            *sorted(DOCS.rglob("*.md"))]


def _prose(page: Path) -> str:
    """The page without its fenced code blocks (code is not a link), line count kept."""
    return _FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), page.read_text())


def _heading_ids(page: Path) -> set[str]:
    """GitHub's ids of a page's headings: lower case, markup and punctuation other than
    ``-`` and ``_`` dropped, spaces to ``-``; a repeated id gets ``-1``, ``-2``, ..."""
    ids: set[str] = set()
    for m in _HEADING.finditer(_prose(page)):
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", m.group(1))     # a link: its text
        slug = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
        base, n = slug, 0
        while slug in ids:
            n += 1
            slug = f"{base}-{n}"
        ids.add(slug)
    return ids


def _where(page: Path, text: str, pos: int) -> str:
    return f"  {page.relative_to(ROOT)}:{text.count(chr(10), 0, pos) + 1}: "


def test_every_page_exists():
    for page in _pages()[:3]:
        assert page.is_file(), f"{page.name} is missing"
    assert len(list(DOCS.glob("results/*.md"))) >= 5, "docs/results/ holds the measured figures, one file per area"


def test_links_between_docs_resolve():
    """Every relative link of README.md, ARCHITECTURE.md, CONTRIBUTING.md and docs/**/*.md
    points at an existing path; an anchor into one of these pages names one of its headings."""
    pages = _pages()
    checked = {p.resolve() for p in pages}
    broken, links = [], 0
    for page in pages:
        text = _prose(page)
        for m in _MD_LINK.finditer(text):
            target = m.group(1)
            if "://" in target or target.startswith("mailto:"):
                continue
            links += 1
            if not (page.parent / target).exists():
                broken.append(f"{_where(page, text, m.start())}{target}")
        for m in _ANCHOR_LINK.finditer(text):
            target, anchor = m.group(1), m.group(2)
            if "://" in target:
                continue
            dest = (page.parent / target).resolve() if target else page.resolve()
            if dest in checked and anchor not in _heading_ids(dest):
                broken.append(f"{_where(page, text, m.start())}{target}#{anchor} (no such heading)")
    assert links >= 50, f"only {links} relative links found: is the link pattern still right?"
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_readme_is_short():
    """A newcomer reads the README in ten minutes; long material lives in docs/ and docs/results/."""
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, (f"README.md has {n} lines (at most {README_MAX_LINES}): move detail to "
                                   "docs/*.md and measured figures to docs/results/, keeping a short table")


def _module_paths() -> tuple[set[str], set[str]]:
    """(folders that hold .py files, outside tests/; modules at the top of each wheel package)."""
    m = re.search(r"^wheel\.packages\s*=\s*\[([^\]]*)\]", (ROOT / "pyproject.toml").read_text(), re.M)
    assert m, "pyproject.toml names no wheel.packages"
    packages = set(re.findall(r'"([^"]+)"', m.group(1)))
    assert {"common", "mapper", "apps"} <= packages, packages
    folders, modules = set(), set()
    for p in _files():
        rel = p.relative_to(ROOT)
        if p.suffix != ".py" or rel.parts[0] == "tests":
            continue
        if len(rel.parts) > 1:
            folders.add(rel.parent.as_posix() + "/")
        if len(rel.parts) == 2 and rel.parts[0] in packages:
            modules.add(rel.as_posix())
    return folders, modules


def test_architecture_names_every_module_folder_and_top_level_module():
    text = (ROOT / "ARCHITECTURE.md").read_text()
    folders, modules = _module_paths()
    assert {"mapper/", "mapper/outputs/", "apps/console/"} <= folders and "mapper/state.py" in modules
    named = lambda path: re.search(r"(?<![\w./-])" + re.escape(path), text) is not None  # noqa: E731
    missing = sorted(p for p in folders | modules if not named(p))
    assert not missing, ("ARCHITECTURE.md, the module map, does not name (by its path from the repository root):\n"
                         + "\n".join(f"  {m}" for m in missing))
