"""ROS message handling shared by the ``rosbag`` (files) and ``ros2`` (live) sources, so
both build the same frames from the same messages: image / depth decoding, CameraInfo
intrinsics, camera body axes, pose samples, the tf tree and the pose lookup at a depth
stamp (pose topic, optionally + the tf chain to ``camera_frame``; or the tf chain
``world_frame`` → ``camera_frame``), and the colour match. Pure computation, no I/O.

Pose lookup (both sources): :class:`GrowingTrack` keeps a pose topic's samples (bounded
for the live source) and answers like :class:`edge.sources.transforms.PoseTrack` (exact
sample, else interpolation across at most ``pose_max_gap``, else the nearest within
``sync_tolerance``, no extrapolation); the tf tree keeps one such track per dynamic edge.
"""
from __future__ import annotations

from collections import defaultdict, deque
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import cv2
import numpy as np

from common.geometry import invert_pose, scale_intrinsics
from edge.sources.errors import SourceError
from edge.sources.transforms import PoseTrack, pose_from_tq

if TYPE_CHECKING:
    from edge.sources.config import SourceConfig

#: a tf chain: (parent, child, forward) edges, forward = parent → child
TfChain = list[tuple[str, str, bool]]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
POSE_TYPES = (POSE_STAMPED, ODOMETRY)


def norm_type(t: str) -> str:
    """ROS 1 style 'sensor_msgs/Image' → 'sensor_msgs/msg/Image'."""
    parts = t.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else t


