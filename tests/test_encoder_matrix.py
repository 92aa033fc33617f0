"""Every encoder × output × PCA combination the edge accepts runs end to end through real
processes, and the ones it does not accept are refused at start-up with one line.

* Runs: a ``rayfronts mapper`` (router mode, the base station) and a ``rayfronts edge`` per
  combination — NARADIO with random radio_v2.5-b weights saved to a model directory (as a user
  has it after ``rayfronts models convert``), NACLIP's reduced last block ("NACLIP only"),
  plain RADIO (no NACLIP), and the label encoder; output radio / language; PCA fitted online /
  none. The mapper must fuse every frame in the expected feature space and answer a query (an
  image query on NARADIO maps — no SigLIP text weights exist offline —, text on label maps).
  One map per feature space, so one mapper per combination; four run at a time.
* Refusals: against one mapper, edges with an impossible combination exit with code 2 and one
  error line naming it; the mapper shows the robot's ``edge_state``/``edge_reason`` and logs
  the reason once.
"""
from __future__ import annotations

import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.zenoh_session import ZenohConfig, free_tcp_port
from tests.support.processes import ROOT, cli_cmd, proc_env, start_cli, stop_all, wait_for

FRAMES = 4
RES = "48x64"                 # NARADIO: a 3x4 patch grid; label: 6x8 cells
# fleet.no_space_evict_s: eight processes share two cores here, and a NARADIO edge serves its
# feature space only after building the model and fitting its PCA; under load that has taken
# over the default 60 s, the mapper then forgot the robot and dropped its held frames (eviction
# is tested in tests/test_fleet*.py, not here)
MAPPER = ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0",
          "snapshots.on_exit=false", "queues.per_robot=1000", "fleet.no_space_evict_s=600",
          "fleet.pending_ttl_s=600"]


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    """radio_v2.5-b random weights (real architecture) in a model directory, as float16."""
    import torch

    from apps.bench.encoder import random_model_dir

    d = tmp_path_factory.mktemp("models")
    random_model_dir("radio_v2.5-b", d, dtype=torch.float16)
    return d


def _edge_items(kind: str, mdir: Path, output: str = "radio", pca: bool = True, extra=()) -> list[str]:
    items = [f"source.n_frames={FRAMES}", f"source.resolution={RES}", "source.depth_limit=20",
             "publish.rate_hz=4", "publish.linger_s=0.5"]
    if kind == "label":
        items += ["encoder.kind=label"]
    else:
        items += ["encoder.kind=naradio", "encoder.model=radio_v2.5-b", f"encoder.model_dir={mdir}",
                  f"encoder.output={output}"]
    items += ["pca.out_dim=8", "pca.fit_frames=2"] if pca else ["pca.out_dim=0"]
    return items + list(extra)


def _run_combo(name: str, items: list[str], mdir: Path, logdir: Path) -> dict:
    """Mapper + edge for one combination: frames mapped, the map's space, one query."""
    from query_client import Client
    from query_client.vocabulary import settled

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = proc_env()   # the session's text cache: label edges and maps embed names once
    logs = {k: open(logdir / f"{name}.{k}.log", "wb") for k in ("mapper", "edge")}
    mp = start_cli(["mapper", "--mode", "router", "--listen", ep, *MAPPER, f"query.image_model_dir={mdir}"],
                   logs["mapper"], env=env)
    procs = [mp]
    out: dict = {"name": name}
    try:
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=120_000), timeout=60.0) as c:
            # the edge starts once the mapper answers: frames published before its subscriber
            # exists are not received (a camera stream, not a queue), and a label edge with the
            # text cache publishes within a second of starting
            wait_for(lambda: c.stats(timeout=5.0), 120, every=0.5, what=f"{name}: mapper up")
            ed = start_cli(["edge", "--connect", ep, f"robot={name}", *items], logs["edge"], env=env)
            procs.insert(0, ed)
            seen: list = []

            def done():
                s = c.stats(timeout=10.0)
                seen[:] = [s]
                # voxels become visible at the map's voxel block / idle flush: wait for it
                return s if ed.poll() is not None and settled(s, mapped=FRAMES) else None

            try:
                st = wait_for(done, 600, every=0.5, what=f"{name}: {FRAMES} frames mapped")
            except AssertionError as e:
                logs["mapper"].flush()
                tail = (logdir / f"{name}.mapper.log").read_text()[-3000:]
                raise AssertionError(f"{e}; edge rc {ed.poll()}; stats {seen and seen[0].get('frames')} "
                                     f"{seen and seen[0].get('robots')}; mapper log: {tail}") from None
            out["edge_rc"] = ed.wait(30)
            out["mapped"] = st["frames"]["mapped"]
            out["rejected"] = st["frames"]["rejected"]
            out["space"] = st["robots"][name]["feature_space"]
            out["edge_state"] = st["robots"][name].get("edge_state")
            if "encoder.kind=label" in items:
                r = c.query("car", top_k=5, timeout=120.0)
            else:
                img = np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8)
                r = c.query(image=cv2.imencode(".png", img)[1].tobytes(), top_k=5, timeout=180.0)
            out["n_voxels_answered"] = len(r.voxel_xyz)
            out["scores_finite"] = bool(np.isfinite(r.voxel_score).all())
    finally:
        stop_all(procs, signal.SIGTERM, 30)
        for f in logs.values():
            f.close()
    return out


