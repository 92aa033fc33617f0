"""The operator view's pure parts: heat colour scale, label thinning, cone outlines, the
blueprint (one query visible, the others hidden), and the loopback-bound rerun server."""
from __future__ import annotations

import math
import socket
import urllib.request

import numpy as np

from mapper.outputs.rerun_view import (
    HEAT_LUT,
    RerunServer,
    build_blueprint,
    colour_scale_image,
    cone_outlines,
    heat_colors,
    thin_labels,
)


def test_heat_colors_span_the_scale_and_report_the_range():
    cols, lo, hi = heat_colors([2.0, 6.0, 3.0, float("nan")])
    assert (lo, hi) == (2.0, 6.0)
    assert (cols[0] == HEAT_LUT[0]).all() and (cols[1] == HEAT_LUT[255]).all()
    assert (cols[2] == HEAT_LUT[64]).all()  # a quarter of the way: round(63.75) = 64
    assert (cols[3] == HEAT_LUT[0]).all()   # NaN drawn as the lowest score
    assert heat_colors([])[0].shape == (0, 3)
    img = colour_scale_image(lo, hi)
    assert img.shape[2] == 3 and (img[0, 0] == HEAT_LUT[0]).all() and (img[0, -1] == HEAT_LUT[255]).all()


def test_thin_labels_keeps_the_best_and_drops_neighbours():
    xyz = [[0, 0, 0], [1, 0, 0], [10, 0, 0], [10.5, 0, 0], [20, 0, 0]]
    scores = [0.9, 0.95, 0.5, 0.8, 0.1]
    assert thin_labels(xyz, scores, min_sep=3.0) == [1, 3, 4]
    assert thin_labels(xyz, scores, min_sep=3.0, max_labels=2) == [1, 3]


def test_cone_outlines_have_the_cone_angle_and_length():
    strips = cone_outlines([[1, 2, 3]], [[0, 0, 2]], half_angle_deg=30.0, length=10.0, n_lines=4, rings=(1.0,))
    assert len(strips) == 5
    for s in strips[:4]:  # generator lines: apex to the rim
        o, tip = s
        assert np.allclose(o, [1, 2, 3])
        v = tip - o
        assert math.isclose(math.degrees(math.acos(v[2] / np.linalg.norm(v))), 30.0, abs_tol=1e-3)
        assert math.isclose(v[2], 10.0, rel_tol=1e-5)
    ring = strips[4]
    assert np.allclose(ring[:, 2], 13.0, atol=1e-4)
    assert np.allclose(np.linalg.norm(ring[:, :2] - [1, 2], axis=1), 10 * math.tan(math.radians(30)), atol=1e-3)


def test_blueprint_shows_only_the_selected_query():
    bp = build_blueprint("vehicle", ["water_tower", "vehicle", "tree"], ["r1"], eye=([0, 0, 10], [0, 0, 0]))
    view3d, side = bp.root_container.contents
    assert view3d.origin == "world"
    hidden = {str(k): v for k, v in view3d.visualizer_overrides.items()}
    assert set(hidden) == {"world/queries/water_tower", "world/queries/tree"}  # the selected one stays visible
    assert all("visible=[False]" in repr(v) for v in hidden.values())
    assert [str(c.origin) for c in side.contents] == ["scale/vehicle/legend", "scale/vehicle/colour_scale",
                                                       "world/robots/r1/camera/image"]
    none = build_blueprint(None, [], [])  # before any query or robot: the 3D view alone
    assert [str(v.origin) for v in none.root_container.contents] == ["world"]


def test_rerun_server_binds_loopback_only():
    def free():
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    g, w = free(), free()
    srv = RerunServer(bind="127.0.0.1", grpc_port=g, serve_web=True, web_port=w)
    try:
        assert srv.url == f"rerun+http://127.0.0.1:{g}/proxy" and srv.web_url.startswith(f"http://127.0.0.1:{w}/?url=")
        with urllib.request.urlopen(f"http://127.0.0.1:{w}/", timeout=10) as r:
            assert r.status == 200 and b"rerun" in r.read().lower()
        import psutil

        conns = [c for c in psutil.net_connections("tcp") if c.status == "LISTEN" and c.laddr.port in (g, w)]
        assert conns and all(c.laddr.ip == "127.0.0.1" for c in conns), conns
    finally:
        srv.close()
    assert srv.proc.poll() is not None


def test_recording_file_carries_the_blueprint_and_the_layout(tmp_path):
    """A mapper recording (RerunLogger to a file) holds a blueprint store next to the data,
    read back by rerun's own CLI (``rerun rrd stats``), not by our code."""
    import subprocess
    from types import SimpleNamespace

    from mapper.outputs.rerun import RerunLogger
    from mapper.outputs.rerun_view import rerun_binary

    path = tmp_path / "m.rrd"
    lg = RerunLogger("rayfronts_test", file=str(path))
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    frame = SimpleNamespace(robot="r7", stamp=1.0, pose=np.eye(4), intrinsics=K,
                            rgb=np.full((48, 64, 3), 120, np.uint8), depth=np.full((48, 64), 3.0, np.float32))
    lg.log_frame(frame, 1)
    xyz = np.random.default_rng(0).uniform(0, 10, (200, 3)).astype(np.float32)
    lg.log_map(1, xyz, np.full((200, 3), 100, np.uint8), xyz[:5], xyz[:3], np.tile([[0, 0, 1.0]], (3, 1)), 0.5)
    lg.close()
    out = subprocess.run([rerun_binary(), "rrd", "stats", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    text = out.stdout
    for ent in ("/viewport", "/blueprint_panel", "/world/robots/r7/camera/image/rgb", "/world/map/voxels"):
        assert ent in text, f"{ent} not in the recording:\n{text[:3000]}"
    assert text.count("/view/") >= 2  # the 3D view and the camera view of robot r7


def test_query_cli_recording_uses_the_mappers_entity_paths(tmp_path):
    """``rayfronts query --rerun``: the answer under ``world/queries/<query>`` and the map's
    voxels under ``world/map/voxels``, the mapper's own paths (docs/conventions.md), read back
    by rerun's CLI; a path of the old ``world/query`` layout is absent."""
    import subprocess

    from common.messages import QueryResult
    from mapper.outputs.rerun_view import rerun_binary
    from query_client.cli import log_result_rerun

    r = QueryResult(query="water tower", cluster_xyz=np.ones((2, 3), np.float32),
                    cluster_size=np.array([3, 4], np.int32), cluster_extent=np.ones((2, 3), np.float32),
                    cluster_score=np.array([0.9, 0.5], np.float32), ray_origin=np.zeros((1, 3), np.float32),
                    ray_direction=np.array([[1.0, 0, 0]], np.float32), ray_score=np.array([0.7], np.float32))
    path = tmp_path / "q.rrd"
    log_result_rerun(r, file=str(path), layers={"voxels": {"xyz": np.zeros((5, 3), np.float32),
                                                           "rgb": np.full((5, 3), 9, np.uint8)}})
    out = subprocess.run([rerun_binary(), "rrd", "stats", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for ent in ("/world/queries/water_tower/clusters", "/world/queries/water_tower/rays", "/world/map/voxels"):
        assert ent in out.stdout, f"{ent} not in the recording:\n{out.stdout[:3000]}"
    assert "/world/query/" not in out.stdout
