"""The query client's role install: a fresh venv with only the dependencies pyproject.toml
declares for the client (base + ``[client]``, installed by pip from the registry), the
source tree on PYTHONPATH, and no torch / OpenCV / rerun. It queries a running mapper
(started here, from the main venv) with ``python -m apps.cli query`` and with
``query_client.Client``, and its answers must equal the mapper's own.

The venv gets the declared dependencies only, not this project (building the wheel means the
C++ extension's CMake build; a client-only wheel would use ``-Cwheel.cmake=false``).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "cv2", "rerun", "scipy", "matplotlib")


def _client_requirements() -> list[str]:
    import tomllib  # Python >= 3.11, as the dev/test environment

    proj = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return list(proj["dependencies"]) + list(proj["optional-dependencies"]["client"])


@pytest.fixture(scope="module")
def client_python(tmp_path_factory) -> str:
    venv = tmp_path_factory.mktemp("client-venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = str(venv / "bin" / "python")
    # this venv's pip installs into the other interpreter (--python): no pip bootstrap needed
    p = subprocess.run([sys.executable, "-m", "pip", "--python", py, "install", "-q", "--disable-pip-version-check",
                        *_client_requirements()], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return py


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["PYTHONPATH"] = str(ROOT)
    return env


def _run(py: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([py, *args], capture_output=True, text=True, timeout=timeout, env=_env(), cwd=ROOT)


@pytest.fixture(scope="module")
def mapper():
    """A mapper serving a small map whose 'water tower' voxel is known."""
    import torch

    from common.feature_space import FeatureSpace
    from common.zenoh_session import free_tcp_port
    from encoders.text import make_text_encoder
    from mapper.service import MapperService
    from mapper.service_config import load_mapper_config
    from mapper.service_map import create_map

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    cfg = load_mapper_config(None, ["preset=throughput", "map.vox_size=0.5", "zenoh.mode=router",
                                    f'zenoh.listen=["{ep}"]', "layers.rate_hz=0"])
    fs = FeatureSpace("label", "1", 384)
    enc = make_text_encoder("minilm-l6")
    names = ["road", "tree", "house", "car", "water tower", "grass"]
    emb = torch.as_tensor(fs.embed_queries(names, enc), dtype=torch.float32)
    m = create_map(cfg, fs)
    rng = np.random.default_rng(0)
    xyz = (rng.integers(-20, 20, (600, 3)) + 0.5) * 0.5
    xyz = np.unique(xyz, axis=0)
    cls = rng.integers(0, len(names), len(xyz))
    cls[cls == 4] = 0                          # one water tower only, at a known place
    tower = np.array([3.25, -1.75, 8.25])
    xyz = np.concatenate([xyz[np.abs(xyz - tower).sum(1) > 0.1], tower[None]])
    cls = np.concatenate([cls[: len(xyz) - 1], [4]])
    m.fuse_samples(torch.as_tensor(xyz, dtype=torch.float32), torch.rand(len(xyz), 3), emb[cls])
    svc = MapperService(cfg)
    svc.map, svc.space, svc.map_gen, svc.mapped = m, fs, 1, 7
    svc.start()
    try:
        yield svc, ep, tower
    finally:
        svc.close()


def test_client_venv_has_no_heavy_packages(client_python):
    p = _run(client_python, "-c", "import torch")
    assert p.returncode != 0 and "No module named 'torch'" in p.stderr
    for mod in ("cv2", "rerun"):
        p = _run(client_python, "-c", f"import {mod}")
        assert p.returncode != 0 and f"No module named '{mod}'" in p.stderr, mod
    # and the tree it runs is this one, not an installed copy
    p = _run(client_python, "-c", "import common, query_client; print(common.__file__)")
    assert p.returncode == 0 and p.stdout.strip() == str(ROOT / "common" / "__init__.py"), p.stderr


def test_cli_query_from_client_venv(client_python, mapper):
    from common.messages import QueryRequest

    svc, ep, tower = mapper
    p = _run(client_python, "-m", "apps.cli", "query", "water tower", "--connect", ep, "--json", "--top-k", "3",
             "--timeout", "30")
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout)
    want = svc.run_query(QueryRequest(text="water tower", top_k=3))
    assert got["frames_mapped"] == 7
    np.testing.assert_allclose(got["voxel_xyz"][0], tower, atol=1e-4)
    np.testing.assert_allclose(np.asarray(got["voxel_xyz"]), want.voxel_xyz, atol=1e-6)
    np.testing.assert_allclose(np.asarray(got["voxel_score"]), want.voxel_score, atol=1e-6)


def test_cli_rerun_option_in_client_venv_is_one_clear_error(client_python, mapper, tmp_path):
    _, ep, _ = mapper
    p = _run(client_python, "-m", "apps.cli", "query", "water tower", "--connect", ep, "--rerun",
             str(tmp_path / "q.rrd"), "--timeout", "30")
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "rerun-sdk" in lines[0] and "Traceback" not in p.stderr, p.stderr
    assert not (tmp_path / "q.rrd").exists()


def test_python_client_from_client_venv(client_python, mapper):
    svc, ep, tower = mapper
    script = f"""
import json, sys
from query_client import Client
from common.zenoh_session import ZenohConfig
with Client(ZenohConfig(connect=[{ep!r}], connect_timeout_ms=30000), timeout=30.0) as c:
    r = c.query("water tower", top_k=2)
    st = c.stats()
heavy = [m for m in {HEAVY!r} if m in sys.modules]
print(json.dumps({{"xyz": r.voxel_xyz.tolist(), "mapped": st["frames"]["mapped"], "heavy": heavy}}))
"""
    p = _run(client_python, "-c", script)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["heavy"] == []
    assert got["mapped"] == 7
    np.testing.assert_allclose(got["xyz"][0], tower, atol=1e-4)


def test_query_path_imports_nothing_heavy_in_main_venv():
    """Also where torch & co. are installed, the query subcommand does not load them."""
    code = ("import sys, runpy; sys.argv = ['rayfronts', 'query', '--help']\n"
            "try:\n    runpy.run_module('apps.cli', run_name='__main__')\nexcept SystemExit:\n    pass\n"
            f"print([m for m in {HEAVY!r} if m in sys.modules])")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "[]", p.stdout
