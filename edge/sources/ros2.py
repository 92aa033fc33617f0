"""Live ROS 2 topics over Zenoh as a frame source (``source.kind=ros2``): no ROS install.

The robot's ROS 2 graph is reached through plain Zenoh, in one of two key layouts
(``source.ros_keys``, see :mod:`common.ros2`): ``rmw_zenoh`` (the robot runs ROS 2 with
``RMW_IMPLEMENTATION=rmw_zenoh_cpp``; keys ``<ros_domain>/<topic>/<dds type>/<type hash>``,
any type hash accepted: Humble's ``TypeHashNotSupported`` or Jazzy's ``RIHS01_...``) or
``bridge`` (zenoh-bridge-ros2dds next to a DDS robot; keys ``<topic>``, the message type
is inferred per topic by decoding: an image topic whose name contains ``compressed`` is
tried as CompressedImage first, the pose topic as Odometry then PoseStamped). Payloads
are CDR, decoded with rosbags' typestore (:mod:`common.ros2.cdr`).

It reads the same topics and options as the ``rosbag`` source (``rgb_topic``,
``depth_topic``, ``camera_info_topic``, ``intrinsics``, ``pose_topic`` or ``tf_topic`` +
``tf_static_topic`` with ``world_frame`` / ``camera_frame`` / ``pose_frame``,
``body_axes``, ``world_axes``, ``depth_scale``, ``sync_tolerance``, ``interpolate_pose``,
``pose_max_gap``, ``use_header_stamps``, ``frame_skip``, ``max_frames``) and builds frames
with the same code (:mod:`edge.sources.ros_msgs`), so a stream and a bag holding the same
messages give the same frames: depth drives; the colour image nearest in time within
``sync_tolerance``; the pose at the depth stamp (interpolated, no extrapolation).

Live behaviour (decisions):

* Zenoh session: its own, to ``ros_connect`` (e.g. the robot's local ``rmw_zenohd`` at
  ``tcp/127.0.0.1:7447``) in client mode, or, with ``ros_connect=[]``, the edge's own
  ``zenoh`` section (same network as the base station).
* Subscriber callbacks only append ``(payload, receive time)`` to a bounded buffer per
  topic (``ros_queue``; a full buffer drops its oldest message, counted as
  ``dropped_full``); decoding happens on the pipeline thread.
* A depth image waits until a colour image and pose samples at or after its stamp have
  arrived, or ``ros_max_delay`` seconds of wall clock, then is matched exactly as in a bag
  (colour nearest in time, pose interpolated between the samples around the stamp).
  Frames without colour, pose, tf chain or valid depth are skipped and counted by reason
  in ``skipped`` with a rate-limited warning (``ros_log_every``).
* Per topic: a message whose stamp is older than the newest one already taken is dropped
  and counted (``out_of_order``); a message that does not decode or has an unsupported
  encoding is counted (``bad``) with one line naming the topic; a stream topic (colour,
  depth, pose, tf; not CameraInfo / tf_static, which may be sent once) silent for more
  than 2 s while the others flow is reported (``stalls``). ``stats()`` returns it all.
* Latched topics: ``/tf_static`` and CameraInfo are subscribed with a Zenoh advanced
  subscriber with history (late-publisher detection), so the caches of transient-local
  publishers (rmw_zenoh's advanced publishers, e.g. robot_state_publisher's static tf sent
  long before the edge starts) are fetched, and once more with a plain ``get`` for older
  publication caches. Pose and tf tracks keep the newest 2000 samples per track.
* Start-up waits for the first matched frame, logging every ``ros_log_every`` seconds
  which topics have been seen (with types and counts) and which not; with
  ``ros_startup_timeout`` > 0 it gives up with that listing as the error. The stream ends
  when ``stop`` is set, after ``max_frames``, or after ``ros_idle_timeout`` s without a frame.

:func:`list_topics` (``rayfronts edge --list-topics``) lists what the robot publishes:
rmw_zenoh graph tokens (``@ros2_lv/<domain>/...``) plus the data keys seen for a moment.
"""
from __future__ import annotations