def stamp_seconds(stamp: Any) -> float:
    """A ROS ``builtin_interfaces/Time`` (sec, nanosec) in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def tq(translation: Any, rotation: Any) -> np.ndarray:
    """4×4 transform from a ROS ``Vector3``/``Point`` translation (m) and ``Quaternion`` rotation."""
    return pose_from_tq([translation.x, translation.y, translation.z],
                        [rotation.x, rotation.y, rotation.z, rotation.w])


def pose_from_msg(msg: Any, msgtype: str) -> np.ndarray:
    """PoseStamped / Odometry → 4×4 pose of its body in its frame."""
    p = msg.pose.pose if msgtype == ODOMETRY else msg.pose
    return tq(p.position, p.orientation)


# ---------------------------------------------------------------- images


def _image_rows(msg: Any, dtype: type, channels: int) -> np.ndarray:
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


def decode_rgb(msg: Any, msgtype: str) -> np.ndarray:
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


def decode_depth(msg: Any, msgtype: str, depth_scale: float) -> np.ndarray:
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


def has_valid_depth(depth: np.ndarray) -> bool:
    """Whether any depth value is a measurement (> 0, not NaN; +inf counts: beyond range)."""
    with np.errstate(invalid="ignore"):
        return bool(np.any((depth > 0) & ~np.isneginf(depth) & ~np.isnan(depth)))


def camera_info(msg: Any) -> tuple[np.ndarray, tuple[int, int]]:
    """CameraInfo → (K 3×3, (height, width))."""
    k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64).reshape(3, 3)
    return k, (int(msg.height), int(msg.width))


def resolve_intrinsics(who: str, info: tuple[np.ndarray, tuple[int, int]] | None, intrinsics: Sequence[float] | None,
                       native_hw: tuple[int, int] | None, info_topic: str) -> np.ndarray:
    """K at the depth resolution from the first CameraInfo (rescaled if it is for another
    size) or the configured ``[fx, fy, cx, cy]``; SourceError if neither is usable."""
    if info is not None:
        K, info_hw = info
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise SourceError(f"{who}: CameraInfo on {info_topic} has an invalid K: {K.ravel()}")
        if native_hw is not None and info_hw != native_hw and info_hw[0] > 0:
            return scale_intrinsics(K, info_hw, native_hw)
        return K
    if intrinsics is not None:
        if len(intrinsics) != 4:
            raise SourceError(f"{who}: intrinsics must be [fx, fy, cx, cy], got {intrinsics}")
        fx, fy, cx, cy = intrinsics
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    raise SourceError(f"{who}: no intrinsics: set camera_info_topic (sensor_msgs/CameraInfo) "
                      "or intrinsics=[fx,fy,cx,cy]")


def resolve_body_axes(who: str, body_axes: str, body_frame: str, world_axes: str) -> str:
    """'auto' = RDF for ``*_optical_frame`` bodies, else FLU (REP-103); checked against world_axes."""
    from common.conventions import convert_pose

    body = body_axes.upper()
    if body == "AUTO":
        body = "RDF" if body_frame.rstrip("/").endswith("optical_frame") else "FLU"
    try:
        convert_pose(np.eye(4), body, world_axes)
    except ValueError as e:
        raise SourceError(f"{who}: body_axes/world_axes: {e}") from None
    return body


def nearest_colour(sorted_times: np.ndarray, t: float, tolerance: float) -> int | None:
    """Index of the colour stamp nearest ``t`` within ``tolerance`` (ties: the earlier one)."""
    if len(sorted_times) == 0:
        return None
    j = int(np.searchsorted(sorted_times, t))
    cand = [k for k in (j - 1, j) if 0 <= k < len(sorted_times)]
    k = min(cand, key=lambda k: abs(sorted_times[k] - t))
    return k if abs(sorted_times[k] - t) <= tolerance else None


# ---------------------------------------------------------------- poses and tf


class GrowingTrack:
    """Pose samples added one by one (optionally only the newest ``maxlen`` kept), looked up
    with :class:`PoseTrack` semantics (rebuilt lazily after additions)."""

    def __init__(self, tolerance: float, interpolate: bool, max_gap: float, maxlen: int | None = None):
        self._t: deque = deque(maxlen=maxlen)
        self._T: deque = deque(maxlen=maxlen)
        self._track: PoseTrack | None = None
        self.args = (tolerance, interpolate, max_gap)

    def add(self, t: float, T: np.ndarray) -> None:
        """Append the 4×4 pose ``T`` at time ``t`` (s)."""
        self._t.append(float(t))
        self._T.append(T)
        self._track = None

    def __len__(self) -> int:
        return len(self._t)

    @property
    def newest(self) -> float:
        """Time (s) of the newest sample, -inf when empty."""
        return max(self._t) if self._t else -np.inf

    def at(self, t: float) -> np.ndarray | None:
        """The 4×4 pose at time ``t`` (s) as :meth:`PoseTrack.at` gives it, or None."""
        if self._track is None:
            tol, interp, gap = self.args
            self._track = PoseTrack(list(self._t), list(self._T) or np.zeros((0, 4, 4)), tol, interp, gap)
        return self._track.at(t)


class NoTfChain(SourceError):
    """No chain of transforms between two frames (yet)."""


class TfTree:
    """Static and time-stamped transforms (parent → child = child's pose in parent)."""

    def __init__(self, tolerance: float, interpolate: bool, max_gap: float, maxlen: int | None = None):
        self.static: dict[tuple[str, str], np.ndarray] = {}
        self.dynamic: dict[tuple[str, str], GrowingTrack] = {}
        self.args = (tolerance, interpolate, max_gap, maxlen)
        self.version = 0  # bumped when an edge appears

    def add(self, parent: str, child: str, t: float, T: np.ndarray, static: bool) -> None:
        """The child's 4×4 pose ``T`` in the parent at time ``t`` (s; ignored when ``static``)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if static:
            if (parent, child) not in self.static:
                self.version += 1
            self.static[(parent, child)] = T
            return
        tr = self.dynamic.get((parent, child))
        if tr is None:
            tr = self.dynamic[(parent, child)] = GrowingTrack(*self.args)
            self.version += 1
        tr.add(t, T)

    def add_message(self, msg: Any, static: bool, t_fallback: float | None = None) -> None:
        """Every transform of a TFMessage (header stamps, or ``t_fallback`` when given)."""
        for tr in msg.transforms:
            t = stamp_seconds(tr.header.stamp) if t_fallback is None else t_fallback
            self.add(tr.header.frame_id, tr.child_frame_id, t, tq(tr.transform.translation, tr.transform.rotation),
                     static)

    def finalize(self) -> None:
        """Kept for symmetry with the bag reader; lookups rebuild lazily."""

    @property
    def frames(self) -> set[str]:
        return {f for k in list(self.static) + list(self.dynamic) for f in k}

    def path(self, src: str, dst: str) -> TfChain | None:
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
        while (step := prev[n]) is not None:
            n, e = step
            edges.append(e)
        return edges[::-1]

    def lookup(self, edges: TfChain, t: float) -> np.ndarray | None:
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

    def newest(self, edges: TfChain) -> float:
        """Oldest of the newest samples of the chain's dynamic edges (+inf if all static)."""
        ts = [self.dynamic[(p, c)].newest for p, c, _ in edges if (p, c) not in self.static]
        return min(ts) if ts else np.inf


class PoseLookup:
    """The camera body's pose at a time, from a pose topic (+ the tf chain from its body
    frame to ``camera_frame`` when set) or from the tf chain ``world_frame`` → ``camera_frame``.

    ``at(t)`` returns the raw pose (body axes as in the messages) or None; it raises
    :class:`NoTfChain` while the needed chain does not exist. ``maxlen`` bounds the samples
    kept per track (live); None keeps all (bags)."""

    def __init__(self, who: str, cfg: SourceConfig, maxlen: int | None = None):
        self.who = who
        self.cfg = cfg
        args = (cfg.sync_tolerance, cfg.interpolate_pose, cfg.pose_max_gap)
        self.track = GrowingTrack(*args, maxlen=maxlen) if cfg.pose_topic else None
        self.tree = TfTree(*args, maxlen=maxlen)
        self.pose_child = ""
        self._chain: TfChain | None = None
        self._chain_version = -1

    @property
    def uses_tf(self) -> bool:
        """Whether the tf tree is needed (no pose topic, or a camera_frame below the pose's body)."""
        return self.track is None or bool(self.cfg.camera_frame)

    @property
    def body_frame(self) -> str:
        """The frame whose axes the camera body has (decides 'auto' body axes)."""
        return self.cfg.camera_frame or self.cfg.pose_frame or self.pose_child

    def add_pose(self, msg: Any, msgtype: str, t: float) -> None:
        """A PoseStamped / Odometry message of type ``msgtype`` at time ``t`` (s)."""
        assert self.track is not None, "add_pose without a pose topic"
        self.track.add(t, pose_from_msg(msg, msgtype))
        if msgtype == ODOMETRY and not self.pose_child:
            self.pose_child = msg.child_frame_id

    def _need_chain(self) -> tuple[str, str] | None:
        cfg = self.cfg
        if self.track is None:
            return cfg.world_frame, cfg.camera_frame
        pose_frame = cfg.pose_frame or self.pose_child
        if cfg.camera_frame and pose_frame and pose_frame.lstrip("/") != cfg.camera_frame.lstrip("/"):
            return pose_frame, cfg.camera_frame
        return None

    def chain(self) -> TfChain | None:
        """The tf edges needed (None when the pose topic alone gives the camera); NoTfChain if missing."""
        need = self._need_chain()
        if need is None:
            return None
        if self._chain is None or self._chain_version != self.tree.version:
            self._chain = self.tree.path(*need)
            self._chain_version = self.tree.version
        if self._chain is None:
            what = "world_frame" if self.track is None else "pose frame"
            raise NoTfChain(f"{self.who}: no tf chain from {what} {need[0]!r} to camera_frame {need[1]!r}; "
                            f"tf frames: {sorted(self.tree.frames)}")
        return self._chain

    def at(self, t: float) -> np.ndarray | None:
        """The raw 4×4 camera-body pose at time ``t`` (s), or None (see the class docstring)."""
        chain = self.chain()
        if self.track is None:
            assert chain is not None                   # without a pose topic the tf chain is always needed
            return self.tree.lookup(chain, t)
        T = self.track.at(t)
        if T is None or chain is None:
            return T
        E = self.tree.lookup(chain, t)
        return None if E is None else T @ E

    def newest(self) -> float:
        """The newest time the lookup can interpolate to without waiting for more samples."""
        out = np.inf if self.track is None else self.track.newest
        try:
            chain = self.chain()
        except NoTfChain:
            return -np.inf
        if chain:
            out = min(out, self.tree.newest(chain))
        return out

    def describe(self, pose_types: Iterable[str] = ()) -> str:
        """Where poses come from, for logs (``pose_types``: the pose topic's message types)."""
        cfg = self.cfg
        if self.track is not None:
            kinds = "/".join(sorted(t.split("/")[-1] for t in pose_types))
            return f"{cfg.pose_topic} ({kinds})" if kinds else cfg.pose_topic
        return f"tf {cfg.world_frame} -> {cfg.camera_frame}"
