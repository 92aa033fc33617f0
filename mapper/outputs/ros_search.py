"""The planners' search and costmap as ROS 2 topics (part of the ROS 2 output, ``ros.enabled``;
docs/key_space.md, ROS 2). Answers come from the mapper's own search service
(:class:`mapper.search_server.SearchServer`: the same replies ``Client.search`` and
``Client.occupancy_slice`` get); this module only turns them into ROS messages.

Topics (under ``ros.topic_prefix``, frame ``ros.frame_id``: the map's world, z up, metres):

* ``<p>/search_text`` (subscribed) — std_msgs/String, comma-separated targets: starts or
  replaces the one standing ROS search (id :data:`SEARCH_ID`), re-run by the search service
  after map changes;
* ``<p>/search/found`` — visualization_msgs/MarkerArray: DELETEALL, then per found instance a
  CUBE (ns ``found``, id = the instance id, its box) and a TEXT_VIEW_FACING label (ns
  ``found_label``, same id, ``"<target> #<id> <confidence>"`` above the box);
* ``<p>/search/found_poses`` — geometry_msgs/PoseArray: instance centroids (best first);
* ``<p>/search/goals`` — geometry_msgs/PoseArray: look-next goals (yaw = ``heading_rad``);
* ``<p>/search/goal_scores`` — std_msgs/Float32MultiArray: the goals' scores, same order;
* ``<p>/search/events`` — std_msgs/String: the reply's ``events`` as a JSON list
  (docs/identity.md#events; ``[]`` when the update changed nothing);
* ``<p>/costmap`` — nav_msgs/OccupancyGrid of the z band ``ros.costmap_z_band``: -1 unknown,
  0 free, 100 occupied; cell ``(x, y)`` at ``data[y * width + x]``, origin the min corner
  of cell 0 at z = the band's bottom, published with the layers, reliable + transient-local
  depth 1 (a late subscriber gets the last grid; :meth:`mapper.outputs.ros.RosOutput._publisher`).
"""
from __future__ import annotations

import json
import logging
import math
import threading
import time
from typing import Any

import numpy as np

from common.search_messages import OccupancyReply, SearchReply
from mapper.outputs.ros_markers import header_msg, marker_extra_fields, stamp_msg

log = logging.getLogger("rayfronts.mapper")

MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
FLOAT32_ARRAY = "std_msgs/msg/Float32MultiArray"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
STRING = "std_msgs/msg/String"
#: id of the standing search the ROS output owns
SEARCH_ID = "ros_search"
#: OccupancyGrid values of the occupancy states (unknown, free, occupied)
GRID_VALUES = {-1: -1, 0: 0, 1: 100}


def pose_msg(T: dict, xyz, yaw: float = 0.0) -> Any:
    """Pose at ``xyz`` (m) turned ``yaw`` (rad) about z."""
    q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    p = T["geometry_msgs/msg/Point"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))
    return T["geometry_msgs/msg/Pose"](position=p, orientation=q)


