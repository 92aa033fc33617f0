"""Rerun entity paths: the one place that names them, for every recording we write (the
mapper's, ``rayfronts query --rerun``, ``rayfronts world``, the closed loop's episodes) and the
tests that read them back. One convention: everything in 3D sits under ``world`` (world frame,
z up, metres); 2D side panels under ``scale``. docs/conventions.md#rerun-entity-paths lists them::

    world                                    ViewCoordinates RIGHT_HAND_Z_UP (+ class annotations)
    world/robots/<robot>/camera              Transform3D (camera to world)
    world/robots/<robot>/camera/image        Pinhole (RDF) + rgb, depth, labels
    world/robots/<robot>/trajectory          LineStrips3D of the robot's camera positions
    world/robots/<robot>/position, goal      Points3D (closed loop)
    world/map/voxels, frontiers, rays        the map's layers
    world/truth/instances, targets           ground truth: a world's instances, a mission's targets
    world/queries/<q>/heat, clusters, rays, search_volume    a query's answer
    world/searches/<s>/instances, goals      a search's answer
    scale/<q>/legend, colour_scale           a query's legend and heat colour scale
    summary                                  TextDocument (an episode's outcome)

``<robot>`` is a robot id; ``<q>`` / ``<s>`` is :func:`entity_name` of the query text or the
comma-joined search targets.
"""
from __future__ import annotations

import re

WORLD = "world"
MAP_VOXELS = "world/map/voxels"
MAP_FRONTIERS = "world/map/frontiers"
MAP_RAYS = "world/map/rays"
TRUTH_INSTANCES = "world/truth/instances"
TRUTH_TARGETS = "world/truth/targets"
SUMMARY = "summary"
QUERIES = "world/queries"
SEARCHES = "world/searches"


def entity_name(label: str) -> str:
    """``label`` (a query text, search targets) as one entity path part: runs of characters
    other than ``[A-Za-z0-9_-]`` become ``_``, at most 48 characters, ``query`` if empty."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", label)[:48] or "query"


def robot(robot_id: str) -> str:
    """``world/robots/<robot_id>``: a robot's subtree."""
    return f"world/robots/{robot_id}"


def camera(robot_id: str) -> str:
    """``world/robots/<robot_id>/camera``: the camera pose (camera to world)."""
    return f"{robot(robot_id)}/camera"


def image(robot_id: str) -> str:
    """``world/robots/<robot_id>/camera/image``: the pinhole; ``/rgb``, ``/depth``, ``/labels`` below."""
    return f"{camera(robot_id)}/image"


def trajectory(robot_id: str) -> str:
    """``world/robots/<robot_id>/trajectory``: the camera positions so far."""
    return f"{robot(robot_id)}/trajectory"


def query(name: str) -> str:
    """``world/queries/<name>``: one query's answer (``name`` from :func:`entity_name`)."""
    return f"{QUERIES}/{name}"


def search(name: str) -> str:
    """``world/searches/<name>``: one search's answer (``name`` from :func:`entity_name`)."""
    return f"{SEARCHES}/{name}"


def scale(name: str) -> str:
    """``scale/<name>``: a query's legend and colour scale (2D panels)."""
    return f"scale/{name}"