@pytest.mark.timeout(1500)
def test_every_accepted_combination_runs_end_to_end(model_dir, tmp_path):
    combos = {   # name -> (edge overrides, expected stored dim)
        "label_pca": (_edge_items("label", model_dir), 8),
        "label_raw": (_edge_items("label", model_dir, pca=False), 384),
        "radio_pca": (_edge_items("naradio", model_dir, "radio"), 8),
        "radio_raw": (_edge_items("naradio", model_dir, "radio", pca=False), 768),
        "lang_pca": (_edge_items("naradio", model_dir, "language"), 8),
        "lang_raw": (_edge_items("naradio", model_dir, "language", pca=False), 1152),
        "naclip_only": (_edge_items("naradio", model_dir, "radio", extra=["encoder.reduced_block=true"]), 8),
        "plain_radio": (_edge_items("naradio", model_dir, "language", pca=False, extra=["encoder.naclip=false"]),
                        1152),
    }
    with ThreadPoolExecutor(4) as ex:
        futs = {n: ex.submit(_run_combo, n, items, model_dir, tmp_path) for n, (items, _) in combos.items()}
        results = {n: f.result() for n, f in futs.items()}
    for name, (_, dim) in combos.items():
        r = results[name]
        assert r["edge_rc"] == 0 and r["edge_state"] == "done", r
        assert r["mapped"] == FRAMES and not r["rejected"], r
        assert r["space"].endswith(f"-{dim}"), r
        assert r["n_voxels_answered"] == 5 and r["scores_finite"], r
    # the variants are distinct feature spaces (maps never mix them)
    spaces = [results[n]["space"] for n in ("radio_pca", "naclip_only")]
    assert ".reduced" in spaces[1] and ".reduced" not in spaces[0]
    assert ".plain" in results["plain_radio"]["space"] and ".lang" in results["lang_raw"]["space"]