import functools
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from common.conventions import convert_pose
from edge.sources.base import FrameSource, RateLimitedLog, native_frame
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.ros_msgs import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    ODOMETRY,
    POSE_STAMPED,
    TF,
    NoTfChain,
    PoseLookup,
    camera_info,
    decode_depth,
    decode_rgb,
    has_valid_depth,
    nearest_colour,
    resolve_body_axes,
    resolve_intrinsics,
    stamp_seconds,
)

if TYPE_CHECKING:
    from common.zenoh_session import SessionGuard, ZenohConfig

log = logging.getLogger(__name__)

STALL_S = 2.0
TRACK_SAMPLES = 2000
ROLE_TYPES = {
    "rgb": (IMAGE, COMPRESSED),
    "depth": (IMAGE, COMPRESSED),
    "info": (CAMERA_INFO,),
    "pose": (ODOMETRY, POSE_STAMPED),
    "tf": (TF,),
    "tf_static": (TF,),
}


def _ros_session_config(cfg: SourceConfig, zenoh: ZenohConfig | None) -> ZenohConfig:
    from common.zenoh_session import ZenohConfig

    if cfg.ros_connect:
        return ZenohConfig(mode="client", connect=list(cfg.ros_connect))
    if zenoh is not None:
        return zenoh
    return ZenohConfig(mode="client", connect=["tcp/127.0.0.1:7447"])


def _candidates(role: str, topic: str, key_type: str | None) -> tuple[str, ...]:
    types = ROLE_TYPES[role]
    if key_type is not None:
        return (key_type,)
    if role in ("rgb", "depth") and "compressed" in topic.lower():
        return (COMPRESSED, IMAGE)
    return types


