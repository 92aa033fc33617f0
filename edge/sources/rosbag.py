"""ROS 2 (and ROS 1) bags as a frame source, read with the pure-Python ``rosbags``
package: no ROS install needed.

Topics (configurable): colour ``rgb_topic`` (sensor_msgs/Image rgb8, bgr8, rgba8, bgra8,
mono8 or CompressedImage jpeg/png), depth ``depth_topic`` (Image 32FC1 metres, 16UC1 /
mono16 × ``depth_scale``, or CompressedImage png / image_transport ``compressedDepth``),
intrinsics ``camera_info_topic`` (sensor_msgs/CameraInfo of the depth camera; K is
rescaled to the depth resolution if the CameraInfo is for another size) or the
``intrinsics`` key, and the pose from either ``pose_topic`` (geometry_msgs/PoseStamped,
nav_msgs/Odometry) or the tf tree (``tf_topic`` + ``tf_static_topic``, chain
``world_frame`` → ``camera_frame``, static and dynamic edges composed, walked in either
direction). With ``pose_topic`` and ``camera_frame`` both set, the tf chain from the
pose's body frame (``pose_frame`` or Odometry ``child_frame_id``) to ``camera_frame`` is
appended (e.g. odometry of ``base_link`` + the static camera extrinsics).

Synchronisation: the depth stream drives; each depth message is paired with the colour
message nearest in time within ``sync_tolerance`` and with the pose at the depth stamp
(interpolated: linear translation + slerp between the two pose samples around it when
they are at most ``pose_max_gap`` apart; otherwise the nearest sample within
``sync_tolerance``). Depth messages without a colour match, without a pose, or without
any valid depth pixel are skipped and counted by reason in ``skipped``. The bag is read
twice: once at open time (timestamps, poses, depth validity, so ``len`` is exact), once
while iterating.

Message decoding, intrinsics, body axes and the pose lookup live in
:mod:`edge.sources.ros_msgs`, shared with the live ``ros2`` source.

Conventions: the camera body axes are ``body_axes`` ('auto' = RDF for frames named
``*_optical_frame``, else FLU as REP-103 bodies); the world axes are ``world_axes``
(default ENU, REP-103). Poses are converted once with ``convert_pose`` to an RDF body in
a z-up world.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.conventions import convert_pose
from edge.sources.base import FrameSource, native_frame, select_indices
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.ros_msgs import (  # noqa: F401  (decode_rgb, decode_depth, TfTree: public here too)
    CAMERA_INFO,
    IMAGE_TYPES,
    ODOMETRY,
    POSE_TYPES,
    TF,
    PoseLookup,
    TfTree,
    camera_info,
    decode_depth,
    decode_rgb,
    has_valid_depth,
    nearest_colour,
    norm_type,
    resolve_body_axes,
    resolve_intrinsics,
    stamp_seconds,
)

_norm_type = norm_type


# ---------------------------------------------------------------- the source


@dataclass
class _Plan:
    index: int  # depth message ordinal
    stamp: float
    rgb_ord: int
    pose: np.ndarray


class RosbagSource(FrameSource):
    kind = "rosbag"

    def __init__(self, cfg: SourceConfig):
        super().__init__(cfg)
        path = self._input_path("bag")
        try:
            from rosbags.highlevel import AnyReader, AnyReaderError
            from rosbags.typesys import Stores, get_typestore
        except ImportError as e:
            raise SourceError(f"rosbag: the 'rosbags' package is needed (pip install rosbags): {e}") from None
        self._AnyReader = AnyReader
        self._typestore = get_typestore(Stores.ROS2_HUMBLE)
        self.path = path
        if not cfg.sync_tolerance > 0:
            raise SourceError(f"rosbag: sync_tolerance must be > 0 seconds, got {cfg.sync_tolerance}")
        try:
            with self._open() as reader:
                self._scan(reader)
        except AnyReaderError as e:
            raise SourceError(f"rosbag: cannot read {path}: {e}") from None
        self.name = f"rosbag:{path.name}"
        self._report_skips()

    def _open(self):
        return self._AnyReader([self.path], default_typestore=self._typestore)

    def _topic(self, reader, topic: str, types: tuple[str, ...], what: str, required: bool = True):
        conns = [c for c in reader.connections if c.topic == topic]
        if not topic or not conns:
            if not required and not topic:
                return None
            listing = "\n  ".join(sorted(f"{c.topic} [{_norm_type(c.msgtype)}]" for c in reader.connections))
            why = "is not set" if not topic else f"{topic!r} is not in the bag"
            raise SourceError(f"rosbag: {what} {why} ({self.path}); the bag has:\n  {listing}")
        bad = [c for c in conns if _norm_type(c.msgtype) not in types]
        if bad:
            raise SourceError(f"rosbag: {what} topic {topic!r} has type {bad[0].msgtype}, expected one of {types}")
        return conns

    def _stamp(self, msg, bag_ns: int) -> float:
        if self.cfg.use_header_stamps and hasattr(msg, "header"):
            t = stamp_seconds(msg.header.stamp)
            if t > 0:
                return t
        return bag_ns * 1e-9

    def _scan(self, reader: Any) -> None:
        cfg = self.cfg
        roles, lookup, pose_c = self._scan_topics(reader)
        rgb_t, depth_t, depth_ok, info = self._read_stamps(reader, roles, lookup)
        if not depth_t:
            raise SourceError(f"rosbag: no messages on depth topic {cfg.depth_topic!r} in {self.path}")

        self.native_K = resolve_intrinsics("rosbag", info, cfg.intrinsics, self.native_hw, cfg.camera_info_topic)
        body = resolve_body_axes("rosbag", cfg.body_axes, lookup.body_frame, cfg.world_axes)
        self.body_axes = body
        self._pose_child = lookup.pose_child
        lookup.chain()  # raises (SourceError) when the tf chain is missing
        src_desc = lookup.describe({_norm_type(c.msgtype) for c in pose_c or ()})
        plans = self._plan(rgb_t, depth_t, depth_ok, lookup, body)
        self._plans = {p.index: p for p in plans}
        self._indices = [p.index for p in plans]
        self.world_frame = (f"bag world frame from {src_desc} with {cfg.world_axes} axes, re-expressed as ENU "
                            f"(z up; gravity-aligned if the bag's world is); camera body {body} converted to RDF")

    def _scan_topics(self, reader: Any) -> tuple[dict[int, str], PoseLookup, list | None]:
        """The role of each connection to read (rgb, depth, info, pose, tf, tf_static), the pose
        lookup to fill and the pose topic's connections (None without a pose topic)."""
        cfg = self.cfg
        rgb_c = self._topic(reader, cfg.rgb_topic, IMAGE_TYPES, "rgb_topic")
        depth_c = self._topic(reader, cfg.depth_topic, IMAGE_TYPES, "depth_topic")
        info_c = self._topic(reader, cfg.camera_info_topic, (CAMERA_INFO,), "camera_info_topic", required=False)
        pose_c = self._topic(reader, cfg.pose_topic, POSE_TYPES, "pose_topic", required=False)
        if pose_c is None and not (cfg.world_frame and cfg.camera_frame):
            raise SourceError("rosbag: no pose source: set pose_topic, or world_frame and camera_frame to use /tf")
        tf_c = [c for c in reader.connections if c.topic == cfg.tf_topic and _norm_type(c.msgtype) == TF]
        tfs_c = [c for c in reader.connections if c.topic == cfg.tf_static_topic and _norm_type(c.msgtype) == TF]
        if pose_c is None and not (tf_c or tfs_c):
            raise SourceError(f"rosbag: no {cfg.tf_topic} / {cfg.tf_static_topic} TFMessage topics in {self.path}")

        roles = {c.id: "rgb" for c in rgb_c} | {c.id: "depth" for c in depth_c}
        roles |= {c.id: "info" for c in info_c or ()} | {c.id: "pose" for c in pose_c or ()}
        lookup = PoseLookup("rosbag", cfg)
        if lookup.uses_tf:  # the tf tree is needed
            roles |= {c.id: "tf" for c in tf_c} | {c.id: "tf_static" for c in tfs_c}
        return roles, lookup, pose_c

    def _read_stamps(self, reader: Any, roles: dict[int, str],
                     lookup: PoseLookup) -> tuple[list[float], list[float], list[bool | None],
                                                  tuple[np.ndarray, tuple[int, int]] | None]:
        """One pass over the bag: colour and depth stamps (s), whether each depth message has a
        valid pixel (None: corrupt, counted), the first CameraInfo; poses and tf go into ``lookup``."""
        cfg = self.cfg
        conns = [c for c in reader.connections if c.id in roles]
        rgb_t: list[float] = []
        depth_t: list[float] = []
        depth_ok: list[bool | None] = []
        info: tuple[np.ndarray, tuple[int, int]] | None = None
        for conn, ns, raw in reader.messages(connections=conns):
            role = roles[conn.id]
            mtype = _norm_type(conn.msgtype)
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as e:  # rosbags raises several serde errors
                err = SourceError(f"rosbag: cannot deserialize a {conn.msgtype} message on {conn.topic}: {e}")
                if role == "depth":   # a corrupt frame message: skip it, keep the ordinals aligned
                    self._skip_corrupt(f"depth message {len(depth_t)}", err)
                    depth_t.append(ns * 1e-9)
                    depth_ok.append(None)
                    continue
                if role == "rgb":
                    self._skip_corrupt(f"colour message {len(rgb_t)}", err)
                    rgb_t.append(float("inf"))   # never within sync_tolerance of a depth stamp
                    continue
                raise err from None
            if role == "rgb":
                rgb_t.append(self._stamp(msg, ns))
            elif role == "depth":
                depth_t.append(self._stamp(msg, ns))
                depth_ok.append(self._depth_ok(msg, mtype, len(depth_t) - 1, conn.topic))
            elif role == "info" and info is None:
                info = camera_info(msg)
            elif role == "pose":
                lookup.add_pose(msg, mtype, self._stamp(msg, ns))
            elif role in ("tf", "tf_static"):
                lookup.tree.add_message(msg, role == "tf_static", None if cfg.use_header_stamps else ns * 1e-9)
        return rgb_t, depth_t, depth_ok, info

    def _depth_ok(self, msg: Any, mtype: str, i: int, topic: str) -> bool | None:
        """Whether depth message ``i`` has a valid pixel; None when it does not decode (counted).
        The first decoded one sets ``native_hw``."""
        try:
            d = decode_depth(msg, mtype, self.cfg.depth_scale)
        except ValueError as e:
            self._skip_corrupt(f"depth message {i}", SourceError(f"rosbag: depth message {i} on {topic}: {e}"))
            return None
        ok = has_valid_depth(d)
        if self.native_hw is None:
            self.native_hw = d.shape
        return ok

    def _plan(self, rgb_t: list[float], depth_t: list[float], depth_ok: list[bool | None], lookup: PoseLookup,
              body: str) -> list[_Plan]:
        """Synchronise: depth drives; nearest colour within tolerance; pose at the depth stamp."""
        cfg = self.cfg
        rgb_arr = np.asarray(rgb_t, dtype=np.float64)
        rgb_order = np.argsort(rgb_arr, kind="stable")
        rgb_sorted = rgb_arr[rgb_order]
        kept = select_indices(range(len(depth_t)), cfg.frame_skip, None)
        plans: list[_Plan] = []
        for i in kept:
            t = depth_t[i]
            if depth_ok[i] is None:   # corrupt: already counted
                continue
            if not depth_ok[i]:
                self._skip("no valid depth pixel")
                continue
            k = nearest_colour(rgb_sorted, t, cfg.sync_tolerance)
            if k is None:
                self._skip("no colour image within sync_tolerance")
                continue
            T = lookup.at(t)
            if T is None or not np.all(np.isfinite(T)):
                self._skip("no pose at the depth stamp")
                continue
            plans.append(_Plan(i, t, int(rgb_order[k]), convert_pose(T, body, cfg.world_axes)))
            if cfg.max_frames is not None and len(plans) >= cfg.max_frames:
                break
        return plans

    def _iter_native(self, indices):
        plans = [self._plans[i] for i in indices]
        need_d = {p.index for p in plans}
        need_r: defaultdict[int, int] = defaultdict(int)
        for p in plans:
            need_r[p.rgb_ord] += 1
        got_d, got_r = {}, {}
        nd = nr = 0
        pos = 0
        with self._open() as reader:  # connections belong to their reader: look them up again
            conns = [c for c in reader.connections if c.topic in (self.cfg.rgb_topic, self.cfg.depth_topic)]
            types = {c.id: _norm_type(c.msgtype) for c in conns}
            depth_ids = {c.id for c in conns if c.topic == self.cfg.depth_topic}
            for conn, _ns, raw in reader.messages(connections=conns):
                if conn.id in depth_ids:
                    if nd in need_d:
                        got_d[nd] = (raw, conn)
                    nd += 1
                else:
                    if nr in need_r:
                        got_r[nr] = (raw, conn)
                    nr += 1
                while pos < len(plans) and plans[pos].index in got_d and plans[pos].rgb_ord in got_r:
                    p = plans[pos]
                    draw, dconn = got_d.pop(p.index)
                    rraw, rconn = got_r[p.rgb_ord]
                    need_r[p.rgb_ord] -= 1
                    if need_r[p.rgb_ord] == 0:
                        del got_r[p.rgb_ord]
                    try:
                        depth = decode_depth(reader.deserialize(draw, dconn.msgtype), types[dconn.id],
                                             self.cfg.depth_scale)
                        rgb = decode_rgb(reader.deserialize(rraw, rconn.msgtype), types[rconn.id])
                    except Exception as e:  # a message that does not deserialise/decode: skip it
                        self._skip_corrupt(p.index, SourceError(
                            f"rosbag: frame {p.index} ({dconn.topic}, {rconn.topic}): {e}"))
                        pos += 1
                        continue
                    yield native_frame(p.index, p.stamp, p.pose, self.native_K, depth, rgb, rgb_index=p.rgb_ord)
                    pos += 1
                if pos == len(plans):
                    return
        if pos < len(plans):
            raise SourceError(f"rosbag: {self.path} changed while reading: frame {plans[pos].index} not found")
