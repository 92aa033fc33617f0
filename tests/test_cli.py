"""The ``rayfronts`` command: every subcommand has a working --help; config errors are clear."""
import subprocess

import pytest

from apps.cli import SUBCOMMANDS
from tests.support.processes import cli_cmd


def _run(*args, timeout=120):
    return subprocess.run(cli_cmd(*args), capture_output=True, text=True, timeout=timeout)


def test_top_level_help_lists_every_subcommand():
    r = _run("--help")
    assert r.returncode == 0, r.stderr
    for name in SUBCOMMANDS:
        assert name in r.stdout


@pytest.mark.parametrize("name", sorted(SUBCOMMANDS))
def test_subcommand_help(name):
    r = _run(name, "--help")
    assert r.returncode == 0, r.stderr
    assert f"rayfronts {name}" in r.stdout
    assert "unavailable" not in r.stdout, r.stdout  # the module imported
    assert "-h, --help" in r.stdout


@pytest.mark.parametrize("cmd,key,close", [
    ("mapper", "map.vox_sise=0.3", "map.vox_size"),
    ("edge", "source.knd=synthetic", "source.kind"),
])
def test_unknown_config_key_names_closest(cmd, key, close):
    r = _run(cmd, key)
    assert r.returncode == 2
    assert key.split("=")[0] in r.stderr and close in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_missing_config_file_is_a_clear_error(tmp_path):
    r = _run("mapper", "--config", str(tmp_path / "nope.yaml"))
    assert r.returncode == 2
    assert "nope.yaml" in r.stderr and "Traceback" not in r.stderr
