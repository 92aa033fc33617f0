"""Benchmarks with a language-head encoder (tiny random NARADIO checkpoint + tiny random
SigLIP text tower, written here) and ``rayfronts eval semseg`` on the ScanNet and NICE-SLAM
Replica on-disk formats (fixtures written here in those formats). Random weights: these
tests check the plumbing and well-formed outputs, not the numbers."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from common.config import merge
from common.feature_space import FeatureSpaceError

pytestmark = pytest.mark.usefixtures("torch_two_threads")

LANG = 24           # SigLIP projection = the tiny head's output dim


# ----------------------------------------------------------------------------- tiny models
def _tiny_siglip(d, words):
    from tokenizers import Tokenizer, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast, SiglipTextConfig, SiglipTextModel

    vocab = {w: i for i, w in enumerate(["<pad>", "</s>", "<unk>"] + sorted(set(words)))}
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="<pad>", unk_token="<unk>",
                            eos_token="</s>").save_pretrained(d)
    cfg = SiglipTextConfig(vocab_size=len(vocab), hidden_size=32, intermediate_size=64, num_hidden_layers=1,
                           num_attention_heads=4, max_position_embeddings=16, projection_size=LANG,
                           pad_token_id=0, eos_token_id=1, bos_token_id=None)
    torch.manual_seed(0)
    SiglipTextModel(cfg).save_pretrained(d)
    return d


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    from encoders.radio import RadioConfig, save_flat
    from encoders.random_init import random_checkpoint

    d = tmp_path_factory.mktemp("models")
    rc = RadioConfig(embed_dim=32, depth=1, num_heads=2, pos_grid=8, mlp_hidden=64)
    radio = save_flat(random_checkpoint(rc, head_hidden=32, head_out=LANG), d / "radio.safetensors")
    words = "ground building tree car fence chimney street lamp bench rock sky wall table floor none".split()
    return dict(radio=str(radio), siglip=str(_tiny_siglip(d / "siglip_text", words)), dir=str(d))


def _enc_cfg(models):
    return dict(kind="naradio", model="auto", checkpoint=models["radio"])


@pytest.fixture(scope="module")
def world():
    from synthetic_world import World
    return World.generate(0)


def test_language_plumbing(models):
    """Class texts come from the SigLIP text model; map features go through the head after
    averaging (independently: head(mean) vs the similarity callable)."""
    from apps.evaluation.language import eval_language, text_model_dir
    from encoders import EncoderConfig, make_encoder
    from encoders.text.siglip import SiglipText

    enc = make_encoder(EncoderConfig(**_enc_cfg(models)))
    names = ["car", "tree", "wall"]
    lang = eval_language(enc, names, model_dir=models["siglip"])
    assert lang.text_model == "siglip" and lang.text.shape == (3, LANG) and lang.similarity is not None
    torch.testing.assert_close(lang.text, SiglipText(models["siglip"]).encode(names))
    feats = torch.randn(5, 4, 32)                       # 5 voxels, 4 observations each
    avg = feats.mean(1)
    with torch.inference_mode():
        want = torch.nn.functional.normalize(enc.language_head(avg), dim=1) @ lang.text.T
        late = torch.nn.functional.normalize(enc.language_head(feats).mean(1), dim=1) @ lang.text.T
    torch.testing.assert_close(lang.similarity(avg, lang.text), want.T, rtol=1e-4, atol=1e-5)
    # the head does not commute with averaging: averaging language features differs
    assert not torch.allclose(want, late, atol=1e-6)
    # default text-model directory: <encoder.model_dir>/siglip_text
    enc.cfg.model_dir = models["dir"]
    assert text_model_dir(enc) == str(__import__("pathlib").Path(models["dir"]) / "siglip_text")
    assert eval_language(enc, names).text.shape == (3, LANG)
    from common.model_files import ModelFileError
    enc.cfg.model_dir = models["dir"] + "/nowhere"
    with pytest.raises(ModelFileError, match="siglip_text"):
        eval_language(enc, names)


def test_language_dim_mismatch(models, tmp_path):
    from apps.evaluation.language import eval_language
    from encoders import EncoderConfig, make_encoder

    enc = make_encoder(EncoderConfig(**_enc_cfg(models)))
    other = tmp_path / "other"
    import shutil
    shutil.copytree(models["siglip"], other)
    cfg = json.loads((other / "config.json").read_text())
    cfg["projection_size"] = 16
    (other / "config.json").write_text(json.dumps(cfg))
    from transformers import SiglipTextConfig, SiglipTextModel
    SiglipTextModel(SiglipTextConfig(**{k: v for k, v in cfg.items() if k in SiglipTextConfig().to_dict()})
                    ).save_pretrained(other)
    with pytest.raises(FeatureSpaceError, match="16-d"):
        eval_language(enc, ["car"], model_dir=str(other))


def test_srchvol_naradio(models, world, tmp_path):
    from apps.evaluation.srchvol import ALL_METHODS, SrchvolConfig, applicable, run_srchvol

    cfg = merge(SrchvolConfig(), dict(source=dict(n_frames=8, resolution="48x48"), every=4, depth_limits=[0.0, 10.0],
                                      gt_range=20.0, progress=False, plots=False, encoder=_enc_cfg(models),
                                      text_model_dir=models["siglip"], map={"max_rays_per_frame": 200}))
    summary = run_srchvol(cfg, tmp_path, world=world)
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert info["encoder"] == "naradio" and info["text_model"] == "siglip" and info["language_head"] is True
    rows = json.loads((tmp_path / "steps.json").read_text())
    for dk, d in (("0m", 0.0), ("10m", 10.0)):
        for m in ALL_METHODS:
            s = summary[dk][m]
            if not applicable(m, d):
                assert s is None
                continue
            assert set(s) == {"miou_auc", "scv_auc", "recall_auc", "scvr_auc"}
            assert all(v is not None and 0.0 <= v <= 1.0 for v in s.values()), (dk, m, s)
            assert {r["step"] for r in rows if r["method"] == m and r["depth_limit"] == d} == {4, 8}
    assert any(r["n_rays"] > 0 for r in rows if r["method"] == "rayfronts")
    assert "| RayFronts |" in (tmp_path / "table.md").read_text()


def test_semseg_naradio_synthetic(models, world, tmp_path):
    from apps.evaluation.semseg import SemsegConfig, run_semseg

    cfg = merge(SemsegConfig(), dict(source=dict(n_frames=4, resolution="48x64"), vox=0.5, depth_range=20.0,
                                     progress=False, encoder=_enc_cfg(models), text_model_dir=models["siglip"]))
    s = run_semseg(cfg, tmp_path, world=world)
    for k in ("miou", "fmiou", "acc", "miou_bg", "fmiou_bg", "acc_bg"):
        assert 0.0 <= s[k] <= 1.0
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert info["language_head"] is True and info["n_pred_voxels"] > 0


# ----------------------------------------------------------------------------- dataset fixtures
def _plane_depth(h, w, z):
    return np.full((h, w), z, np.float64)


def _pose(i):
    """Camera i: at x = 0.1·i, looking along world +y (RDF camera, z-up world)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])    # columns: right=+x, down=-z, fwd=+y
    T[:3, 3] = [0.1 * i, 0.0, 1.0]
    return T


