"""Rerun entity paths: the one place that names them, for every recording we write (the
mapper's, ``rayfronts query --rerun``, ``rayfronts world``, the closed loop's episodes; the
tests read them back by the documented literal paths). One convention: everything in 3D
sits under ``world`` (world frame, z up, metres); 2D side panels under ``scale``.
docs/conventions.md#rerun-entity-paths lists them::

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
comma-joined search targets. Subtrees by name: :data:`ROBOTS`, :data:`QUERIES`,
:data:`SEARCHES`, :data:`SCALE` (``ROBOTS("r1", IMAGE)`` is ``world/robots/r1/camera/image``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

WORLD = "world"
MAP_VOXELS = "world/map/voxels"
MAP_FRONTIERS = "world/map/frontiers"
MAP_RAYS = "world/map/rays"
TRUTH_INSTANCES = "world/truth/instances"
TRUTH_TARGETS = "world/truth/targets"
SUMMARY = "summary"
#: below a robot (``ROBOTS(robot_id, IMAGE)``): the camera pose, its image, the camera positions so far
CAMERA, IMAGE, TRAJECTORY = "camera", "camera/image", "trajectory"


@dataclass(frozen=True)
class Tree:
    """One subtree of named members: ``tree(name, *parts)`` is ``<root>/<name>/<part>/...``."""

    root: str

    def __call__(self, name: str, *parts: str) -> str:
        return "/".join((self.root, name, *parts))


ROBOTS = Tree("world/robots")        #: by robot id
QUERIES = Tree("world/queries")      #: by :func:`entity_name` of the query text
SEARCHES = Tree("world/searches")    #: by :func:`entity_name` of the comma-joined targets
SCALE = Tree("scale")                #: a query's legend and colour scale (2D panels), by its query name


def entity_name(label: str) -> str:
    """``label`` (a query text, search targets) as one entity path part: runs of characters
    other than ``[A-Za-z0-9_-]`` become ``_``, at most 48 characters, ``query`` if empty."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", label)[:48] or "query"
