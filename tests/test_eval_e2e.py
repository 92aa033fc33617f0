"""End-to-end benchmark runs on small synthetic / TartanAir-format data (real maps, real encoder)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from apps.evaluation.semseg import SemsegConfig, run_semseg
from apps.evaluation.srchvol import ALL_METHODS, SrchvolConfig, run_srchvol
from common.config import merge
from synthetic_world import World

pytestmark = pytest.mark.usefixtures("torch_two_threads")


@pytest.fixture(scope="module")
def world():
    return World.generate(0)


@pytest.fixture(scope="module")
def sv_run(tmp_path_factory, world):
    out = tmp_path_factory.mktemp("srchvol")
    cfg = merge(SrchvolConfig(), dict(source=dict(n_frames=16, resolution="48x48"), every=8, depth_limits=[0.0, 10.0],
                                      gt_range=25.0, progress=False, map={"max_rays_per_frame": 500}))
    summary = run_srchvol(cfg, out, world=world)
    return out, summary


def test_srchvol_outputs(sv_run):
    out, summary = sv_run
    top = json.loads((out / "summary.json").read_text())
    assert set(top) == {"0m", "10m"}
    for per in top.values():
        for m in ALL_METHODS:
            assert m in per
            s = per[m]
            if s is None:
                continue
            assert set(s) == {"scvr_auc", "scv_auc", "recall_auc", "miou_auc"}
            for v in s.values():
                assert v is not None and 0.0 <= v <= 1.0
    # Table I's N/A pattern
    assert top["0m"]["semantic_voxels"] is None and top["10m"]["semantic_poses"] is None
    assert top["0m"]["semantic_poses"] is not None and top["10m"]["spherical_semfronts"] is not None
    table = (out / "table.md").read_text()
    assert "| RayFronts |" in table and "--" in table
    assert (out / "plots" / "scvr_rayfronts_10m.png").stat().st_size > 1000
    rows = json.loads((out / "steps.json").read_text())
    assert {r["step"] for r in rows} == {8, 16}
    assert (out / "steps.csv").read_text().count("\n") == len(rows) + 1


def test_srchvol_paper_shape(sv_run):
    out, _ = sv_run
    top = json.loads((out / "summary.json").read_text())
    rows = json.loads((out / "steps.json").read_text())
    # Semantic Voxels: no evidence beyond range -> default prediction: Recall 1 and
    # SCV = |class| / |unobserved| exactly, i.e. SCVR ~ 0
    sv_rows = [r for r in rows if r["method"] == "semantic_voxels"]
    assert sv_rows and all(not r["evidence"] for r in sv_rows)
    for r in sv_rows:
        assert r["recall"] == 1.0 and r["fp"] == r["vol"] - r["tp"]
        assert r["scv"] == pytest.approx(r["tp"] / r["vol"])
    assert top["10m"]["semantic_voxels"]["recall_auc"] == 1.0
    assert top["10m"]["semantic_voxels"]["scvr_auc"] < 0.02
    # Semantic Poses maps nothing in range: mIoU 0
    assert top["0m"]["semantic_poses"]["miou_auc"] == 0.0
    # rays never change the voxel layer: the frontier baselines' own (separate) maps give
    # RayFronts' observed-region mIoU exactly, and it is > 0 (Semantic Voxels shares the
    # RayFronts map under share_maps, so comparing with it would prove nothing)
    mi = {m: top["10m"][m]["miou_auc"] for m in ("rayfronts", "spherical_semfronts", "unidirectional_semfronts")}
    assert mi["rayfronts"] > 0 and mi["rayfronts"] == mi["spherical_semfronts"] == mi["unidirectional_semfronts"]
    # beyond-range rays cut search volume: RayFronts above Semantic Voxels
    assert top["10m"]["rayfronts"]["scvr_auc"] > top["10m"]["semantic_voxels"]["scvr_auc"]
    assert any(r["evidence"] for r in rows if r["method"] == "rayfronts" and r["depth_limit"] == 10.0)


def test_shared_semantic_voxels_equal_separate_map(world):
    """Semantic Voxels evaluated on the RayFronts map (share_maps) is exact: the separate
    semantic_voxels map has the same voxels and occupancy."""
    from apps.evaluation.srchvol import method_map_config
    from encoders import EncoderConfig, make_encoder
    from semantic_map.map import RayFrontsMap

    cfg = SrchvolConfig()
    enc = make_encoder(EncoderConfig(kind="label"), world.classes)
    hw = (32, 32)
    K = world.camera(hw, 90)
    maps = [RayFrontsMap(method_map_config(cfg, m, 10.0, hw[1]), enc.feature_dim, "label")
            for m in ("rayfronts", "semantic_voxels")]
    for p in world.trajectory("ground", 40)[:10]:
        r = world.render(p, K, hw)
        f = enc.encode(None, r.labels)
        for mp in maps:
            mp.integrate(p, K, r.depth, r.rgb, f, None)
    for mp in maps:
        mp.flush()
    a, b = (mp.voxels() for mp in maps)
    assert a.xyz.shape[0] > 0 and maps[0].n_rays() > 0 and maps[1].n_rays() == 0
    ia = torch.argsort(a.xyz[:, 0] * 1e6 + a.xyz[:, 1] * 1e3 + a.xyz[:, 2])
    ib = torch.argsort(b.xyz[:, 0] * 1e6 + b.xyz[:, 1] * 1e3 + b.xyz[:, 2])
    torch.testing.assert_close(a.xyz[ia], b.xyz[ib])
    torch.testing.assert_close(a.features[ia], b.features[ib])
    oa, ob = maps[0].occupancy_view().active(), maps[1].occupancy_view().active()
    assert torch.equal(oa[0], ob[0]) and torch.equal(oa[1], ob[1])


def test_semseg_synthetic_label_encoder(tmp_path, world):
    cfg = merge(SemsegConfig(), dict(source=dict(n_frames=8, resolution="48x64"), vox=0.5, depth_range=20.0,
                                     progress=False, encoder=dict(label_stride=2)))
    s = run_semseg(cfg, tmp_path, world=world)
    top = json.loads((tmp_path / "summary.json").read_text())
    assert set(top) >= {"miou", "fmiou", "acc", "miou_bg", "fmiou_bg", "acc_bg", "per_class"}
    for k in ("miou", "fmiou", "acc", "miou_bg", "fmiou_bg", "acc_bg"):
        assert 0.0 <= top[k] <= 1.0
    # the label encoder is near-oracle
    assert s["miou_bg"] >= 0.6 and s["acc_bg"] >= 0.8 and s["miou"] >= 0.5
    assert "building" in s["per_class"] and s["per_class"]["ground"]["background"]


# ----------------------------------------------------------------------------- TartanAir fixture
def _write_tartanair(root, world, n=8, hw=(64, 64)):
    """Synthetic-world frames in the TartanAir v2 on-disk format (640×640 native, NED/FRD)."""
    import cv2
    from scipy.spatial.transform import Rotation

    traj = root / "Synth" / "Data_ground" / "P0000"
    cam = "lcam_front"
    K = world.camera(hw, 90)
    up = 640 // hw[0]
    W = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], float)      # ENU -> NED
    B = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float)       # FRD coords -> RDF coords
    lines = []

    def rep(a):
        return np.repeat(np.repeat(a, up, 0), up, 1)

    for i, p in enumerate(world.trajectory("ground", 3 * n)[::3][:n]):
        r = world.render(p, K, hw)
        d = rep(np.where(np.isfinite(r.depth), r.depth, 10000.0).astype("<f4"))
        rgba = np.frombuffer(d.tobytes(), np.uint8).reshape(*d.shape, 4)
        for sub in ("image", "depth", "seg"):
            (traj / f"{sub}_{cam}").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(traj / f"depth_{cam}" / f"{i:06d}_{cam}_depth.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
        cv2.imwrite(str(traj / f"image_{cam}" / f"{i:06d}_{cam}.png"), cv2.cvtColor(rep(r.rgb), cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(traj / f"seg_{cam}" / f"{i:06d}_{cam}_seg.png"), rep(r.labels.astype(np.uint8)))
        Rn = W @ p[:3, :3] @ B
        q = Rotation.from_matrix(Rn).as_quat()
        lines.append(" ".join(repr(float(v)) for v in [*(W @ p[:3, 3]), *q]))
    (traj / f"pose_{cam}.txt").write_text("\n".join(lines) + "\n")
    (root / "Synth" / "seg_label_map.json").write_text(
        json.dumps({"name_map": {c: i for i, c in enumerate(world.classes)}}))
    return root


def test_semseg_tartanair_fixture(tmp_path, world):
    root = _write_tartanair(tmp_path / "tartan", world, n=6)
    from edge.sources import SourceConfig, open_source
    src = open_source(SourceConfig(kind="tartanair", path=str(root), scene="Synth", sequence="P0000",
                                   resolution="64x64"))
    f0 = next(iter(src))
    np.testing.assert_allclose(f0.pose, world.trajectory("ground", 24)[0], atol=1e-6)   # the fixture is right
    assert src.class_names[:4] == world.classes[:4]
    cfg = merge(SemsegConfig(), dict(source=dict(kind="tartanair", path=str(root), scene="Synth", sequence="P0000",
                                                 resolution="64x64"), vox=0.5, depth_range=20.0, progress=False,
                                     encoder=dict(label_stride=2)))
    s = run_semseg(cfg, tmp_path / "out")
    assert s["miou_bg"] >= 0.6 and s["acc_bg"] >= 0.8
    assert all(0 <= s[k] <= 1 for k in ("miou", "fmiou", "acc"))


def test_report_and_cli(sv_run, tmp_path, world):
    from apps.cli import build_parser
    from apps.evaluation import cli

    out, _ = sv_run
    ss = tmp_path / "ss"
    cfg = merge(SemsegConfig(), dict(source=dict(n_frames=6, resolution="32x40"), vox=1.0, progress=False, k=0))
    run_semseg(cfg, ss, world=world)
    page = tmp_path / "page" / "results.md"
    parser = build_parser("eval")
    args = parser.parse_args(["eval", "report", str(out), str(ss), "--out", str(page)])
    assert cli.run(args) == 0
    text = page.read_text()
    assert "Online search volume" in text and "3D semantic segmentation" in text
    assert "label" in text and "](../" in text          # encoder stated; plots linked relatively
    # bad override -> clear error, exit code 2
    args = parser.parse_args(["eval", "srchvol", "--out", str(tmp_path / "x"), "vox_size=2"])
    assert cli.run(args) == 2
    args = parser.parse_args(["eval", "srchvol", "--out", str(tmp_path / "x"), "--methods", "rayfronts,nope"])
    assert cli.run(args) == 2