@pytest.mark.timeout(600)
def test_impossible_combinations_are_refused_with_one_line(model_dir, tmp_path):
    from common.pca import PCA
    from query_client import Client

    lang_basis = tmp_path / "lang_basis.npz"   # a basis for output=language (1152 inputs)
    rng = np.random.default_rng(0)
    PCA(np.zeros(1152, np.float32), np.linalg.qr(rng.standard_normal((1152, 8)))[0].astype(np.float32)).save(lang_basis)
    empty = tmp_path / "no_models"
    empty.mkdir()
    cases = {   # robot -> (edge overrides, words the one error line must contain)
        "too_many_dims": (_edge_items("label", model_dir, extra=["pca.out_dim=500"]),
                          ["encoder.kind=label", "pca.out_dim=500", "384"]),
        "wrong_basis": (_edge_items("naradio", model_dir, "radio", extra=[f"pca.basis={lang_basis}"]),
                        ["encoder.output=radio", "1152", "768"]),
        "no_weights": (_edge_items("naradio", empty, "radio"), ["no RADIO checkpoint", "radio_v2.5-b"]),
        "few_samples": (_edge_items("naradio", model_dir, "radio",
                                    extra=["source.resolution=32x32", "pca.fit_frames=1"]),
                        ["4 feature vectors per frame", "pca.fit_frames"]),
    }
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = proc_env()   # the session's text cache: label edges and maps embed names once
    mlog = open(tmp_path / "mapper.log", "wb")
    mp = start_cli(["mapper", "--mode", "router", "--listen", ep, *MAPPER], mlog, env=env)
    try:
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=120_000), timeout=30.0) as c:
            wait_for(lambda: c.stats(timeout=5.0), 120, every=0.5, what="mapper up")

            def run(robot):
                return subprocess.run(cli_cmd("edge", "--connect", ep, f"robot={robot}", *cases[robot][0]),
                                      capture_output=True, text=True, env=env, cwd=str(ROOT), timeout=300)

            with ThreadPoolExecutor(4) as ex:
                outs = dict(zip(cases, ex.map(run, cases), strict=True))
            # a missing model file is caught by the command line before the edge connects (one line,
            # exit 1, nothing to tell the mapper); the others by the running edge (exit 2, reported)
            early = {"no_weights"}
            for robot, (_, words) in cases.items():
                o = outs[robot]
                assert "Traceback" not in o.stderr, o.stderr[-3000:]
                if robot in early:
                    lines = [ln for ln in o.stderr.splitlines() if ln.strip()]
                    assert o.returncode != 0 and len(lines) == 1 and all(w in lines[0] for w in words), (robot, lines)
                    continue
                errors = [ln for ln in o.stderr.splitlines() if " ERROR " in ln]
                assert o.returncode == 2 and len(errors) == 1, (robot, o.returncode, o.stderr[-3000:])
                assert "refused to start" in errors[0] and all(w in errors[0] for w in words), (robot, errors)
            late = [r for r in cases if r not in early]
            st = wait_for(lambda: (lambda s: s if all(s["robots"].get(r, {}).get("edge_state") == "refused"
                                                      for r in late) else None)(c.stats(timeout=5.0)),
                          30, every=0.5, what="the mapper sees every refusal")
            for robot in late:
                assert all(w in st["robots"][robot]["edge_reason"] for w in cases[robot][1]), st["robots"][robot]
            time.sleep(2.0)   # a retrying mapper would warn again within this time
    finally:
        mp.terminate()
        mp.wait(30)
        mlog.close()
    lines = (tmp_path / "mapper.log").read_text().splitlines()
    for robot in late:
        said = [i for i, ln in enumerate(lines) if f"robot {robot}: its edge refused to start" in ln]
        assert len(said) == 1, (robot, said)
        # no retry warnings after the reason is known
        assert not any(f"feature space of {robot} not available yet" in ln for ln in lines[said[0]:]), robot


def test_edge_failure_after_start_is_reported_not_raised():
    """An exception while frames flow ends the edge with exit code 1 and state ``failed``
    (with the reason), not a traceback out of ``run``; a bad combination before the first
    frame is ``refused`` (exit code 2)."""
    import dataclasses

    from common.config import load_config
    from edge.config import EdgeConfig
    from edge.runtime import EdgeRuntime
    from edge.sources import SourceConfig, open_source

    src = open_source(SourceConfig(kind="synthetic", n_frames=3, resolution="32x40"))
    good = list(src)

    def frames():
        yield good[0]
        yield good[1]
        raise RuntimeError("camera unplugged")

    cfg = load_config(EdgeConfig, None, ["robot=fx", "pca.out_dim=0", "publish.rate_hz=0", "publish.status_wait_s=0",
                                         "publish.linger_s=0", "zenoh.connect=[tcp/127.0.0.1:9]"])
    rt = EdgeRuntime(cfg, frames=frames(), class_names=list(src.class_names))
    assert rt.run() == 1
    assert rt.connection.state == ("failed", "RuntimeError: camera unplugged") and rt.stats.frames_encoded == 2
    bad = dataclasses.replace(cfg, pca=dataclasses.replace(cfg.pca, out_dim=400))
    rt2 = EdgeRuntime(bad, frames=iter(good), class_names=list(src.class_names))
    assert rt2.run() == 2 and rt2.connection.state[0] == "refused" and "exceeds" in rt2.connection.state[1]
