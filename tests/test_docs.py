"""The design documents live in ``docs/`` and every citation points there.

* No file of the repository cites a design document outside it (the old external design
  page by section, or a path under a shared work directory).
* Every ``docs/<name>.md`` a file mentions exists (anchors are not checked).
* Relative links between the markdown pages of ``docs/`` resolve.

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


def test_links_between_docs_resolve():
    broken = []
    for page in sorted(DOCS.glob("*.md")):
        text = page.read_text()
        for m in _MD_LINK.finditer(text):
            target = m.group(1)
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                broken.append(f"  docs/{page.name}:{text.count(chr(10), 0, m.start()) + 1}: {target}")
    assert not broken, "broken links in docs/:\n" + "\n".join(broken)
