""".ci/check_skips.py: a skip outside the allow-list fails CI; listed ones pass (hand-made
JUnit XML in pytest's layout, and one written by a real pytest run)."""
import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("check_skips", ROOT / ".ci" / "check_skips.py")
CS = importlib.util.module_from_spec(spec)
spec.loader.exec_module(CS)

XML = """<?xml version="1.0" encoding="utf-8"?><testsuites><testsuite name="pytest" tests="3">
<testcase classname="tests.test_a" name="test_ok" time="0.1"/>
<testcase classname="tests.test_zenoh_netns" name="test_three_namespaces" time="0.0">
  <skipped type="pytest.skip" message="needs root and iproute2">needs root</skipped></testcase>
{extra}
</testsuite></testsuites>"""
OTHER = """<testcase classname="tests.test_occupancy_cross" name="test_same[1]" time="0.0">
  <skipped type="pytest.skip" message="OpenVDB extension not built">x</skipped></testcase>"""


def _run(tmp_path, extra, allow_text, root=False, monkeypatch=None):
    x = tmp_path / "j.xml"
    x.write_text(XML.format(extra=extra))
    a = tmp_path / "allow.txt"
    a.write_text(allow_text)
    monkeypatch.setattr(CS.os, "geteuid", lambda: 0 if root else 1000)
    return CS.main(["check_skips", str(x), str(a)])


def test_allowed_and_not_allowed_skips(tmp_path, monkeypatch):
    allow = "tests/test_zenoh_netns.py::* | needs root | not-root\n"
    assert _run(tmp_path, "", allow, monkeypatch=monkeypatch) == 0
    assert _run(tmp_path, OTHER, allow, monkeypatch=monkeypatch) == 1          # the extension skip fails CI
    assert _run(tmp_path, "", allow, root=True, monkeypatch=monkeypatch) == 1  # as root netns must run
    assert _run(tmp_path, "", "tests/test_zenoh_netns.py::* | other reason | always\n", monkeypatch=monkeypatch) == 1
    assert CS.node_id(CS.ET.fromstring('<testcase classname="tests.test_x.TestK" name="t[1]"/>')) == \
        "tests/test_x.py::TestK::t[1]"


def test_empty_report_fails_and_shipped_allowlist_parses(tmp_path, monkeypatch):
    x = tmp_path / "e.xml"
    x.write_text('<?xml version="1.0"?><testsuites><testsuite name="pytest" tests="0"/></testsuites>')
    assert CS.main(["check_skips", str(x), str(ROOT / "tests" / "ci_skip_allowlist.txt")]) == 1
    allow = CS.load_allowlist(str(ROOT / "tests" / "ci_skip_allowlist.txt"))
    assert all(w in ("always", "not-root") for _, _, w in allow)


def test_real_pytest_junit_skip_is_caught(tmp_path):
    t = tmp_path / "tests" / "test_s.py"
    t.parent.mkdir()
    t.write_text("import pytest\n\ndef test_a():\n    pytest.skip('why not')\n\ndef test_b():\n    pass\n")
    x = tmp_path / "j.xml"
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", f"--junitxml={x}",
                        "tests/test_s.py"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "SKIPPED" in r.stdout and "why not" in r.stdout      # -rs prints the reason
    a = tmp_path / "allow.txt"
    a.write_text("# nothing allowed\n")
    r2 = subprocess.run([sys.executable, str(ROOT / ".ci" / "check_skips.py"), str(x), str(a)], capture_output=True,
                        text=True, timeout=60)
    assert r2.returncode == 1 and "NOT ALLOWED skip: tests/test_s.py::test_a: why not" in r2.stderr
    a.write_text("tests/test_s.py::test_a | why not | always\n")
    r3 = subprocess.run([sys.executable, str(ROOT / ".ci" / "check_skips.py"), str(x), str(a)], capture_output=True,
                        text=True, timeout=60)
    assert r3.returncode == 0, r3.stderr
