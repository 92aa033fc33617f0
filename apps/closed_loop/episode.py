"""One geometric closed-loop exploration episode (in process, the ``frontier`` policy only so far).

Per step: render a few yaw views (level and tilted down) at the robot's camera centre, integrate them into a
:class:`semantic_map.map.RayFrontsMap` with one-hot ground-truth label features, take the map's
2D costmap of the body band (:mod:`semantic_map.occupancy_queries`), go toward the nearest
reachable frontier through KNOWN FREE cells (:mod:`apps.closed_loop.planner`), move at most
``step_m`` and check the move against the TRUE world. World frame z up, metres.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from apps.closed_loop.planner import FREE, advance, astar, path_length
from apps.closed_loop.robot import Platform, camera_pose
from semantic_map.config import map_config
from semantic_map.map import RayFrontsMap
from semantic_map.occupancy_queries import costmap_slice
from synthetic_world import World


def frontier_episode(world: World, start_xy: np.ndarray, steps: int = 10, step_m: float = 2.0,
                     vox: float = 0.5, depth_limit: float = 20.0, hw: tuple[int, int] = (48, 64),
                     views: int = 4, reach: float = 15.0) -> dict:
    """Run ``steps`` frontier-exploration steps from ``start_xy`` (m); returns ``{"path":
    (N, 3) camera centres, "path_m", "collided", "moves": [(a, b)]}``."""
    robot = Platform.make("ground")
    K = world.camera(hw, 90.0)
    n_cls = len(world.classes)
    m = RayFrontsMap(map_config("default", dict(vox_size=vox, depth_limit=depth_limit)), n_cls, "labels",
                     occupancy_backend="torch")
    pos = np.array([start_xy[0], start_xy[1], robot.z_band[0]], np.float64)
    path, moves, collided = [pos.copy()], [], False
    for _ in range(steps):
        for k in range(2 * views):       # level views, then views tilted down to see the robot's surroundings
            pose = camera_pose(pos, 2 * math.pi * (k % views) / views, 0.0 if k < views else math.pi / 4)
            r = world.render(pose, K, hw)
            oh = torch.nn.functional.one_hot(torch.as_tensor(r.labels.astype(np.int64)), n_cls)
            m.integrate(pose, K, r.depth.astype(np.float32), r.rgb, oh.permute(2, 0, 1).float())
        m.flush()
        states, origin, cell = costmap_slice(m.occupancy, vox, pos[:2] - reach, pos[:2] + reach,
                                              (max(0.3, vox) + 1e-3, robot.z_band[0]))  # above the ground voxels
        fr = m.frontiers().centres.cpu().numpy().astype(np.float64)
        start = tuple(np.floor((pos[:2] - origin) / cell).astype(int))
        if len(fr) == 0 or not (0 <= start[0] < states.shape[0] and 0 <= start[1] < states.shape[1]) \
                or states[start] != FREE:
            break
        order = np.argsort(np.linalg.norm(fr[:, :2] - pos[:2], axis=1))
        best = None
        for f in fr[order[:20]]:
            g = tuple(np.floor((f[:2] - origin) / cell).astype(int))
            if not (0 <= g[0] < states.shape[0] and 0 <= g[1] < states.shape[1]) or g == start:
                continue
            p = astar(states, start, g)
            if p is not None and (best is None or path_length(p, cell) < path_length(best, cell)):
                best = p
        if best is None:
            break
        nxt = advance(best[:-1] if len(best) > 2 else best[:1], origin, cell, step_m)
        nxt = np.r_[nxt, pos[2]]
        if robot.collides(world, pos, nxt):
            collided = True
            break
        moves.append((pos.copy(), nxt.copy()))
        pos = nxt
        path.append(pos.copy())
    pts = np.asarray(path)
    return {"path": pts, "path_m": float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()),
            "collided": collided, "moves": moves}