SCANNET_K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])


def _write_scannet(root, n=5, h=48, w=64):
    scene = root / "scene0000_00"
    for sub in ("color", "depth", "pose", "intrinsic", "label-filt"):
        (scene / sub).mkdir(parents=True)
    K4 = np.eye(4)
    K4[:3, :3] = SCANNET_K
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", K4, fmt="%f")
    for i in range(n):
        rgb = np.zeros((2 * h, 2 * w, 3), np.uint8)
        rgb[:h] = (200, 60, 40)
        rgb[h:] = (90, 90, 200)
        cv2.imwrite(str(scene / "color" / f"{i}.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(scene / "depth" / f"{i}.png"), np.full((h, w), 2000, np.uint16))     # mm
        lab = np.zeros((2 * h, 2 * w), np.uint16)
        lab[:h] = 5         # raw 5 -> NYU40 7 table (top half)
        lab[h:] = 1         # raw 1 -> NYU40 1 wall
        cv2.imwrite(str(scene / "label-filt" / f"{i}.png"), lab)
        np.savetxt(scene / "pose" / f"{i}.txt", _pose(i), fmt="%.9f")
    (root / "scannetv2-labels.combined.tsv").write_text(
        "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\tnyu40class\n"
        "1\twall\twall\t1\t1\t12\twall\twall\n"
        "5\ttable\ttable\t1\t7\t10\ttable\ttable\n")
    return scene


REPLICA_CAM = {"w": 64, "h": 48, "fx": 40.0, "fy": 40.0, "cx": 31.5, "cy": 23.5, "scale": 6553.5}


def _write_replica(root, n=5):
    root.mkdir(parents=True)
    (root / "cam_params.json").write_text(json.dumps({"camera": REPLICA_CAM}))
    res = root / "room0" / "results"
    res.mkdir(parents=True)
    h, w = REPLICA_CAM["h"], REPLICA_CAM["w"]
    with open(root / "room0" / "traj.txt", "w") as fh:
        for i in range(n):
            fh.write(" ".join(f"{v:.12e}" for v in _pose(i).ravel()) + "\n")
    rng = np.random.default_rng(0)
    for i in range(n):
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        cv2.imwrite(str(res / f"frame{i:06d}.jpg"), rgb)
        cv2.imwrite(str(res / f"depth{i:06d}.png"), np.full((h, w), int(round(2.0 * 6553.5)), np.uint16))
    # external GT: the wall plane y = 2 m seen by the cameras; z > 1 m "painting", below "wall"
    xs, zs = np.meshgrid(np.arange(-1.5, 2.0, 0.02), np.arange(-0.2, 2.2, 0.02))
    xyz = np.stack([xs.ravel(), np.full(xs.size, 2.0), zs.ravel()], 1)
    labels = np.where(xyz[:, 2] > 1.0, 2, 1)
    return root, xyz, labels


def _cli(argv):
    from apps.cli import build_parser
    from apps.evaluation import cli
    args = build_parser("eval").parse_args(["eval", "semseg", "--no-progress", *argv])
    return cli.run(args)


def test_semseg_cli_scannet(tmp_path):
    scene = _write_scannet(tmp_path / "scannet")
    out = tmp_path / "out"
    assert _cli(["--source", "scannet", "--source-path", str(scene), "--vox", "0.1", "--out", str(out),
                 "depth_range=5.0", "encoder.label_stride=2"]) == 0
    s = json.loads((out / "summary.json").read_text())
    info = json.loads((out / "run_info.json").read_text())
    assert info["source"].startswith("scannet") and info["n_gt_voxels"] > 0 and info["frames"] == 5
    assert set(s["per_class"]) == {"wall", "table"}
    assert s["per_class"]["wall"]["background"] and not s["per_class"]["table"]["background"]
    # label encoder = near-oracle: both classes found
    assert s["acc_bg"] >= 0.8 and s["miou_bg"] >= 0.6 and s["miou"] >= 0.6


def _write_ply(path, xyz, labels, binary):
    head = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\ncomment gt\n"
            f"element vertex {len(xyz)}\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty int label\nelement face 0\nproperty list uchar int vertex_indices\n"
            "end_header\n")
    if binary:
        rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("label", "<i4")])
        rec["x"], rec["y"], rec["z"], rec["label"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], labels
        path.write_bytes(head.encode() + rec.tobytes())
    else:
        body = "\n".join(f"{x:.6f} {y:.6f} {z:.6f} 7 {int(lb)}" for (x, y, z), lb in zip(xyz, labels, strict=True))
        path.write_text(head + body + "\n")


