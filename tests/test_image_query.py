"""Image queries end to end with the label encoder: a mapper process (router mode) fed by an
edge process on the synthetic world; a crop of the water tower rendered from the same world
answers with a ray that passes the water tower, a crop of a car with car voxels; bad image
inputs give one error line (CLI) or a QueryError (API)."""
from __future__ import annotations

import signal
import subprocess

import cv2
import numpy as np
import pytest

from apps.demo import zenoh_env
from common.zenoh_session import ZenohConfig, free_tcp_port
from synthetic_world import World
from tests.support.processes import ROOT, cli_cmd, proc_env, start_cli, stop_all, wait_for

FRAMES = 40
RES = (240, 320)
VOX = 0.5


@pytest.fixture(scope="module")
def mapped_world(tmp_path_factory):
    """(endpoint, world): a mapper holding the map of FRAMES demo-like frames."""
    from query_client import Client

    d = tmp_path_factory.mktemp("imgq")
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = proc_env()   # + the session's text cache: class names embedded once per session
    logs = [open(d / f"{n}.log", "wb") for n in ("mapper", "edge")]
    mapper = start_cli(["mapper", "--mode", "router", "--listen", ep, "preset=throughput", f"map.vox_size={VOX}",
                        "map.depth_limit=20", "layers.rate_hz=0", "snapshots.on_exit=false",
                        "queues.per_robot=100000"], logs[0], env=env)
    edge = None
    try:
        with Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000), timeout=30.0) as c:
            # the edge starts once the mapper answers: frames sent before its subscriber exists are
            # not received (a camera stream, not a queue)
            wait_for(lambda: c.stats(timeout=5.0), 120, every=0.5, what="mapper up")
            edge = start_cli(["edge", "--connect", ep, "--rate", "0", "robot=cam", "source.kind=synthetic",
                              f"source.n_frames={FRAMES}", f"source.resolution={RES[0]}x{RES[1]}",
                              "source.depth_limit=20", "encoder.kind=label", "pca.out_dim=64", "pca.fit_frames=8",
                              "publish.linger_s=0.5"],
                             logs[1], env=env)

            def done():
                st = c.stats(timeout=5.0)
                return (edge.poll() is not None and st["frames"]["mapped"] >= FRAMES - 2
                        and not sum(st["queues"].values()))

            try:
                wait_for(done, 240, every=0.5, what="the edge's frames mapped")
            except AssertionError:
                raise AssertionError((d / "edge.log").read_text()[-2000:]
                                     + (d / "mapper.log").read_text()[-2000:]) from None
        yield ep, World.generate(0), d
    finally:
        stop_all([p for p in (edge, mapper) if p is not None], signal.SIGTERM, 30)
        for f in logs:
            f.close()


def _crop(world, cls: str, pick) -> np.ndarray:
    """The crop around one instance of ``cls`` (its pixel bounding box), chosen by ``pick``
    among the renders of the edge's trajectory."""
    cid = world.class_id(cls)
    K = world.camera(RES, 90.0)
    best = None
    for pose in world.trajectory("ground", FRAMES):
        r = world.render(pose, K, RES)
        for inst in np.unique(r.instance[r.labels == cid]):
            ys, xs = np.nonzero(r.instance == inst)
            crop = r.rgb[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
            score = pick(len(ys), crop)
            if score is not None and (best is None or score > best[0]):
                best = (score, crop)
    assert best is not None, f"no {cls} seen"
    return best[1]


def _png(rgb) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    return buf.tobytes()


def test_water_tower_crop_answers_with_a_water_tower_ray(mapped_world):
    from query_client import Client

    ep, world, _ = mapped_world
    crop = _crop(world, "water tower", lambda n, c: n)        # the largest view of the tower
    with Client(ZenohConfig(connect=[ep]), timeout=30.0) as c:
        r = c.query(image=_png(crop), top_k=10)
        text = c.query("water tower", top_k=10)
    assert r.query == "<image>" and len(r.ray_origin) > 0 and r.search_volume_m3 > 0
    miss = world.ray_distance_to_class(np.asarray(r.ray_origin[0], float), np.asarray(r.ray_direction[0], float),
                                       world.class_id("water tower"))
    assert miss <= 10.0, miss
    # it answers like the text query (voxels, rays, clusters, search volume all filled)
    assert len(r.voxel_xyz) and len(r.cluster_xyz) and len(text.ray_origin)


def test_car_crop_answers_with_car_voxels(mapped_world, tmp_path):
    ep, world, _ = mapped_world

    def painted(n, crop):  # a well-filled crop of a coloured car (white/black paints look like other classes)
        c = crop.reshape(-1, 3).astype(float)
        sat = (c.max(1) - c.min(1)).mean()
        return n / len(c) if n >= 150 and sat > 40 else None

    crop = _crop(world, "car", painted)
    f = tmp_path / "car.jpg"
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(crop[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
    f.write_bytes(buf.tobytes())
    out = subprocess.run(cli_cmd("query", "--image", str(f), "--connect", ep, "--json", "--top-k", "10"),
                         capture_output=True, text=True, env=zenoh_env(), cwd=str(ROOT), timeout=120)
    assert out.returncode == 0, out.stderr
    import json

    res = json.loads(out.stdout)
    xyz = np.asarray(res["voxel_xyz"], float)
    assert len(xyz) == 10
    d = world.distance_to_class(xyz, world.class_id("car"))
    assert d[0] <= VOX and (d <= VOX).sum() >= 8, d


def test_bad_image_inputs_one_line_each(mapped_world, tmp_path):
    from query_client import Client, QueryError

    ep, _, _ = mapped_world
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    text = tmp_path / "notes.png"
    text.write_text("not an image at all\n")
    huge = tmp_path / "huge.jpg"
    with open(huge, "wb") as fh:
        fh.truncate(21 << 20)
    cases = {str(tmp_path / "missing.png"): "not found", str(empty): "empty", str(text): "not an image",
             str(huge): "over the limit"}
    for path, needle in cases.items():
        out = subprocess.run(cli_cmd("query", "--image", path, "--connect", ep, "--timeout", "5"),
                             capture_output=True, text=True, env=zenoh_env(), cwd=str(ROOT), timeout=60)
        lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
        assert out.returncode != 0 and len(lines) == 1 and needle in lines[0], (path, out.returncode, out.stderr)
    # the mapper refuses what only decoding shows: garbage behind a JPEG signature, too many pixels
    big = cv2.imencode(".png", np.zeros((4200, 4100, 3), np.uint8))[1].tobytes()
    with Client(ZenohConfig(connect=[ep]), timeout=30.0) as c:
        for data, needle in ((b"\xff\xd8\xff" + b"\x00" * 100, "not a decodable image"), (big, "pixels")):
            with pytest.raises(QueryError, match=needle):
                c.query(image=data)
        assert c.stats()["frames"]["mapped"] >= FRAMES - 2        # and keeps serving