class Ros2Source(FrameSource):
    kind = "ros2"
    default_fps = 30.0

    def __init__(self, cfg: SourceConfig, zenoh=None, stop: threading.Event | None = None):
        super().__init__(cfg)
        from common.ros2 import cdr
        from common.ros2.keys import RosKeyError, check_domain, check_layout, normalize_topic, subscribe_key

        try:
            cdr.typestore()
        except cdr.CdrError as e:
            raise SourceError(f"ros2: {e}") from None
        self._cdr = cdr
        if not cfg.sync_tolerance > 0:
            raise SourceError(f"ros2: sync_tolerance must be > 0 seconds, got {cfg.sync_tolerance}")
        if cfg.ros_queue < 1:
            raise SourceError(f"ros2: ros_queue must be >= 1, got {cfg.ros_queue}")
        if cfg.frame_skip < 0:
            raise SourceError(f"ros2: frame_skip must be >= 0, got {cfg.frame_skip}")
        if not cfg.rgb_topic or not cfg.depth_topic:
            raise SourceError("ros2: set source.rgb_topic and source.depth_topic "
                              "(`rayfronts edge --list-topics` shows what the robot publishes)")
        if not cfg.pose_topic and not (cfg.world_frame and cfg.camera_frame):
            raise SourceError("ros2: no pose source: set pose_topic, or world_frame and camera_frame to use /tf")
        try:
            check_layout(cfg.ros_keys)
            self.domain = check_domain(cfg.ros_domain)
            topics = {"rgb": cfg.rgb_topic, "depth": cfg.depth_topic}
            if cfg.camera_info_topic:
                topics["info"] = cfg.camera_info_topic
            if cfg.pose_topic:
                topics["pose"] = cfg.pose_topic
            self.lookup = PoseLookup("ros2", cfg, maxlen=TRACK_SAMPLES)
            if self.lookup.uses_tf:
                topics["tf"] = cfg.tf_topic
                topics["tf_static"] = cfg.tf_static_topic
            self.topics = {r: normalize_topic(t) for r, t in topics.items()}
            self._keys = {r: subscribe_key(t, cfg.ros_keys, self.domain) for r, t in self.topics.items()}
        except RosKeyError as e:
            raise SourceError(f"ros2: {e}") from None
        if cfg.camera_info_topic == "" and cfg.intrinsics is not None:
            resolve_intrinsics("ros2", None, cfg.intrinsics, (1, 1), "")  # validates the list
        self._zcfg = _ros_session_config(cfg, zenoh)
        self._stop = stop or threading.Event()
        self._guard: SessionGuard | None = None
        self._cond = threading.Condition()
        self._inbox: dict[str, deque] = {r: deque() for r in self.topics}
        self._arrivals: Counter[str] = Counter()
        self._tstats: dict[str, Counter[str]] = {t: Counter() for t in set(self.topics.values())}
        self._types: dict[str, str] = {}  # topic -> decoded type
        self._last_arrival: dict[str, float] = {}
        self._stalled: set[str] = set()
        self._newest: dict[str, float] = {}
        self._rlog = RateLimitedLog(cfg.ros_log_every, log)
        self._rgb: deque = deque(maxlen=cfg.ros_queue)  # (stamp, ordinal, msg, type)
        self._pending: deque = deque()  # (index, stamp, depth, t_arrival)
        self._info: tuple[np.ndarray, tuple[int, int]] | None = None    # (K, (h, w)) of the first CameraInfo
        self.body_axes: str | None = None
        self.frames_out = 0
        self.name = f"ros2:{cfg.ros_keys}:{self.topics['depth']}"
        self.world_frame = (f"the robot's world frame from {self.lookup.describe()} with {cfg.world_axes} axes, "
                            "re-expressed as ENU (z up); camera body converted to RDF")

    # ------------------------------------------------------------------ zenoh side
    def _connect(self) -> None:
        from common.zenoh_session import SessionGuard, ZenohConnectError

        try:
            self._guard = SessionGuard.open(self._zcfg, stop=self._stop, default_mode="client")
        except ZenohConnectError as e:
            raise SourceError(f"ros2: {e}") from None
        import zenoh.ext

        s = self._guard.session
        for role, key in self._keys.items():
            cb = functools.partial(self._on_sample, role)
            if role in ("tf_static", "info"):  # latched topics: also the publishers' caches (late joiner)
                self._guard.add(zenoh.ext.declare_advanced_subscriber(
                    s, key, cb, history=zenoh.ext.HistoryConfig(detect_late_publishers=True)))
            else:
                self._guard.add(s.declare_subscriber(key, cb))
        for role in ("tf_static", "info"):
            if role in self._keys:
                try:  # older publication caches (ze_publication_cache) answer a plain get
                    s.get(self._keys[role], lambda reply, role=role: self._on_reply(role, reply), timeout=2.0)
                except Exception as e:
                    log.debug("ros2: get %s failed: %s", self._keys[role], e)
        log.info("ros2: subscribed (%s layout, domain %d): %s", self.cfg.ros_keys, self.domain,
                 ", ".join(f"{r}={self._keys[r]}" for r in self._keys))

    def _on_reply(self, role: str, reply) -> None:
        try:
            if reply.ok is not None:
                self._on_sample(role, reply.ok)
        except Exception as e:  # never raise out of a callback
            log.debug("ros2: reply on %s: %s", role, e)

    def _on_sample(self, role: str, sample) -> None:
        try:
            item: tuple = (str(sample.key_expr), sample.payload.to_bytes(), time.time())
            topic = self.topics[role]
            with self._cond:
                n = self._arrivals[role]
                self._arrivals[role] = n + 1
                item = (*item, n)  # arrival ordinal: frame indices stay true when a full buffer drops
                box = self._inbox[role]
                if len(box) >= self.cfg.ros_queue:
                    box.popleft()
                    self._tstats[topic]["dropped_full"] += 1
                box.append(item)
                self._tstats[topic]["received"] += 1
                self._last_arrival[topic] = time.monotonic()
                self._cond.notify_all()
        except Exception as e:  # never raise out of a Zenoh callback
            log.debug("ros2: sample on %s: %s", role, e)

    def close(self) -> None:
        g, self._guard = self._guard, None
        if g is not None:
            g.close()
            log.info("ros2: closed; %s", self.stats())

    # ------------------------------------------------------------------ decoding
    def _bad(self, topic: str, why: str) -> None:
        self._tstats[topic]["bad"] += 1
        self._rlog.warn(f"bad:{topic}", "ros2: %s: %s", topic, why)

    def _decode(self, role: str, key: str, payload: bytes):
        """(msg, type) or None (counted)."""
        from common.ros2.keys import RosKeyError, parse_key

        topic = self.topics[role]
        try:
            _, key_type, _ = parse_key(key, self.cfg.ros_keys, self.domain)
        except RosKeyError as e:
            self._bad(topic, str(e))
            return None
        if key_type is not None and key_type not in ROLE_TYPES[role]:
            self._bad(topic, f"type {key_type} is not one of {ROLE_TYPES[role]} (check the {role} topic)")
            return None
        known = self._types.get(topic)
        cands = (known,) if known and key_type is None else _candidates(role, topic, key_type)
        try:
            msg, mtype = self._cdr.deserialize_any(payload, cands)
        except self._cdr.CdrError as e:
            self._bad(topic, f"cannot decode the message ({e})")
            return None
        self._types[topic] = mtype
        return msg, mtype

    def _stamp(self, msg, t_recv: float) -> float:
        if self.cfg.use_header_stamps and hasattr(msg, "header"):
            t = stamp_seconds(msg.header.stamp)
            if t > 0:
                return t
        return t_recv

    def _in_order(self, topic: str, t: float) -> bool:
        if t < self._newest.get(topic, -np.inf):
            self._tstats[topic]["out_of_order"] += 1
            self._rlog.warn(f"ooo:{topic}", "ros2: %s: stamp %.3f is older than the newest taken (%.3f); dropped",
                            topic, t, self._newest[topic])
            return False
        self._newest[topic] = t
        return True

    def _drain(self) -> None:
        with self._cond:
            items = {r: list(b) for r, b in self._inbox.items() if b}
            for r in items:
                self._inbox[r].clear()
        for role in ("tf_static", "tf", "info", "pose", "rgb", "depth"):
            for key, payload, t_recv, index in items.get(role, ()):
                self._take(role, key, payload, t_recv, index)

    def _take(self, role: str, key: str, payload: bytes, t_recv: float, index: int) -> None:
        """Decode one received message (``t_recv``: arrival wall clock, s; ``index``: arrival
        ordinal on its topic) and file it: tf tree, CameraInfo, pose lookup, colour or depth buffer."""
        cfg = self.cfg
        topic = self.topics[role]
        if role == "depth":  # frame_skip on the depth ordinal, as in a bag
            if index % (cfg.frame_skip + 1):
                return
        dec = self._decode(role, key, payload)
        if dec is None:
            if role == "depth":
                self._skip(f"undecodable depth message on {topic}")
            return
        msg, mtype = dec
        self._tstats[topic]["decoded"] += 1
        if role in ("tf", "tf_static"):
            self.lookup.tree.add_message(msg, role == "tf_static", None if cfg.use_header_stamps else t_recv)
        elif role == "info":
            if self._info is None:
                self._info = camera_info(msg)
        elif role == "pose":
            t = self._stamp(msg, t_recv)
            if self._in_order(topic, t):
                self.lookup.add_pose(msg, mtype, t)
        elif role == "rgb":
            t = self._stamp(msg, t_recv)
            if self._in_order(topic, t):
                self._rgb.append((t, index, msg, mtype))
        else:
            self._take_depth(topic, msg, mtype, t_recv, index)

    def _take_depth(self, topic: str, msg: Any, mtype: str, t_recv: float, index: int) -> None:
        """Decode a depth message and queue it for matching (skipped and counted when out of
        order, undecodable or of a changed size)."""
        cfg = self.cfg
        t = self._stamp(msg, t_recv)
        if not self._in_order(topic, t):
            self._skip("out-of-order depth stamp")
            return
        try:
            d = decode_depth(msg, mtype, cfg.depth_scale)
        except ValueError as e:
            self._bad(topic, str(e))
            self._skip(f"unsupported depth message on {topic}")
            return
        if self.native_hw is None:
            self.native_hw = d.shape
        elif d.shape != self.native_hw:
            self._bad(topic, f"depth size changed from {self.native_hw} to {d.shape}")
            self._skip("depth size changed")
            return
        if len(self._pending) >= cfg.ros_queue:
            self._pending.popleft()
            self._tstats[topic]["dropped_full"] += 1
            self._skip("depth buffer full (matching fell behind)")
        self._pending.append((index, t, d, time.monotonic()))

    # ------------------------------------------------------------------ matching
    def _skip_log(self, reason: str, detail: str = "") -> None:
        self._skip(reason)
        self._rlog.warn(f"skip:{reason}", "ros2: frame skipped: %s%s (%d so far)", reason,
                        f" ({detail})" if detail else "", self.skipped[reason])

    def _intrinsics(self):
        if self.native_K is None and (self._info is not None or self.cfg.intrinsics is not None):
            self.native_K = resolve_intrinsics("ros2", self._info, self.cfg.intrinsics, self.native_hw,
                                               self.topics.get("info", ""))
        return self.native_K

    def _match(self) -> Iterator:
        cfg = self.cfg
        now = time.monotonic()
        while self._pending:
            index, t, depth, t_arr = self._pending[0]
            late = now - t_arr > cfg.ros_max_delay
            rgb_ready = bool(self._rgb) and self._rgb[-1][0] >= t
            pose_ready = self.lookup.newest() >= t
            K = self._intrinsics()
            if not late and not (rgb_ready and pose_ready and K is not None):
                return
            self._pending.popleft()
            if K is None:
                self._skip_log("no CameraInfo yet", f"waiting for {self.topics.get('info')}")
                continue
            if not has_valid_depth(depth):
                self._skip_log("no valid depth pixel")
                continue
            times = np.fromiter((r[0] for r in self._rgb), np.float64, len(self._rgb))
            k = nearest_colour(times, t, cfg.sync_tolerance)
            if k is None:
                self._skip_log("no colour image within sync_tolerance", f"{self.topics['rgb']} at {t:.3f}")
                continue
            try:
                T = self.lookup.at(t)
            except NoTfChain as e:
                self._skip_log("no tf chain to camera_frame", str(e).removeprefix("ros2: "))
                continue
            if T is None or not np.all(np.isfinite(T)):
                self._skip_log("no pose at the depth stamp", f"{self.lookup.describe()} at {t:.3f}")
                continue
            if self.body_axes is None:
                self.body_axes = resolve_body_axes("ros2", cfg.body_axes, self.lookup.body_frame, cfg.world_axes)
            _, ordinal, rmsg, rtype = self._rgb[k]
            try:
                rgb = decode_rgb(rmsg, rtype)
            except ValueError as e:
                self._bad(self.topics["rgb"], str(e))
                self._skip("unsupported colour message")
                continue
            pose = convert_pose(T, self.body_axes, cfg.world_axes)
            yield native_frame(index, t, pose, K, depth, rgb, rgb_index=ordinal)

    # ------------------------------------------------------------------ iteration
    def _check_stalls(self) -> None:
        now = time.monotonic()
        if not self._last_arrival:
            return
        freshest = max(self._last_arrival.values())
        streams = {self.topics[r] for r in ("rgb", "depth", "pose", "tf") if r in self.topics}
        for topic, t in self._last_arrival.items():
            if topic not in streams:  # CameraInfo / tf_static may be latched (sent once)
                continue
            silent = now - t
            if silent > STALL_S and now - freshest < STALL_S / 4:  # silent while another stream still flows
                if topic not in self._stalled:
                    self._stalled.add(topic)
                    self._tstats[topic]["stalls"] += 1
                self._rlog.warn(f"stall:{topic}", "ros2: %s: no message for %.1f s (the other topics flow)",
                                topic, silent)
            else:
                self._stalled.discard(topic)

    def seen_summary(self) -> str:
        seen, unseen = [], []
        for role, topic in self.topics.items():
            n = self._tstats[topic]["received"]
            if n:
                seen.append(f"{topic} [{self._types.get(topic, '?')}] {n} msgs")
            else:
                unseen.append(f"{topic} ({role})")
        return (f"seen: {', '.join(seen) or 'nothing'}; not seen yet: {', '.join(unseen) or 'none'}"
                + (f"; skipped: {dict(self.skipped)}" if self.skipped else ""))

    def __iter__(self) -> Iterator:
        cfg = self.cfg
        self._connect()
        try:
            t0 = last_frame = last_wait_log = time.monotonic()
            while not self._stop.is_set():
                self._drain()
                for fr in self._match():
                    if self.frames_out == 0:
                        log.info("ros2: first frame matched after %.1f s; %s", time.monotonic() - t0,
                                 self.seen_summary())
                    yield self._finish(fr, self.frames_out)
                    self.frames_out += 1
                    last_frame = time.monotonic()
                    if cfg.max_frames is not None and self.frames_out >= cfg.max_frames:
                        return
                    if self._stop.is_set():
                        return
                now = time.monotonic()
                self._check_stalls()
                if self.frames_out == 0:
                    if now - last_wait_log >= cfg.ros_log_every:
                        log.warning("ros2: waiting for the first matched frame (%.0f s); %s", now - t0,
                                    self.seen_summary())
                        last_wait_log = now
                    if cfg.ros_startup_timeout > 0 and now - t0 > cfg.ros_startup_timeout:
                        raise SourceError(f"ros2: no frame matched within {cfg.ros_startup_timeout:g} s; "
                                          f"{self.seen_summary()}")
                elif cfg.ros_idle_timeout > 0 and now - last_frame > cfg.ros_idle_timeout:
                    log.info("ros2: no new frame for %.1f s: stream ended", cfg.ros_idle_timeout)
                    return
                with self._cond:
                    if not any(self._inbox.values()):
                        self._cond.wait(0.05)
        finally:
            self.close()

    def __len__(self) -> int:
        """Live: frames yielded so far (the stream's length is not known in advance)."""
        return self.frames_out

    def stats(self) -> dict:
        """Per-topic counters (received, decoded, dropped_full, out_of_order, bad, stalls),
        types, seconds since the last message, skipped frames by reason, frames yielded."""
        now = time.monotonic()
        with self._cond:
            topics = {t: {**dict(c), "type": self._types.get(t),
                          "last_age_s": (round(now - self._last_arrival[t], 3) if t in self._last_arrival else None)}
                      for t, c in self._tstats.items()}
        return {"frames": self.frames_out, "topics": topics, "skipped": dict(self.skipped)}


