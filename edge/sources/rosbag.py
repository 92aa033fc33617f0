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

Conventions: the camera body axes are ``body_axes`` ('auto' = RDF for frames named
``*_optical_frame``, else FLU as REP-103 bodies); the world axes are ``world_axes``
(default ENU, REP-103). Poses are converted once with ``convert_pose`` to an RDF body in
a z-up world.
"""
from __future__ import annotations

from collections import defaultdict, deque
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.conventions import convert_pose
from common.geometry import invert_pose, scale_intrinsics
from edge.sources.base import FrameSource, native_frame, select_indices
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.transforms import PoseTrack, pose_from_tq

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"


def _norm_type(t: str) -> str:
    """ROS 1 style 'sensor_msgs/Image' → 'sensor_msgs/msg/Image'."""
    parts = t.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else t


def stamp_seconds(stamp) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def _tq(translation, rotation) -> np.ndarray:
    return pose_from_tq([translation.x, translation.y, translation.z],
                        [rotation.x, rotation.y, rotation.z, rotation.w])


# ---------------------------------------------------------------- message decoding


def _image_rows(msg, dtype, channels: int) -> np.ndarray:
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize * channels
    buf = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, dtype=np.uint8)
    if step < w * item or buf.size < h * step:
        raise ValueError(f"image data too short: {buf.size} bytes for {h}x{w}, step {step}")
    rows = buf[: h * step].reshape(h, step)[:, : w * item]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    out = np.ascontiguousarray(rows).view(dt).reshape(h, w, channels) if channels > 1 else \
        np.ascontiguousarray(rows).view(dt).reshape(h, w)
    return out.astype(np.dtype(dtype).newbyteorder("="))


def decode_rgb(msg, msgtype: str) -> np.ndarray:
    """Image / CompressedImage → (H, W, 3) uint8 RGB."""
    if msgtype == COMPRESSED:
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"cannot decode compressed image (format {msg.format!r})")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    enc = msg.encoding.lower()
    if enc in ("rgb8", "bgr8"):
        img = _image_rows(msg, np.uint8, 3)
        return img if enc == "rgb8" else img[..., ::-1].copy()
    if enc in ("rgba8", "bgra8"):
        img = _image_rows(msg, np.uint8, 4)[..., :3]
        return img.copy() if enc == "rgba8" else img[..., ::-1].copy()
    if enc in ("mono8", "8uc1"):
        return np.repeat(_image_rows(msg, np.uint8, 1)[..., None], 3, axis=2)
    raise ValueError(f"unsupported colour encoding {msg.encoding!r} (use rgb8, bgr8, rgba8, bgra8, mono8)")


def decode_depth(msg, msgtype: str, depth_scale: float) -> np.ndarray:
    """Image / CompressedImage → (H, W) float32 metres (invalid values left for sanitize)."""
    if msgtype == COMPRESSED:
        fmt = msg.format.lower()
        data = bytes(msg.data)
        if "compresseddepth" in fmt:
            # image_transport compressedDepth: 12-byte header (int32 format, float32 quant A, B) + PNG.
            head, png = data[:12], data[12:]
            img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"cannot decode compressedDepth PNG (format {msg.format!r})")
            if fmt.startswith("32fc1"):
                a, b = np.frombuffer(head[4:12], "<f4")
                v = img.astype(np.float32)
                with np.errstate(divide="ignore", invalid="ignore"):
                    return np.where(v > 0, a / (v - b), np.nan).astype(np.float32)
            return img.astype(np.float32) * np.float32(depth_scale)
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2 or img.dtype != np.uint16:
            raise ValueError(f"compressed depth must be a single-channel 16-bit PNG (format {msg.format!r})")
        return img.astype(np.float32) * np.float32(depth_scale)
    enc = msg.encoding.lower()
    if enc == "32fc1":
        return _image_rows(msg, np.float32, 1)
    if enc in ("16uc1", "mono16"):
        return _image_rows(msg, np.uint16, 1).astype(np.float32) * np.float32(depth_scale)
    raise ValueError(f"unsupported depth encoding {msg.encoding!r} (use 32FC1 metres or 16UC1)")


def _has_valid(depth: np.ndarray) -> bool:
    with np.errstate(invalid="ignore"):
        return bool(np.any((depth > 0) & ~np.isneginf(depth) & ~np.isnan(depth)))


# ---------------------------------------------------------------- tf tree


class TfTree:
    """Static and time-stamped transforms (parent → child = child's pose in parent)."""

    def __init__(self, tolerance: float, interpolate: bool, max_gap: float):
        self.static: dict[tuple[str, str], np.ndarray] = {}
        self._dyn: dict[tuple[str, str], list[tuple[float, np.ndarray]]] = defaultdict(list)
        self.dynamic: dict[tuple[str, str], PoseTrack] = {}
        self.args = (tolerance, interpolate, max_gap)

    def add(self, parent: str, child: str, t: float, T: np.ndarray, static: bool) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if static:
            self.static[(parent, child)] = T
        else:
            self._dyn[(parent, child)].append((t, T))

    def finalize(self) -> None:
        tol, interp, gap = self.args
        for k, samples in self._dyn.items():
            self.dynamic[k] = PoseTrack([s[0] for s in samples], [s[1] for s in samples], tol, interp, gap)

    @property
    def frames(self) -> set[str]:
        return {f for k in list(self.static) + list(self.dynamic) for f in k}

    def path(self, src: str, dst: str) -> list[tuple[str, str, bool]] | None:
        """Edges from ``src`` to ``dst``: (parent, child, forward) with forward = parent→child."""
        src, dst = src.lstrip("/"), dst.lstrip("/")
        adj = defaultdict(list)
        for p, c in list(self.static) + list(self.dynamic):
            adj[p].append((c, (p, c, True)))
            adj[c].append((p, (p, c, False)))
        prev: dict[str, tuple[str, tuple] | None] = {src: None}
        q = deque([src])
        while q:
            n = q.popleft()
            if n == dst:
                break
            for m, e in adj[n]:
                if m not in prev:
                    prev[m] = (n, e)
                    q.append(m)
        if dst not in prev:
            return None
        edges, n = [], dst
        while prev[n] is not None:
            n, e = prev[n]
            edges.append(e)
        return edges[::-1]

    def lookup(self, edges, t: float) -> np.ndarray | None:
        """Pose of the chain's last frame in its first frame at time ``t`` (None if a dynamic edge has no sample)."""
        T = np.eye(4)
        for p, c, fwd in edges:
            E = self.static.get((p, c))
            if E is None:
                E = self.dynamic[(p, c)].at(t)
                if E is None:
                    return None
            T = T @ (E if fwd else invert_pose(E))
        return T


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
        path = Path(cfg.path)
        if not path.exists():
            raise SourceError(f"rosbag: bag not found: {path}")
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

    def _scan(self, reader) -> None:
        cfg = self.cfg
        rgb_c = self._topic(reader, cfg.rgb_topic, (IMAGE, COMPRESSED), "rgb_topic")
        depth_c = self._topic(reader, cfg.depth_topic, (IMAGE, COMPRESSED), "depth_topic")
        info_c = self._topic(reader, cfg.camera_info_topic, (CAMERA_INFO,), "camera_info_topic", required=False)
        pose_c = self._topic(reader, cfg.pose_topic, (POSE_STAMPED, ODOMETRY), "pose_topic", required=False)
        if pose_c is None and not (cfg.world_frame and cfg.camera_frame):
            raise SourceError("rosbag: no pose source: set pose_topic, or world_frame and camera_frame to use /tf")
        tf_c = [c for c in reader.connections if c.topic == cfg.tf_topic and _norm_type(c.msgtype) == TF]
        tfs_c = [c for c in reader.connections if c.topic == cfg.tf_static_topic and _norm_type(c.msgtype) == TF]
        if pose_c is None and not (tf_c or tfs_c):
            raise SourceError(f"rosbag: no {cfg.tf_topic} / {cfg.tf_static_topic} TFMessage topics in {self.path}")

        roles = {c.id: "rgb" for c in rgb_c} | {c.id: "depth" for c in depth_c}
        roles |= {c.id: "info" for c in info_c or ()} | {c.id: "pose" for c in pose_c or ()}
        if pose_c is None or cfg.camera_frame:  # the tf tree is needed
            roles |= {c.id: "tf" for c in tf_c} | {c.id: "tf_static" for c in tfs_c}
        conns = [c for c in reader.connections if c.id in roles]
        rgb_t, depth_t, depth_ok = [], [], []
        pose_t, pose_T = [], []
        self._pose_child = ""
        info = None
        tree = TfTree(cfg.sync_tolerance, cfg.interpolate_pose, cfg.pose_max_gap)
        for conn, ns, raw in reader.messages(connections=conns):
            role = roles[conn.id]
            mtype = _norm_type(conn.msgtype)
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as e:  # rosbags raises several serde errors
                raise SourceError(f"rosbag: cannot deserialize a {conn.msgtype} message on {conn.topic}: {e}") from None
            if role == "rgb":
                rgb_t.append(self._stamp(msg, ns))
            elif role == "depth":
                depth_t.append(self._stamp(msg, ns))
                try:
                    d = decode_depth(msg, mtype, cfg.depth_scale)
                except ValueError as e:
                    raise SourceError(f"rosbag: depth message {len(depth_t) - 1} on {conn.topic}: {e}") from None
                depth_ok.append(_has_valid(d))
                if self.native_hw is None:
                    self.native_hw = d.shape
            elif role == "info" and info is None:
                k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64).reshape(3, 3)
                info = (k, (int(msg.height), int(msg.width)))
            elif role == "pose":
                p = msg.pose.pose if mtype == ODOMETRY else msg.pose
                pose_t.append(self._stamp(msg, ns))
                pose_T.append(_tq(p.position, p.orientation))
                if mtype == ODOMETRY and not self._pose_child:
                    self._pose_child = msg.child_frame_id
            elif role in ("tf", "tf_static"):
                for tr in msg.transforms:
                    t = stamp_seconds(tr.header.stamp) if cfg.use_header_stamps else ns * 1e-9
                    tree.add(tr.header.frame_id, tr.child_frame_id, t,
                             _tq(tr.transform.translation, tr.transform.rotation), role == "tf_static")
        tree.finalize()
        if not depth_t:
            raise SourceError(f"rosbag: no messages on depth topic {cfg.depth_topic!r} in {self.path}")

        # Intrinsics at the depth resolution.
        if info is not None:
            K, info_hw = info
            if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise SourceError(f"rosbag: CameraInfo on {cfg.camera_info_topic} has an invalid K: {K.ravel()}")
            self.native_K = scale_intrinsics(K, info_hw, self.native_hw) if info_hw != self.native_hw and info_hw[0] > 0 else K
        elif cfg.intrinsics is not None:
            if len(cfg.intrinsics) != 4:
                raise SourceError(f"rosbag: intrinsics must be [fx, fy, cx, cy], got {cfg.intrinsics}")
            fx, fy, cx, cy = cfg.intrinsics
            self.native_K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        else:
            raise SourceError("rosbag: no intrinsics: set camera_info_topic (sensor_msgs/CameraInfo) or intrinsics=[fx,fy,cx,cy]")

        # Pose lookup.
        body_frame = cfg.camera_frame or cfg.pose_frame or self._pose_child
        body = cfg.body_axes.upper()
        if body == "AUTO":
            body = "RDF" if body_frame.rstrip("/").endswith("optical_frame") else "FLU"
        try:
            convert_pose(np.eye(4), body, cfg.world_axes)
        except ValueError as e:
            raise SourceError(f"rosbag: body_axes/world_axes: {e}") from None
        self.body_axes = body
        if pose_c is not None:
            track = PoseTrack(pose_t, pose_T, cfg.sync_tolerance, cfg.interpolate_pose, cfg.pose_max_gap)
            extr = None
            pose_frame = cfg.pose_frame or self._pose_child
            if cfg.camera_frame and pose_frame and pose_frame.lstrip("/") != cfg.camera_frame.lstrip("/"):
                extr = tree.path(pose_frame, cfg.camera_frame)
                if extr is None:
                    raise SourceError(f"rosbag: no tf chain from pose frame {pose_frame!r} to camera_frame "
                                      f"{cfg.camera_frame!r}; tf frames: {sorted(tree.frames)}")

            def pose_at(t):
                T = track.at(t)
                if T is None or extr is None:
                    return T
                E = tree.lookup(extr, t)
                return None if E is None else T @ E
            src_desc = f"{cfg.pose_topic} ({'/'.join(t.split('/')[-1] for t in {_norm_type(c.msgtype) for c in pose_c})})"
        else:
            chain = tree.path(cfg.world_frame, cfg.camera_frame)
            if chain is None:
                raise SourceError(f"rosbag: no tf chain from world_frame {cfg.world_frame!r} to camera_frame "
                                  f"{cfg.camera_frame!r}; tf frames: {sorted(tree.frames)}")

            def pose_at(t):
                return tree.lookup(chain, t)
            src_desc = f"tf {cfg.world_frame} -> {cfg.camera_frame}"

        # Synchronise: depth drives; nearest colour within tolerance; pose at the depth stamp.
        rgb_arr = np.asarray(rgb_t, dtype=np.float64)
        rgb_order = np.argsort(rgb_arr, kind="stable")
        rgb_sorted = rgb_arr[rgb_order]
        kept = select_indices(range(len(depth_t)), cfg.frame_skip, None)
        plans = []
        for i in kept:
            t = depth_t[i]
            if not depth_ok[i]:
                self._skip("no valid depth pixel")
                continue
            if len(rgb_sorted) == 0:
                self._skip("no colour image within sync_tolerance")
                continue
            j = int(np.searchsorted(rgb_sorted, t))
            cand = [k for k in (j - 1, j) if 0 <= k < len(rgb_sorted)]
            k = min(cand, key=lambda k: abs(rgb_sorted[k] - t))
            if abs(rgb_sorted[k] - t) > cfg.sync_tolerance:
                self._skip("no colour image within sync_tolerance")
                continue
            T = pose_at(t)
            if T is None or not np.all(np.isfinite(T)):
                self._skip("no pose at the depth stamp")
                continue
            plans.append(_Plan(i, t, int(rgb_order[k]), convert_pose(T, body, cfg.world_axes)))
            if cfg.max_frames is not None and len(plans) >= cfg.max_frames:
                break
        self._plans = {p.index: p for p in plans}
        self._indices = [p.index for p in plans]
        self.world_frame = (f"bag world frame from {src_desc} with {cfg.world_axes} axes, re-expressed as ENU "
                            f"(z up; gravity-aligned if the bag's world is); camera body {body} converted to RDF")

    def _iter_native(self, indices):
        plans = [self._plans[i] for i in indices]
        need_d = {p.index for p in plans}
        need_r = defaultdict(int)
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
                        depth = decode_depth(reader.deserialize(draw, dconn.msgtype), types[dconn.id], self.cfg.depth_scale)
                        rgb = decode_rgb(reader.deserialize(rraw, rconn.msgtype), types[rconn.id])
                    except ValueError as e:
                        raise SourceError(f"rosbag: frame {p.index} ({dconn.topic}, {rconn.topic}): {e}") from None
                    yield native_frame(p.index, p.stamp, p.pose, self.native_K, depth, rgb, rgb_index=p.rgb_ord)
                    pos += 1
                if pos == len(plans):
                    return
        if pos < len(plans):
            raise SourceError(f"rosbag: {self.path} changed while reading: frame {plans[pos].index} not found")