def pose_array(T: dict, frame_id: str, t: float, xyz, yaw=None) -> Any:
    """PoseArray of positions (N, 3) (m), yaw (N,) rad or None (identity orientations)."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    yaw = np.zeros(len(xyz)) if yaw is None else np.asarray(yaw, np.float64).reshape(-1)
    return T[POSE_ARRAY](header=header_msg(T, frame_id, t),
                         poses=[pose_msg(T, p, a) for p, a in zip(xyz, yaw, strict=True)])


def float32_array(T: dict, values, label: str) -> Any:
    """Float32MultiArray of one dimension named ``label``."""
    v = np.asarray(values, np.float32).reshape(-1)
    dim = T["std_msgs/msg/MultiArrayDimension"](label=label, size=len(v), stride=len(v))
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0)
    return T[FLOAT32_ARRAY](layout=layout, data=v)


def found_markers(T: dict, frame_id: str, t: float, found: list[dict]) -> Any:
    """MarkerArray: DELETEALL, then per instance a CUBE (its box) and a text label (ids = instance ids)."""
    marker_t: Any = T["visualization_msgs/msg/Marker"]
    hdr = header_msg(T, frame_id, t)
    zero = T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    extra = marker_extra_fields(T, hdr)

    def marker(ns: str, i: int, kind: int, action: int, centre=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0),
               rgba=(0.0, 0.0, 0.0, 0.0), text: str = "") -> Any:
        return marker_t(header=hdr, ns=ns, id=int(i), type=kind, action=action, pose=pose_msg(T, centre),
                        scale=T["geometry_msgs/msg/Vector3"](x=float(size[0]), y=float(size[1]), z=float(size[2])),
                        color=T["std_msgs/msg/ColorRGBA"](r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]),
                                                          a=float(rgba[3])),
                        lifetime=zero, frame_locked=False, points=[], colors=[], text=text, mesh_resource="",
                        mesh_use_embedded_materials=False, **extra)

    out = [marker("found", 0, marker_t.CUBE, marker_t.DELETEALL)]
    for f in found:
        lo, hi = np.asarray(f["box_min"], np.float64), np.asarray(f["box_max"], np.float64)
        c, size = (lo + hi) / 2, np.maximum(hi - lo, 1e-3)
        conf = float(f.get("confidence", 0.0))
        out.append(marker("found", f["id"], marker_t.CUBE, marker_t.ADD, c, size, (1.0 - conf, conf, 0.0, 0.4)))
        out.append(marker("found_label", f["id"], marker_t.TEXT_VIEW_FACING, marker_t.ADD,
                          (c[0], c[1], hi[2] + 0.3), (0.0, 0.0, 0.3), (1.0, 1.0, 1.0, 1.0),
                          f"{f.get('target', '')} #{f['id']} {conf:.2f}"))
    return T[MARKER_ARRAY](markers=out)


def occupancy_grid(T: dict, frame_id: str, t: float, rep: OccupancyReply, z0: float) -> Any:
    """OccupancyGrid of a slice reply (states (nx, ny): -1/0/1 → -1/0/100, x fastest)."""
    st = np.asarray(rep.states, np.int8)
    nx, ny = st.shape
    data = np.where(st > 0, 100, np.where(st == 0, 0, -1)).astype(np.int8).T.reshape(-1)
    info = T["nav_msgs/msg/MapMetaData"](map_load_time=stamp_msg(T, t), resolution=float(rep.cell_m), width=nx,
                                         height=ny, origin=pose_msg(T, (rep.origin[0], rep.origin[1], z0)))
    return T[OCCUPANCY_GRID](header=header_msg(T, frame_id, t), info=info, data=data)


def search_reply_messages(T: dict, frame_id: str, t: float, rep: SearchReply, base: str) -> dict:
    """{topic: (type, message)} of a search reply under topic ``base`` (``<p>/search``):
    ``base/found`` MarkerArray, ``base/found_poses`` PoseArray of the instance centroids,
    ``base/goals`` PoseArray of the look-next goals (yaw = heading), ``base/goal_scores``,
    ``base/events`` the reply's ``events`` as a JSON string."""
    goals = rep.look_next
    centroids = np.array([f["centroid"] for f in rep.found], np.float64).reshape(-1, 3)
    gxyz = np.array([g["position"] for g in goals], np.float64).reshape(-1, 3)
    return {f"{base}/found": (MARKER_ARRAY, found_markers(T, frame_id, t, rep.found)),
            f"{base}/found_poses": (POSE_ARRAY, pose_array(T, frame_id, t, centroids)),
            f"{base}/goals": (POSE_ARRAY, pose_array(T, frame_id, t, gxyz, [g.get("heading_rad", 0.0) for g in goals])),
            f"{base}/goal_scores": (FLOAT32_ARRAY, float32_array(T, [g["score"] for g in goals], "goals")),
            f"{base}/events": (STRING, T[STRING](data=json.dumps(rep.events)))}


def parse_targets(text: str) -> list[str]:
    """``"chair, red car"`` → ``["chair", "red car"]`` (ValueError when none)."""
    targets = [p.strip() for p in str(text).split(",") if p.strip()]
    if not targets:
        raise ValueError("no targets (expected comma-separated phrases)")
    return targets


