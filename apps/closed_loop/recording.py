"""One closed-loop episode as a rerun recording (.rrd): the robot's path, its goal, the found
instances (boxes labelled with their ids) and the map's voxels growing, one ``step`` per
loop iteration; the mission's true target boxes for reference. World frame z up, metres;
entity paths :mod:`common.rerun_paths` (the robot is named by the episode's platform)."""
from __future__ import annotations

import numpy as np

from apps.closed_loop.episode import Trace
from apps.closed_loop.missions import Mission
from synthetic_world import World


def record_episode(path: str, world: World, mission: Mission, trace: Trace, row: dict) -> None:
    """Write ``trace`` of the episode ``row`` on ``mission`` to ``path`` (.rrd)."""
    from pathlib import Path

    import rerun as rr

    from common import rerun_paths as paths

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("rayfronts_eval_search")
    rec.save(path)
    rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    lo = np.array([t.aabb_min for t in mission.instances])
    hi = np.array([t.aabb_max for t in mission.instances])
    rec.log(paths.TRUTH_TARGETS, rr.Boxes3D(mins=lo, sizes=hi - lo, colors=[[255, 255, 255]],
                                            labels=[f"{mission.target} (true)"] * len(lo)), static=True)
    rec.log(paths.SUMMARY, rr.TextDocument(f"{row['policy']}: success={row['success']} spl={row['spl']:.2f} "
                                           f"path={row['path_m']:.1f} m steps={row['steps']}"), static=True)
    pos = np.asarray(trace.positions)
    robot_id = str(row.get("platform") or "robot")
    robot = paths.ROBOTS(robot_id)
    found_at = paths.SEARCHES(paths.entity_name(mission.target)) + "/instances"
    for i in range(len(trace.goals)):
        rec.set_time("step", sequence=i)
        rec.log(paths.ROBOTS(robot_id, paths.TRAJECTORY), rr.LineStrips3D([pos[:i + 2]], colors=[[255, 80, 0]]))
        rec.log(f"{robot}/position", rr.Points3D(pos[i:i + 1], radii=0.6, colors=[[255, 80, 0]]))
        g = trace.goals[i]
        if g is not None:
            rec.log(f"{robot}/goal", rr.Points3D([[g[0], g[1], pos[i][2]]], radii=0.5, colors=[[0, 160, 255]],
                                                 labels=[trace.why[i]]))
        else:
            rec.log(f"{robot}/goal", rr.Clear(recursive=False))
        found = trace.found[i]
        if found:
            fl = np.array([f["box_min"] for f in found])
            fh = np.array([f["box_max"] for f in found])
            rec.log(found_at, rr.Boxes3D(mins=fl, sizes=np.maximum(fh - fl, 0.1), colors=[[255, 220, 0]],
                                         labels=[f"{f['target']} #{f['id']}" for f in found]))
        if i < len(trace.voxels):
            rec.log(paths.MAP_VOXELS, rr.Points3D(trace.voxels[i], radii=0.15, colors=[[150, 150, 150]]))
    rec.flush()
