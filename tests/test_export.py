"""``rayfronts export`` (docs/export.md): each format read back by an independent reader and
compared with the map computed independently from the snapshot's arrays.

Readers: meshio (PLY) and OpenVDB's Python module ``pyopenvdb`` plus OpenVDB's own
``vdb_print`` (Debian's ``python3-meshio``, ``python3-openvdb``, ``libopenvdb-tools``; run
under ``/usr/bin/python3`` by :mod:`tests.support.standard_readers`); the map_server PGM by
OpenCV and its YAML by PyYAML, turned into cells with map_server's trinary rule written here.
"""
from __future__ import annotations

import json
import math
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from tests.support.processes import ROOT, cli_cmd, proc_env

SYSTEM_PYTHON = "/usr/bin/python3"
READERS = ROOT / "tests" / "support" / "standard_readers.py"
VOX = 0.5
LABELS = ("car", "tree", "building")


def _read(kind: str, path: Path, tmp: Path) -> dict:
    out = tmp / f"read-{kind}.npz"
    r = subprocess.run([SYSTEM_PYTHON, str(READERS), kind, str(path), str(out)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def _export(*argv: str) -> None:
    """``rayfronts export ARGV`` in this process (its result checked by the caller's reader)."""
    from apps.cli import build_parser

    args = build_parser("export").parse_args(["export", *argv])
    assert args._module.run(args) == 0


def _unpack(keys: np.ndarray) -> np.ndarray:
    """(N, 3) voxel indices of packed keys, per docs/conventions.md (21 bits per axis)."""
    keys = keys.astype(np.int64)
    m = (1 << 21) - 1
    return np.stack([(keys >> 42) & m, (keys >> 21) & m, keys & m], 1) - (1 << 20)


@pytest.fixture(scope="module")
def snap(tmp_path_factory):
    """A snapshots dir of a small flushed map (a box room seen by a turning camera, 16-d
    features in the label space) and the snapshot's arrays as numpy reads them."""
    from apps.bench.query import _space
    from common.messages import encode_feature_space
    from mapper.snapshot import capture_map
    from mapper.snapshot_store import write_snapshot
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap
    from tests.test_mapper_map import _frames

    fs = _space(16)
    m = RayFrontsMap(map_config("default", dict(vox_size=VOX, max_depth_sensing=12.0)), 16, fs.id)
    for i, (pose, K, depth, rgb, _) in enumerate(_frames(12)[:6]):
        m.integrate(pose, K, depth, rgb, torch.randn(16, 6, 8, generator=torch.Generator().manual_seed(i)))
    m.flush()
    root = tmp_path_factory.mktemp("export") / "snaps"
    gen = write_snapshot(root, capture_map(m), encode_feature_space("r1", fs.to_body()), {"frames_mapped": 6})
    man = json.loads((gen / "map" / "manifest.json").read_text())
    # flushed: the arrays are the whole map (a pending prune changes nothing until it runs)
    assert (man["buffers"]["occ"], man["buffers"]["sem"], man["buffers"]["rays"]) == (0, 0, 0)
    with np.load(gen / "map" / "arrays.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return {"root": root, "gen": gen, "arrays": arrays, "fs": fs}


def _mapper_scores(gen: Path, fs, text: str) -> dict[tuple, float]:
    """Voxel centre -> score of ``text`` as the mapper answers a query on the snapshot's map."""
    from common.messages import QueryRequest
    from mapper.query_answer import answer_query
    from mapper.service_config import QuerySection
    from mapper.snapshot import load_map
    from semantic_map.map import RayFrontsMap

    m = load_map(gen / "map", RayFrontsMap)
    r = answer_query(m, fs, QueryRequest(text=text, top_k=m.n_voxels()), QuerySection())
    assert len(r.voxel_score) == m.n_voxels()
    ijk = np.floor(np.asarray(r.voxel_xyz, np.float64) / VOX).astype(int)
    return {tuple(c): float(s) for c, s in zip(ijk.tolist(), r.voxel_score, strict=True)}


# First in the file: its edge embeds the synthetic world's class names into the session's
# text cache (RAYFRONTS_TEXT_CACHE), which the PLY test's query and labels then read instead
# of loading the text model again.
def test_export_from_a_live_mapper_over_zenoh(procs, pca_file, tmp_path):
    """A mapper and an edge over Zenoh: an export of its empty map is one line and exit 2
    (``rayfronts export --connect`` as a process); after a few frames the exports (run in this
    process) equal what the running mapper answers (its occupancy slice, its voxels layer, its
    query scores), and the mapper keeps running throughout."""
    from apps.processes import wait_for
    from semantic_map.query_copy import SCORE_ATOL
    from tests.support.ports import free_port
    from tests.support.processes import Proc
    from tests.support.roles import client, edge_args, mapper_args

    ep = f"tcp/127.0.0.1:{free_port()}"
    mapper = Proc("mapper", mapper_args(ep, ["queues.idle_flush_s=0.3", f"snapshots.dir={tmp_path / 'snaps'}"]),
                  tmp_path)
    procs.append(mapper)
    with client(ep) as c:
        wait_for(lambda: c.stats(timeout=5.0), 120, what="mapper answering")
        _one_line_exit_2(_run_cli("--connect", ep, "--format", "ply", "--out", str(tmp_path / "e.ply")),
                         "empty map")
        assert mapper.p.poll() is None
        procs.append(Proc("edge", edge_args(ep, pca_file, frames=4, rate=8.0), tmp_path))
        assert procs[-1].p.wait(timeout=180) == 0, (tmp_path / "edge.log").read_text()[-2000:]
        c.wait_settled(timeout=60)
        band = (0.2, 1.5)
        yml = tmp_path / "live.yaml"
        _export("--connect", ep, "--format", "map_server", "--out", str(yml), "--z-min", str(band[0]),
                "--z-max", str(band[1]))
        cells, meta = _load_map_server(yml)
        cell = meta["resolution"]
        lo = np.array(meta["origin"][:2]) + cell / 2
        rep = c.occupancy_slice(lo, lo + (np.array(cells.shape) - 1) * cell, band)
        assert rep.cell_m == cell and np.allclose(rep.origin, meta["origin"][:2])
        live = np.array([-1, 0, 100])[np.asarray(rep.states) + 1]
        assert (live == 100).sum() > 20 and (live == 0).sum() > 20
        assert (cells == live).all()
        # PLY with a query's scores: the voxels layer and the query answer
        ply = tmp_path / "live.ply"
        _export("--connect", ep, "--format", "ply", "--out", str(ply), "--query", "car")
        got = _read("ply", ply, tmp_path)
        layer, lmeta = c.layer("voxels")
        assert lmeta["total"] == len(layer["xyz"]) == len(got["points"]) > 100
        key = np.lexsort(got["points"].T[::-1]), np.lexsort(layer["xyz"].T[::-1])
        np.testing.assert_array_equal(got["points"][key[0]], layer["xyz"][key[1]])
        colours = np.stack([got[k] for k in ("red", "green", "blue")], 1).view(np.uint8)
        np.testing.assert_array_equal(colours[key[0]], layer["rgb"][key[1]])
        r = c.query("car", top_k=50)
        assert len(r.voxel_xyz) == 50
        at = {tuple(np.floor(q / VOX).astype(int).tolist()): i for i, q in enumerate(got["points"].astype(float))}
        rows = [at[tuple(np.floor(q / VOX).astype(int).tolist())] for q in np.asarray(r.voxel_xyz, float)]
        np.testing.assert_allclose(got["score"][rows], r.voxel_score, atol=SCORE_ATOL)
        assert got["score"].max() <= r.voxel_score[0] + SCORE_ATOL
        assert mapper.p.poll() is None and c.stats(timeout=5.0)["frames"]["mapped"] >= 1


def test_ply_read_back_by_meshio_equals_the_map_voxels(snap, tmp_path, monkeypatch):
    from semantic_map.query_copy import SCORE_ATOL

    monkeypatch.setenv("RAYFRONTS_TEXT_CACHE", proc_env()["RAYFRONTS_TEXT_CACHE"])
    out = tmp_path / "map.ply"
    _export("--snapshot", str(snap["root"]), "--format", "ply", "--out", str(out), "--query", "car",
            *[a for t in LABELS for a in ("--label", t)])
    head = out.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in head
    assert [ln for ln in head.splitlines() if ln.startswith("property")] == [
        "property float x", "property float y", "property float z", "property uchar red", "property uchar green",
        "property uchar blue", "property float score", "property int label"]
    got = _read("ply", out, tmp_path)
    a = snap["arrays"]
    n = len(a["sem_keys"])
    assert n > 500 and len(got["points"]) == n
    ijk = _unpack(a["sem_keys"])
    rgb = np.clip(a["sem_rgb"].astype(np.float32) * 255 + 0.5, 0, 255).astype(np.uint8)
    # row for row against the snapshot's voxels, compared by index
    got_ijk = np.floor(got["points"].astype(np.float64) / VOX).astype(np.int64)
    order_got, order_ref = np.lexsort(got_ijk.T[::-1]), np.lexsort(ijk.T[::-1])
    assert (got_ijk[order_got] == ijk[order_ref]).all()
    np.testing.assert_allclose(got["points"][order_got], (ijk[order_ref] + 0.5) * VOX, atol=1e-5)
    colours = np.stack([got[c] for c in ("red", "green", "blue")], 1).view(np.uint8)  # meshio reads uchar as int8
    assert (colours[order_got] == rgb[order_ref]).all()
    assert len(np.unique(rgb, axis=0)) > 50
    # score: the mapper's query answer for the same voxel (its float16 copy: within SCORE_ATOL)
    ref = _mapper_scores(snap["gen"], snap["fs"], "car")
    score = np.array([ref[tuple(c)] for c in got_ijk])
    assert np.ptp(score) > 0.1
    np.testing.assert_allclose(got["score"], score, atol=SCORE_ATOL)
    # label: the index of the best of the labels' scores (where it is not a near tie)
    refs = [_mapper_scores(snap["gen"], snap["fs"], t) for t in LABELS]
    per = np.stack([[r[tuple(c)] for c in got_ijk] for r in refs])
    top2 = np.sort(per, 0)[-2:]
    clear = top2[1] - top2[0] > 2 * SCORE_ATOL
    assert clear.mean() > 0.9 and len(np.unique(got["label"])) == len(LABELS)
    assert (got["label"][clear] == per.argmax(0)[clear]).all()


def test_vdb_read_by_openvdb_equals_the_occupancy(snap, tmp_path):
    out = tmp_path / "occ.vdb"
    _export("--snapshot", str(snap["gen"]), "--format", "vdb", "--out", str(out))
    a = snap["arrays"]
    seen = a["occ_values"] != 0
    ijk, val = a["occ_ijk"][seen], a["occ_values"][seen]
    assert (val > 0).sum() > 500 and (val < 0).sum() > 5000
    # OpenVDB's own tool lists both grids with their voxel counts
    info = subprocess.run(["vdb_print", "-l", str(out)], capture_output=True, text=True, timeout=60)
    assert info.returncode == 0, info.stderr
    assert re.findall(r"Name: (\w+)", info.stdout) == ["log_odds", "occupied"]
    counts = [int(c.replace(",", "")) for c in re.findall(r"Number of active voxels:\s+([\d,]+)", info.stdout)]
    assert counts == [len(val), int((val > 0).sum())]
    assert re.findall(r"voxel size: ([\d.]+)", info.stdout) == [str(VOX)] * 2
    got = _read("vdb", out, tmp_path)
    assert sorted(got["names"]) == ["log_odds", "occupied"]
    assert str(got["log_odds_type"]) == "FloatGrid" and str(got["occupied_type"]) == "BoolGrid"

    def as_dict(k, v):
        return dict(zip(map(tuple, k.astype(np.int64).tolist()), np.asarray(v).tolist(), strict=True))

    assert as_dict(got["log_odds_ijk"], got["log_odds_value"]) == as_dict(ijk, val.astype(float))
    assert as_dict(got["occupied_ijk"], got["occupied_value"]) == as_dict(ijk[val > 0], [True] * int((val > 0).sum()))
    for g in ("log_odds", "occupied"):
        np.testing.assert_allclose(got[f"{g}_world"], (np.array([1, 2, 3]) + 0.5) * VOX)  # index -> voxel centre
        meta = json.loads(str(got[f"{g}_meta"]))
        assert meta["voxel_size_m"] == VOX and (meta["occ_lo"], meta["occ_hi"]) == (-5, 30)
        assert "centre" in meta["convention"]


def _slice_from_arrays(a: dict, x0: int, y0: int, nx: int, ny: int, z_band) -> np.ndarray:
    """Brute force: per (x, y) map voxel, over the voxels k of the z band: 100 if any is
    occupied, 0 if all are observed free, else -1 (unobserved voxels are 0 log-odds)."""
    k0, k1 = math.floor(z_band[0] / VOX), math.floor(z_band[1] / VOX)
    vol = np.zeros((nx, ny, k1 - k0 + 1), np.int8)
    ijk, v = a["occ_ijk"], a["occ_values"]
    sel = ((ijk[:, 0] >= x0) & (ijk[:, 0] < x0 + nx) & (ijk[:, 1] >= y0) & (ijk[:, 1] < y0 + ny)
           & (ijk[:, 2] >= k0) & (ijk[:, 2] <= k1))
    vol[ijk[sel, 0] - x0, ijk[sel, 1] - y0, ijk[sel, 2] - k0] = v[sel]
    return np.where((vol > 0).any(2), 100, np.where((vol < 0).all(2), 0, -1))


def _load_map_server(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """(cells [x, y] in -1 / 0 / 100, the YAML) as map_server loads them: image rows top down
    (its last row is the cell at ``origin``), occ = (255 - p) / 255 (negate 0), trinary."""
    import cv2

    meta = yaml.safe_load(yaml_path.read_text())
    img = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.dtype == np.uint8 and img.ndim == 2
    occ = (255.0 - img) / 255.0
    if meta["negate"]:
        occ = 1.0 - occ
    cells = np.where(occ > meta["occupied_thresh"], 100, np.where(occ < meta["free_thresh"], 0, -1))
    return cells[::-1].T, meta


def test_map_server_files_reload_to_the_slice(snap, tmp_path):
    from mapper.snapshot import load_map
    from planning.occupancy_queries import costmap_slice
    from semantic_map.map import RayFrontsMap

    out = tmp_path / "room.yaml"
    band = (0.2, 1.5)
    _export("--snapshot", str(snap["root"]), "--format", "map_server", "--out", str(out),
            "--z-min", str(band[0]), "--z-max", str(band[1]))
    cells, meta = _load_map_server(out)
    assert meta["mode"] == "trinary" and meta["resolution"] == VOX and meta["origin"][2] == 0.0
    x0, y0 = round(meta["origin"][0] / VOX), round(meta["origin"][1] / VOX)
    assert np.allclose(meta["origin"][:2], [x0 * VOX, y0 * VOX])
    a = snap["arrays"]
    seen = a["occ_ijk"][a["occ_values"] != 0]
    assert (x0, y0) == tuple(seen[:, :2].min(0))  # the extent of the observed voxels
    assert cells.shape == tuple(seen[:, :2].max(0) - seen[:, :2].min(0) + 1)
    ref = _slice_from_arrays(a, x0, y0, *cells.shape, band)
    assert (ref == 100).sum() > 100 and (ref == 0).sum() > 100 and (ref == -1).sum() > 10
    assert (cells == ref).all()
    # and the mapper's own slice function on the loaded map
    m = load_map(snap["gen"] / "map", RayFrontsMap)
    st, origin, cell = costmap_slice(m.occupancy_view(), VOX, seen[:, :2].min(0) * VOX + 0.25,
                                     seen[:, :2].max(0) * VOX + 0.25, band)
    assert (np.array([-1, 0, 100])[st + 1] == cells).all() and cell == VOX  # UNKNOWN -1, FREE 0, OCCUPIED 1
    # --stride 2: cells of 2 x 2 voxel columns, occupied if any, free if all free, else unknown
    out2 = tmp_path / "coarse.yaml"
    _export("--snapshot", str(snap["root"]), "--format", "map_server", "--out", str(out2), "--stride", "2",
            "--z-min", str(band[0]), "--z-max", str(band[1]))
    coarse, meta2 = _load_map_server(out2)
    assert meta2["resolution"] == 2 * VOX and meta2["origin"] == meta["origin"]
    assert coarse.shape == tuple((np.array(cells.shape) + 1) // 2)
    fine = _slice_from_arrays(a, x0, y0, 2 * coarse.shape[0], 2 * coarse.shape[1], band)
    blocks = fine.reshape(coarse.shape[0], 2, coarse.shape[1], 2)
    want = np.where((blocks == 100).any((1, 3)), 100, np.where((blocks == 0).all((1, 3)), 0, -1))
    assert (coarse == want).all() and (want == 100).sum() > 50


def test_snapshot_export_is_a_generation_the_mapper_restores(snap, tmp_path):
    from mapper.snapshot import check_generation, snapshot_generations

    out = tmp_path / "copy"
    _export("--snapshot", str(snap["gen"]), "--format", "snapshot", "--out", str(out))
    gens = snapshot_generations(out)
    assert len(gens) == 1 and (out / "LATEST").read_text() == gens[0].name
    assert check_generation(gens[0])["frames_mapped"] == 6
    assert (gens[0] / "feature_space.bin").read_bytes() == (snap["gen"] / "feature_space.bin").read_bytes()
    with np.load(gens[0] / "map" / "arrays.npz") as z:
        assert set(z.files) == set(snap["arrays"])
        for k in z.files:
            assert np.array_equal(z[k], snap["arrays"][k]), k


def _run_cli(*argv: str) -> subprocess.Popen:
    return subprocess.Popen(cli_cmd("export", *argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=proc_env(), cwd=str(ROOT))


def _one_line_exit_2(p: subprocess.Popen, *words: str) -> str:
    out, err = p.communicate(timeout=120)
    assert p.returncode == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rayfronts export: error: "), err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def test_bad_input_is_one_line_and_exit_2(snap, tmp_path):
    from apps.cli import error_line
    from apps.export.source import UserError
    from common.messages import encode_feature_space
    from mapper.snapshot import capture_map
    from mapper.snapshot_store import write_snapshot
    from semantic_map.config import map_config
    from semantic_map.map import RayFrontsMap

    empty = tmp_path / "empty"
    write_snapshot(empty, capture_map(RayFrontsMap(map_config("default", {}), 16, snap["fs"].id)),
                   encode_feature_space("r1", snap["fs"].to_body()), {"frames_mapped": 0})
    root = str(snap["root"])
    runs = [
        (_run_cli("--snapshot", str(tmp_path / "nowhere"), "--format", "ply", "--out", str(tmp_path / "a.ply")),
         ("does not exist", "--snapshot")),
        (_run_cli("--snapshot", root, "--format", "obj", "--out", str(tmp_path / "a.obj")), ("--format", "obj")),
        (_run_cli("--snapshot", root, "--format", "ply", "--out", "/proc/rayfronts-export.ply"),
         ("not writable", "--out")),
        (_run_cli("--snapshot", root, "--format", "vdb", "--out", str(tmp_path / "no" / "a.vdb")),
         ("does not exist", "--out")),
        (_run_cli("--snapshot", root, "--format", "vdb", "--query", "car", "--out", str(tmp_path / "a.vdb")),
         ("--query", "vdb")),
    ]
    # an empty map: in this process (the same error path as the command line, without
    # another torch start-up)
    for fmt, out, what in (("ply", "e.ply", "semantic voxels"), ("vdb", "e.vdb", "occupancy"),
                           ("map_server", "e.yaml", "occupancy")):
        with pytest.raises(UserError) as e:
            _export("--snapshot", str(empty), "--format", fmt, "--out", str(tmp_path / out))
        line, code = error_line("rayfronts export", e.value)
        assert code == 2 and "\n" not in line and "empty map" in line and what in line, line
    for p, words in runs:
        _one_line_exit_2(p, *words)
    assert not [f for f in tmp_path.iterdir() if f.suffix in (".ply", ".vdb", ".yaml", ".pgm", ".obj", ".tmp")]
