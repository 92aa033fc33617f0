"""``rayfronts world``: render the synthetic world along a trajectory into a recording
directory (``common.recording``) and a rerun file.

Outputs under ``--out`` (default ``out/world``):

* ``recording/`` — one :class:`common.frame.Frame` per pose (rgb, planar depth with the
  optional depth limit applied, ground-truth labels, no features), ``stamp = index × 0.1 s``;
  replayable as an edge source.
* ``world.rrd`` — rerun 0.41 recording (z-up world): the instances as labelled 3-D boxes,
  the trajectory, and per frame the camera pose and pinhole (RDF), JPEG RGB, depth and
  the label image with the class names/colours as annotation context.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

HELP = "render the synthetic world to a recording directory and a rerun file"
DESCRIPTION = __doc__

log = logging.getLogger("rayfronts.world")

FRAME_DT = 0.1  # seconds between frames


def _resolution(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like HxW (e.g. 480x640), got {text!r}") from None
    if h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {text!r}")
    return h, w


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/world"),
                        help="output directory (recording/ and world.rrd go here; default out/world)")
    parser.add_argument("--seed", type=int, default=0, help="world and trajectory seed (default 0)")
    parser.add_argument("--preset", choices=["ground", "drone"], default="ground",
                        help="trajectory: 'ground' (car-mounted camera at 1.5 m) or 'drone' (10-18 m, pitched down)")
    parser.add_argument("--world-preset", choices=["default", "sparse"], default="default",
                        help="world layout density (default: 'default')")
    parser.add_argument("--frames", type=int, default=60, help="number of frames over one lap of the town (default 60)")
    parser.add_argument("--resolution", type=_resolution, default=(480, 640),
                        help="image size HxW (default 480x640)")
    parser.add_argument("--hfov", type=float, default=90.0, help="horizontal field of view, degrees (default 90)")
    parser.add_argument("--depth-limit", type=float, default=None,
                        help="simulate a shorter sensor: finite depth above this many metres becomes +inf "
                             "(default: no limit)")
    parser.add_argument("--robot", default="robot0", help="robot id stored in the frames (default robot0)")
    parser.add_argument("--no-rerun", action="store_true", help="do not write world.rrd")


def _log_rerun(path: Path, world, poses, K, hw, frames_iter, seed: int, robot: str) -> None:
    """``world.rrd``: the world's instances (ground truth), the trajectory and each frame of
    robot ``robot`` (entity paths: :mod:`common.rerun_paths`)."""
    import cv2
    import rerun as rr

    from common import rerun_paths as paths

    rec = rr.RecordingStream("rayfronts_world", recording_id=f"world-seed{seed}")
    rec.save(str(path))
    rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    classes = enumerate(zip(world.classes, world.class_colors, strict=True))
    rec.log(paths.WORLD, rr.AnnotationContext([(i, n, c) for i, (n, c) in classes]), static=True)
    inst = world.instances
    rec.log(paths.TRUTH_INSTANCES, rr.Boxes3D(
        centers=np.array([i.center for i in inst]),
        half_sizes=np.array([(i.aabb_max - i.aabb_min) / 2 for i in inst]),
        labels=[f"{world.classes[i.class_id]} ({i.name})" for i in inst],
        class_ids=np.array([i.class_id for i in inst])), static=True)
    rec.log(paths.ROBOTS(robot, paths.TRAJECTORY), rr.LineStrips3D([poses[:, :3, 3]]), static=True)
    h, w = hw
    image = paths.ROBOTS(robot, paths.IMAGE)
    for i, (pose, r, depth) in enumerate(frames_iter):
        rec.set_time("frame", sequence=i)
        rec.set_time("time", duration=i * FRAME_DT)
        rec.log(paths.ROBOTS(robot, paths.CAMERA), rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        rec.log(image, rr.Pinhole(image_from_camera=K, width=w, height=h, camera_xyz=rr.ViewCoordinates.RDF))
        ok, jpg = cv2.imencode(".jpg", r.rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        rec.log(f"{image}/rgb", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
        rec.log(f"{image}/depth", rr.DepthImage(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32), meter=1.0))
        lab = r.labels.astype(np.uint8) if len(world.classes) < 256 else r.labels.astype(np.uint16)
        rec.log(f"{image}/labels", rr.SegmentationImage(lab))
    rec.flush()
    rec.disconnect()


def run(args: argparse.Namespace) -> int:
    problems = []
    if args.frames < 1:
        problems.append(f"--frames must be >= 1, got {args.frames}")
    if not 1.0 <= args.hfov < 179.0:
        problems.append(f"--hfov must be in [1, 179) degrees, got {args.hfov}")
    if args.depth_limit is not None and not args.depth_limit >= 0:
        problems.append(f"--depth-limit must be >= 0, got {args.depth_limit}")
    if problems:
        print("rayfronts world: error: " + "; ".join(problems), file=sys.stderr)
        return 2
    from common.recording import RecordingError

    try:
        return _run(args)
    except RecordingError as e:
        print(f"rayfronts world: error: {e}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    from common.conventions import sanitize_depth
    from common.frame import Frame
    from common.recording import RecordingWriter

    from .scene import World

    t0 = time.perf_counter()
    world = World.generate(args.seed, args.world_preset)
    hw = tuple(args.resolution)
    K = world.camera(hw, args.hfov)
    poses = world.trajectory(args.preset, args.frames, seed=args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rec_dir = out / "recording"
    source = {"type": "synthetic_world", "seed": args.seed, "world_preset": args.world_preset,
              "trajectory": args.preset, "frames": args.frames, "resolution": list(hw), "hfov_deg": args.hfov,
              "depth_limit": args.depth_limit, "classes": world.classes, "frame_dt": FRAME_DT}

    def frames():
        with RecordingWriter(rec_dir, robot=args.robot, source=source, overwrite=True) as writer:
            for i, pose in enumerate(poses):
                r = world.render(pose, K, hw)
                depth = sanitize_depth(r.depth, args.depth_limit)
                writer.write(Frame(robot=args.robot, seq=i, stamp=i * FRAME_DT, pose=pose, intrinsics=K,
                                   depth=depth, rgb=r.rgb, features=None, feature_space="", labels=r.labels,
                                   meta={"source": "synthetic_world", "frame": i}))
                yield pose, r, depth

    rrd = out / "world.rrd"
    if args.no_rerun:
        for _ in frames():
            pass
    else:
        _log_rerun(rrd, world, poses, K, hw, frames(), args.seed, args.robot)
    dt = time.perf_counter() - t0
    print(f"rayfronts world: {args.frames} frames ({hw[0]}x{hw[1]}, {args.preset}, seed {args.seed}) in {dt:.1f} s")
    print(f"  recording: {rec_dir}")
    if not args.no_rerun:
        print(f"  rerun:     {rrd}   (view with: rerun {rrd})")
    return 0
