"""Dataset frame sources (Replica, ScanNet, TartanAir) on small fixtures written here in the
real on-disk formats; expectations are written by hand or computed independently."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from edge.sources import SourceConfig, SourceError, open_source
from edge.sources.imageops import decode_rgba_float32, encode_float32_rgba, resize_nearest

RNG = np.random.default_rng(0)


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _write_u16(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert img.dtype == np.uint16
    assert cv2.imwrite(str(path), img)


def _smooth_rgb(h, w, k=0):
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([(u * 7 + k) % 256, (v * 5) % 256, ((u + v) * 3) % 256], -1).astype(np.uint8)


# --------------------------------------------------------------------------- TartanAir

def _rgba_depth_png(path: Path, depth: np.ndarray) -> None:
    """Pack float32 little-endian bytes into R, G, B, A (independently of the source code)."""
    rgba = np.frombuffer(depth.astype("<f4").tobytes(), dtype=np.uint8).reshape(*depth.shape, 4)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))


S = np.sqrt(0.5)
# tx ty tz qx qy qz qw in NED with FRD body.
TARTAN_POSES = [
    [1.0, 2.0, 3.0, 0, 0, 0, 1],  # facing north, level
    [0.0, 0.0, -5.0, 0, 0, S, S],  # yaw +90° about NED down: facing east, 5 m up
    [0.0, 0.0, 0.0, np.nan, 0, 0, 1],  # broken row: skipped
    [4.0, 0.0, 0.0, 0, 0.25881904510252074, 0, 0.9659258262890683],  # +30° about FRD y (right): nose up
]


def _expected_tartan(i):
    """Hand-written RDF camera-to-world poses in ENU for TARTAN_POSES."""
    T = np.eye(4)
    if i == 0:  # right = east, down = -z, forward = north; NED (1,2,3) = ENU (2,1,-3)
        T[:3, :3] = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).T
        T[:3, 3] = [2, 1, -3]
    elif i == 1:  # right = south, down = -z, forward = east; 5 m up
        T[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]]).T
        T[:3, 3] = [0, 0, 5]
    elif i == 3:  # facing north, tilted up 30°: forward = (0, cos30, sin30), down = (0, sin30, -cos30)
        c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
        T[:3, :3] = np.array([[1, 0, 0], [0, s, -c], [0, c, s]]).T
        T[:3, 3] = [0, 4, 0]
    return T


@pytest.fixture(scope="module")
def tartan_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tartan")
    traj = root / "Town" / "Data_ground" / "P0001"
    cam = "lcam_front"
    h = w = 640
    for i in range(len(TARTAN_POSES)):
        _write_rgb(traj / f"image_{cam}" / f"{i:06d}_{cam}.png", _smooth_rgb(h, w, i))
        d = np.full((h, w), 3.0 + i, dtype=np.float32)
        d[0, 0] = 0.0  # no measurement
        d[1, 1] = 150.0  # beyond the 100 m cutoff
        d[2, 2] = 10000.0  # TartanAir sky
        d[3, 3] = 99.5
        d[4, 4] = 0.123456789
        _rgba_depth_png(traj / f"depth_{cam}" / f"{i:06d}_{cam}_depth.png", d)
        seg = np.zeros((h, w), np.uint8)
        seg[:, w // 2:] = 7
        (traj / f"seg_{cam}").mkdir(exist_ok=True)
        cv2.imwrite(str(traj / f"seg_{cam}" / f"{i:06d}_{cam}_seg.png"), seg)
    (traj / f"pose_{cam}.txt").write_text("\n".join(" ".join(repr(float(v)) for v in p) for p in TARTAN_POSES) + "\n")
    (root / "Town" / "seg_label_map.json").write_text(json.dumps({"name_map": {"sky": 0, "tree": 7, "road": 3}}))
    return root


def test_rgba_float_packing_roundtrip():
    d = RNG.normal(size=(5, 7)).astype(np.float32) * 100
    d[0, 0], d[0, 1] = np.inf, np.nan
    back = decode_rgba_float32(encode_float32_rgba(d))
    np.testing.assert_array_equal(back.view(np.uint32), d.view(np.uint32))


def test_tartanair_depth_poses_labels(tartan_root):
    src = open_source(SourceConfig(kind="tartanair", path=str(tartan_root), scene="Town", sequence="P0001"))
    assert len(src) == 3 and src.skipped and sum(src.skipped.values()) == 1
    np.testing.assert_allclose(src.intrinsics, [[320, 0, 320], [0, 320, 320], [0, 0, 1]])
    assert src.class_names[7] == "tree" and src.class_names[3] == "road"
    assert "ENU" in src.world_frame
    frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 1, 3]
    assert [f.seq for f in frames] == [0, 1, 2]
    for f in frames:
        i = f.meta["index"]
        np.testing.assert_allclose(f.pose, _expected_tartan(i), atol=1e-9)
        assert f.depth.dtype == np.float32 and f.depth.shape == (640, 640)
        assert np.isnan(f.depth[0, 0])
        assert f.depth[1, 1] == np.inf and f.depth[2, 2] == np.inf
        assert f.depth[3, 3] == np.float32(99.5)
        assert f.depth[4, 4] == np.float32(0.123456789)
        assert f.depth[100, 100] == np.float32(3.0 + i)
        assert f.labels.dtype == np.int32 and f.labels[0, 0] == 0 and f.labels[0, -1] == 7
        assert f.rgb.shape == (640, 640, 3) and f.robot == "robot1"


def test_tartanair_pose_physics(tartan_root):
    """Independent check: a world point straight north of frame 0 projects on the image centre
    row/column, and a point below it projects lower in the image (v grows downward)."""
    f = next(iter(open_source(SourceConfig(kind="tartanair", path=str(tartan_root), scene="Town", sequence="P0001"))))
    w2c = np.linalg.inv(f.pose)
    eye = f.pose[:3, 3]
    for p_world, expect in (([0, 10, 0], "centre"), ([0, 10, -2], "below")):
        pc = w2c[:3, :3] @ (eye + np.array(p_world)) + w2c[:3, 3]
        u = f.intrinsics[0, 0] * pc[0] / pc[2] + f.intrinsics[0, 2]
        v = f.intrinsics[1, 1] * pc[1] / pc[2] + f.intrinsics[1, 2]
        assert pc[2] > 0
        assert u == pytest.approx(320)
        assert v == pytest.approx(320) if expect == "centre" else v > 320


def test_tartanair_cutoff_resolution_limit(tartan_root):
    src = open_source(SourceConfig(kind="tartanair", path=str(tartan_root / "Town" / "Data_ground" / "P0001"),
                                   depth_cutoff=50.0, resolution="320x320", depth_limit=3.5, max_frames=2))
    assert len(src) == 2
    np.testing.assert_allclose(src.intrinsics, [[160, 0, 160], [0, 160, 160], [0, 0, 1]])
    f0, f1 = list(src)
    assert f0.depth.shape == (320, 320) and f0.labels.shape == (320, 320) and f0.rgb.shape == (320, 320, 3)
    assert f0.depth[10, 10] == np.float32(3.0)  # 3.0 <= limit 3.5
    assert f1.depth[10, 10] == np.inf  # 4.0 > depth limit
    np.testing.assert_array_equal(f0.intrinsics, src.intrinsics)


def test_tartanair_missing(tmp_path, tartan_root):
    with pytest.raises(SourceError, match="P9999"):
        open_source(SourceConfig(kind="tartanair", path=str(tartan_root), scene="Town", sequence="P9999"))
    with pytest.raises(SourceError, match="image_rcam_front"):
        open_source(SourceConfig(kind="tartanair", path=str(tartan_root), scene="Town", sequence="P0001",
                                 camera="rcam_front"))


# --------------------------------------------------------------------------- ScanNet

SCANNET_K = np.array([[577.59, 0, 318.9], [0, 578.73, 242.68], [0, 0, 1]])


def _scannet_pose(i):
    T = np.eye(4)
    a = 0.1 * i
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [i, 2.0 * i, 1.5]
    return T


@pytest.fixture(scope="module")
def scannet_scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scannet")
    scene = root / "scene0000_00"
    h, w = 48, 64
    for sub in ("color", "depth", "pose", "intrinsic", "label-filt"):
        (scene / sub).mkdir(parents=True)
    K4 = np.eye(4)
    K4[:3, :3] = SCANNET_K
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", K4, fmt="%f")
    for i in range(6):
        _write_rgb(scene / "color" / f"{i}.jpg", _smooth_rgb(2 * h, 2 * w, i))  # colour at 2× depth size
        d = np.full((h, w), 1000 + 250 * i, np.uint16)
        d[:5, :5] = 0
        d[10, 20] = 65535
        _write_u16(scene / "depth" / f"{i}.png", d)
        lab = np.zeros((2 * h, 2 * w), np.uint16)
        lab[: h, :] = 5  # raw id 5 → nyu 7 (table)
        lab[h:, :] = 1  # raw id 1 → nyu 1 (wall)
        _write_u16(scene / "label-filt" / f"{i}.png", lab)
        pose = _scannet_pose(i)
        if i == 2:
            pose = np.full((4, 4), -np.inf)
        np.savetxt(scene / "pose" / f"{i}.txt", pose, fmt="%.9f")
    (root / "scannetv2-labels.combined.tsv").write_text(
        "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\tnyu40class\n"
        "1\twall\twall\t1\t1\t12\twall\twall\n"
        "5\ttable\ttable\t1\t7\t10\ttable\ttable\n")
    return scene


def test_scannet_reads_and_skips_inf_pose(scannet_scene):
    src = open_source(SourceConfig(kind="scannet", path=str(scannet_scene)))
    assert len(src) == 5 and sum(src.skipped.values()) == 1
    assert "pose" in next(iter(src.skipped))
    np.testing.assert_allclose(src.intrinsics, SCANNET_K)
    assert src.class_names[7] == "table" and src.class_names[1] == "wall" and src.class_names[0] == "none"
    frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 1, 3, 4, 5]
    for f in frames:
        i = f.meta["index"]
        np.testing.assert_allclose(f.pose, _scannet_pose(i), atol=1e-8)
        assert f.depth.shape == (48, 64) and f.rgb.shape == (96, 128, 3)
        assert np.isnan(f.depth[:5, :5]).all()
        assert f.depth[10, 20] == np.float32(65.535)
        assert f.depth[30, 30] == np.float32((1000 + 250 * i) / 1000.0)
        assert f.labels.shape == (48, 64)
        assert (f.labels[:24] == 7).all() and (f.labels[24:] == 1).all()
        assert f.stamp == pytest.approx(i / 30.0)


def test_scannet_frame_skip_and_missing(scannet_scene, tmp_path):
    src = open_source(SourceConfig(kind="scannet", path=str(scannet_scene.parent), scene=scannet_scene.name,
                                   frame_skip=1))
    assert [f.meta["index"] for f in src] == [0, 4]  # 2 is the -inf pose
    with pytest.raises(SourceError, match="scene0999_00"):
        open_source(SourceConfig(kind="scannet", path=str(scannet_scene.parent), scene="scene0999_00"))
    bad = tmp_path / "scene"
    for sub in ("color", "depth", "pose"):
        (bad / sub).mkdir(parents=True)
    with pytest.raises(SourceError, match="intrinsic_depth.txt"):
        open_source(SourceConfig(kind="scannet", path=str(bad)))


def test_scannet_corrupt_frame_skipped_and_counted(scannet_scene, tmp_path, caplog):
    import shutil

    scene = tmp_path / scannet_scene.name
    shutil.copytree(scannet_scene, scene)
    (scene / "color" / "3.jpg").write_bytes(b"\xff\xd8 not a jpeg at all")      # undecodable colour
    d = (scene / "depth" / "4.png").read_bytes()
    (scene / "depth" / "4.png").write_bytes(d[: len(d) // 2])                   # truncated depth PNG
    src = open_source(SourceConfig(kind="scannet", path=str(scene)))
    with caplog.at_level("ERROR"):
        frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 1, 5]   # 2: -inf pose; 3, 4: corrupt
    assert [f.seq for f in frames] == [0, 1, 2]                    # seq stays contiguous
    assert src.skipped["corrupt frame"] == 2
    lines = [r.getMessage() for r in caplog.records if "skipping frame" in r.getMessage()]
    assert len(lines) == 2 and "3.jpg" in lines[0] and "4.png" in lines[1]


# --------------------------------------------------------------------------- Replica

REPLICA_CAM = {"w": 40, "h": 24, "fx": 20.0, "fy": 20.0, "cx": 19.5, "cy": 11.5, "scale": 6553.5}


def _replica_pose(i):
    T = np.eye(4)
    a = 0.3 * i
    T[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    T[:3, 3] = [0.5 * i, -1.0, 0.25]
    return T


@pytest.fixture(scope="module")
def replica_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("replica")
    (root / "cam_params.json").write_text(json.dumps({"camera": REPLICA_CAM}))
    res = root / "room0" / "results"
    res.mkdir(parents=True)
    n = 7
    with open(root / "room0" / "traj.txt", "w") as fh:
        for i in range(n):
            fh.write(" ".join(f"{v:.12e}" for v in _replica_pose(i).ravel()) + "\n")
    for i in range(n):
        _write_rgb(res / f"frame{i:06d}.jpg", _smooth_rgb(24, 40, i))
        d = (np.arange(24 * 40).reshape(24, 40) * 37 + 1000 * i).astype(np.uint16)  # distinct values per pixel
        _write_u16(res / f"depth{i:06d}.png", d)
    return root


def _replica_depth(i):
    raw = (np.arange(24 * 40).reshape(24, 40) * 37 + 1000 * i).astype(np.uint16)
    return raw.astype(np.float32) / np.float32(6553.5)


def test_replica_reads(replica_root):
    src = open_source(SourceConfig(kind="replica", path=str(replica_root), scene="room0"))
    assert len(src) == 7 and not src.skipped
    np.testing.assert_allclose(src.intrinsics, [[20, 0, 19.5], [0, 20, 11.5], [0, 0, 1]])
    for f in src:
        i = f.meta["index"]
        np.testing.assert_allclose(f.pose, _replica_pose(i), atol=1e-10)
        exp = _replica_depth(i)
        exp[exp == 0] = np.nan
        np.testing.assert_array_equal(f.depth, exp)
        assert f.labels is None and src.class_names is None
        assert f.rgb.shape == (24, 40, 3)


def test_replica_skip_max_limit_resolution(replica_root):
    cfg = SourceConfig(kind="replica", path=str(replica_root / "room0"), frame_skip=2, max_frames=2,
                       depth_limit=2.0, resolution="12x20", robot="r2")
    src = open_source(cfg)
    assert len(src) == 2
    K = src.intrinsics
    np.testing.assert_allclose(K, [[10, 0, 9.75], [0, 10, 5.75], [0, 0, 1]])
    frames = list(src)
    assert [f.meta["index"] for f in frames] == [0, 3] and [f.seq for f in frames] == [0, 1]
    assert all(f.robot == "r2" for f in frames)
    for f in frames:
        full = _replica_depth(f.meta["index"])
        exp = full[1::2, 1::2].copy()  # half size, nearest at pixel centres = odd rows/cols
        exp[exp == 0] = np.nan
        exp[np.isfinite(exp) & (exp > 2.0)] = np.inf
        np.testing.assert_array_equal(f.depth, exp)
        assert f.rgb.shape == (12, 20, 3)
        # Shrinking by 2 with the area filter = 2×2 block means of the decoded (lossy JPEG) image.
        full = cv2.cvtColor(cv2.imread(str(replica_root / "room0" / "results" / f"frame{f.meta['index']:06d}.jpg")),
                            cv2.COLOR_BGR2RGB).astype(np.float64)
        blocks = full.reshape(12, 2, 20, 2, 3).mean(axis=(1, 3))
        assert np.abs(f.rgb.astype(np.float64) - blocks).max() <= 1.0
    assert np.isinf(frames[1].depth).any() and np.isfinite(frames[1].depth).any()


def test_replica_missing(tmp_path, replica_root):
    with pytest.raises(SourceError, match="nowhere"):
        open_source(SourceConfig(kind="replica", path=str(tmp_path / "nowhere")))
    (tmp_path / "scene").mkdir()
    with pytest.raises(SourceError, match="cam_params.json"):
        open_source(SourceConfig(kind="replica", path=str(tmp_path), scene="scene"))
    src = open_source(SourceConfig(kind="replica", path=str(replica_root), scene="room0"))
    (replica_root / "room0" / "results" / "depth000006.png").rename(replica_root / "room0" / "gone.png")
    try:   # a frame whose file vanished is skipped and counted; the others still come
        got = [f.meta["index"] for f in src]
        assert 6 not in got and len(got) == len(src) - 1
        assert src.skipped["corrupt frame"] == 1
    finally:
        (replica_root / "room0" / "gone.png").rename(replica_root / "room0" / "results" / "depth000006.png")


def test_pose_text_files_and_dataset_dirs_name_the_problem(tmp_path):
    """Pose text files (Replica traj.txt, TartanAir pose_<cam>.txt): blank lines are skipped, a bad
    line is named as path:line with the expected layout; a missing dataset or scene directory is
    named with the source kind."""
    import re

    from edge.sources.replica import read_traj
    from edge.sources.tartanair import read_tartanair_poses

    traj = tmp_path / "traj.txt"
    pose = np.arange(16.0).reshape(4, 4)
    traj.write_text("\n" + " ".join(str(v) for v in pose.ravel()) + "\n\n" + " ".join(["1"] * 16) + "\n")
    assert np.array_equal(read_traj(traj), np.stack([pose, np.ones((4, 4))]))
    traj.write_text(" ".join(["1"] * 16) + "\n1 2 3\n")
    with pytest.raises(SourceError, match=re.escape(f"{traj}:2: expected 16 numbers (a row-major 4×4), got 3")):
        read_traj(traj)
    tq = tmp_path / "pose_lcam_front.txt"
    tq.write_text("0 0 0 0 0 0 1\n\n0 0 x 0 0 0 1\n")
    with pytest.raises(SourceError, match=re.escape(f"{tq}:3: not a list of numbers")):
        read_tartanair_poses(tq)
    tq.write_text("0 0 0 0 0 1\n")
    with pytest.raises(SourceError, match=re.escape(f"{tq}:1: expected 7 numbers 'tx ty tz qx qy qz qw', got 6")):
        read_tartanair_poses(tq)
    for kind in ("replica", "scannet"):
        with pytest.raises(SourceError, match=f"^{kind}: scene directory not found: .*nope$"):
            open_source(SourceConfig(kind=kind, path=str(tmp_path), scene="nope"))
    for kind in ("replica", "tartanair"):
        with pytest.raises(SourceError, match=f"^{kind}: directory not found: .*none$"):
            open_source(SourceConfig(kind=kind, path=str(tmp_path / "none")))


def test_bad_config_values(replica_root):
    with pytest.raises(SourceError, match="HxW"):
        open_source(SourceConfig(kind="replica", path=str(replica_root), scene="room0", resolution="big"))
    with pytest.raises(SourceError, match="unknown source kind"):
        open_source(SourceConfig(kind="kinect", path=str(replica_root)))


def test_resize_nearest_centres():
    a = np.arange(12).reshape(3, 4)
    np.testing.assert_array_equal(resize_nearest(a, (6, 8)), np.repeat(np.repeat(a, 2, 0), 2, 1))
    np.testing.assert_array_equal(resize_nearest(np.repeat(np.repeat(a, 2, 0), 2, 1), (3, 4)), a)


def test_progress_bar_yields_same_frames(replica_root, capsys):
    a = [f.depth for f in open_source(SourceConfig(kind="replica", path=str(replica_root), scene="room0",
                                                   max_frames=3))]
    b = [f.depth for f in open_source(SourceConfig(kind="replica", path=str(replica_root), scene="room0", max_frames=3,
                                                   progress=True))]
    assert len(a) == len(b) == 3
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert "replica:room0" in capsys.readouterr().err