class RosSearch:
    """Search topics of a :class:`mapper.outputs.ros.RosOutput` (``out``) answered by the
    mapper's search service ``search``."""

    def __init__(self, out, search) -> None:
        p = out.topic_prefix
        self.out, self.search = out, search
        self.topics = {"found": (f"{p}/search/found", MARKER_ARRAY),
                       "found_poses": (f"{p}/search/found_poses", POSE_ARRAY),
                       "goals": (f"{p}/search/goals", POSE_ARRAY),
                       "goal_scores": (f"{p}/search/goal_scores", FLOAT32_ARRAY),
                       "events": (f"{p}/search/events", STRING),
                       "costmap": (f"{p}/costmap", OCCUPANCY_GRID)}
        self.text_topic = f"{p}/search_text"
        self.request = None            # the standing SearchRequest, once one arrived
        self._busy = threading.Lock()

    def start(self) -> list:
        """Declare the subscriptions; returns their Zenoh entities (the output undeclares them)."""
        from common.ros2.keys import subscribe_key

        o, st = self.out, self.out.state
        ents = [o.session.declare_subscriber(subscribe_key(self.text_topic, o.cfg.keys, o.domain), self._on_text),
                st.session.declare_subscriber(st.keys.mapper_searches(SEARCH_ID), self._on_reply)]
        o._token("MS", self.text_topic, STRING)
        return ents

    # ---------------------------------------------------------------- search
    def _on_text(self, sample) -> None:
        """std_msgs/String on ``<p>/search_text`` → (re)start the standing search (in a thread:
        the first answer may wait for the map)."""
        o = self.out
        try:
            msg = o.cdr.deserialize(sample.payload.to_bytes(), STRING)
            req = self.make_request(parse_targets(msg.data))
        except Exception as e:
            o.errors += 1
            o.state.warn("ros-search", "ROS 2 search on %s rejected: %s", self.text_topic, e)
            return
        threading.Thread(target=self.begin, args=(req,), name="mapper-ros-search", daemon=True).start()

    def make_request(self, targets: list[str]):
        """The standing SearchRequest for ``targets`` with the ``ros.search_*`` settings."""
        from common.search_messages import SearchRequest

        c = self.out.cfg
        return SearchRequest(targets=targets, threshold=float(c.search_threshold),
                             max_instances=int(c.search_max_instances), max_goals=int(c.search_max_goals),
                             standing=True, id=SEARCH_ID).validate()

    def begin(self, req) -> SearchReply | None:
        """Register ``req`` as the standing search through the search service and publish its
        first answer; on an empty map it stays registered and answers once the map changes."""
        from common.messages import MessageError
        from common.search_messages import decode_search_reply, encode_search_request

        with self._busy:
            self.request = req
            try:
                rep = decode_search_reply(self.search.search_payload(encode_search_request(req)))
            except MessageError as e:
                self.search.standing[req.id] = req
                log.info("ROS 2 search %s registered (%s)", req.targets, e)
                return None
            except Exception as e:
                self.out.errors += 1
                self.out.state.warn("ros-search", "ROS 2 search %s failed: %s", req.targets, e)
                return None
            log.info("ROS 2 search %s: %d found, %d goals", req.targets, len(rep.found), len(rep.look_next))
            self.publish_reply(rep)
            return rep

    def _on_reply(self, sample) -> None:
        """A standing-search update (``<p>/mapper/searches/ros_search``) → the search topics."""
        from common.search_messages import decode_search_reply

        try:
            self.publish_reply(decode_search_reply(sample.payload.to_bytes()))
        except Exception as e:  # never raise out of a Zenoh callback
            self.out.errors += 1
            self.out.state.warn("ros-search", "ROS 2 search output failed: %s", e)

    def reply_messages(self, rep: SearchReply) -> dict:
        """{topic: (type, message)} of a search reply."""
        o = self.out
        return search_reply_messages(o.T, o.cfg.frame_id, time.time(), rep, self.topics["found"][0].rsplit("/", 1)[0])

    def publish_reply(self, rep: SearchReply) -> None:
        for topic, (msgtype, msg) in self.reply_messages(rep).items():
            self.out._put(topic, msgtype, msg)

    # ---------------------------------------------------------------- costmap
    def costmap_box(self) -> list[float] | None:
        """``ros.costmap_box`` [x0, y0, x1, y1] (m), or [] → the xy extent of the map's
        observed voxels; None before anything is observed."""
        c = self.out.cfg
        if c.costmap_box:
            return [float(v) for v in c.costmap_box]
        st = self.out.state
        with st.lock:
            if st.map is None:
                return None
            ijk, _ = st.map.occupancy_view().active()
            vox = float(st.map.cfg.vox_size)
        ijk = np.asarray(ijk.cpu() if hasattr(ijk, "cpu") else ijk).reshape(-1, 3)
        if not len(ijk):
            return None
        lo, hi = ijk[:, :2].min(0) * vox, (ijk[:, :2].max(0) + 1) * vox
        return [float(lo[0]), float(lo[1]), float(hi[0]) - 1e-6, float(hi[1]) - 1e-6]

    def costmap_message(self) -> tuple[str, tuple[str, Any]] | None:
        """``(topic, (type, OccupancyGrid))`` of the configured z band, through the search
        service's slice answer (None before the map has observed voxels)."""
        from common.search_messages import OccupancyRequest, encode_occupancy_request

        box = self.costmap_box()
        if box is None:
            return None
        z = [float(v) for v in self.out.cfg.costmap_z_band]
        req = OccupancyRequest("slice", box[:2], box[2:], z, stride=int(self.out.cfg.costmap_stride)).validate()
        rep = self.search.occupancy(encode_occupancy_request(req))
        o = self.out
        return self.topics["costmap"][0], (OCCUPANCY_GRID, occupancy_grid(o.T, o.cfg.frame_id, time.time(), rep, z[0]))