def test_semseg_cli_replica_external_gt(tmp_path, models):
    from apps.evaluation.gt_points import load_labelled_points

    root, xyz, labels = _write_replica(tmp_path / "replica")
    names = ["none", "wall", "painting"]
    np.savez(tmp_path / "gt.npz", xyz=xyz, labels=labels, class_names=np.array(names))
    for binary in (True, False):
        _write_ply(tmp_path / f"gt{int(binary)}.ply", xyz, labels, binary)
        px, pl, pn = load_labelled_points(tmp_path / f"gt{int(binary)}.ply")
        np.testing.assert_allclose(px, xyz.astype(np.float32), atol=1e-6)
        np.testing.assert_array_equal(pl, labels)
        assert pn is None
    opts = ["--source", "replica", "--source-path", str(root), "--scene", "room0", "--vox", "0.1"]
    common = ["depth_range=5.0", "encoder.kind=naradio", "encoder.model=auto", f"encoder.checkpoint={models['radio']}",
              f"text_model_dir={models['siglip']}", "k=1"]
    # frames carry no labels: without external GT a clear error
    assert _cli([*opts, "--out", str(tmp_path / "x"), *common]) == 2
    outs = {}
    for gt, extra in (("npz", []), ("ply", ["class_names=[none, wall, painting]"])):
        out = tmp_path / f"out_{gt}"
        f = tmp_path / ("gt.npz" if gt == "npz" else "gt1.ply")
        assert _cli([*opts, "--out", str(out), *common, f"gt_points={f}", *extra]) == 0
        outs[gt] = json.loads((out / "summary.json").read_text())
        info = json.loads((out / "run_info.json").read_text())
        assert info["gt"] == "points" and info["class_names"] == names and info["n_gt_voxels"] > 0
        assert info["source"].startswith("replica") and info["language_head"] is True
    s = outs["npz"]
    assert set(s["per_class"]) == {"wall", "painting"}
    for k in ("miou", "fmiou", "acc", "miou_bg", "fmiou_bg", "acc_bg"):
        assert s[k] is None or 0.0 <= s[k] <= 1.0
    # both classes' GT voxels are evaluated (float32 PLY points may fall in neighbouring voxels)
    for o in outs.values():
        assert all(o["per_class"][c]["tp"] + o["per_class"][c]["fn"] > 0 for c in ("wall", "painting"))


def test_voxelize_majority_and_bad_files(tmp_path):
    from apps.evaluation.gt_points import load_labelled_points, voxelize_labels

    xyz = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [1.5, 0.1, 0.1], [1.6, 0.1, 0.1],
                    [2.5, 0, 0], [-0.5, 0, 0]])
    lab = np.array([3, 2, 2, 4, 1, 0, 5])
    c, lb = voxelize_labels(xyz, lab, 1.0)
    got = {tuple(np.floor(p).astype(int)): int(v) for p, v in zip(c, lb, strict=True)}
    assert got == {(0, 0, 0): 2, (1, 0, 0): 1, (-1, 0, 0): 5}      # majority; tie -> smallest; 0 ignored
    np.testing.assert_allclose(c[np.argsort(c[:, 0])][0], [-0.5, 0.5, 0.5])
    with pytest.raises(FileNotFoundError):
        load_labelled_points(tmp_path / "absent.npz")
    np.savez(tmp_path / "bad.npz", points=xyz)
    with pytest.raises(ValueError, match="xyz"):
        load_labelled_points(tmp_path / "bad.npz")
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(ValueError, match="label"):
        load_labelled_points(tmp_path / "bad.ply")
    assert math.isfinite(float(c.sum()))