# ---------------------------------------------------------------------- listing
def list_topics(cfg: SourceConfig, zenoh: ZenohConfig | None = None, seconds: float = 2.0) -> list[dict]:
    """What the robot publishes: rmw_zenoh publisher tokens of ``ros_domain`` and the data
    keys seen during ``seconds`` (both layouts), one dict per topic (topic, type, via,
    publishers, samples, bytes)."""
    from common.ros2.keys import BRIDGE, RosKeyError, check_domain, parse_key, parse_liveliness
    from common.zenoh_session import SessionGuard

    domain = check_domain(cfg.ros_domain)
    found: dict[str, dict] = {}
    lock = threading.Lock()

    def entry(topic):
        return found.setdefault(topic, {"topic": topic, "type": None, "via": set(), "publishers": 0,
                                        "samples": 0, "bytes": 0})

    def on_data(sample):
        key = str(sample.key_expr)
        if key.startswith("@"):
            return
        try:
            topic, typ, _ = parse_key(key, cfg.ros_keys, domain)
        except RosKeyError:
            return
        with lock:
            e = entry(topic)
            e["type"] = e["type"] or typ
            e["via"].add("data")
            e["samples"] += 1
            e["bytes"] += len(sample.payload)

    with SessionGuard.open(_ros_session_config(cfg, zenoh), default_mode="client") as g:
        s = g.session
        for reply in s.liveliness().get(f"@ros2_lv/{domain}/**", timeout=max(seconds, 0.5)):
            if reply.ok is None:
                continue
            tok = parse_liveliness(str(reply.ok.key_expr))
            if tok and tok["kind"] == "publisher":
                with lock:
                    e = entry(tok["topic"])
                    e["type"] = e["type"] or tok["type"]
                    e["via"].add("graph")
                    e["publishers"] += 1
        g.add(s.declare_subscriber("**" if cfg.ros_keys == BRIDGE else f"{domain}/**", on_data))
        time.sleep(max(seconds, 0.0))
    out = []
    with lock:
        for e in sorted(found.values(), key=lambda e: e["topic"]):
            out.append({**e, "via": sorted(e["via"]), "rate_hz": round(e["samples"] / seconds, 2) if seconds else 0})
    return out


def format_topics(rows: list[dict]) -> str:
    """A text table of :func:`list_topics` rows (rates in Hz)."""
    if not rows:
        return "no ROS 2 topics seen (check source.ros_keys, source.ros_domain and source.ros_connect)"
    w = max(len(r["topic"]) for r in rows)
    lines = [f"{'topic':<{w}}  {'type':<34} {'via':<11} {'rate':>7}"]
    for r in rows:
        lines.append(f"{r['topic']:<{w}}  {str(r['type'] or '?'):<34} {','.join(r['via']):<11} "
                     f"{r['rate_hz']:>5.1f}Hz")
    return "\n".join(lines)
