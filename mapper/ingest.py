"""Frames in: the frame subscriber, robot liveliness, per-robot queues and the feature-space
fetch of the mapper (module map: :mod:`mapper.state`; ARCHITECTURE.md).

Data path::

    Zenoh callback (per sample)          map worker thread (mapper.map_worker)
    ─────────────────────────            ───────────────────────────────────
    decode_frame (validates) ──reject──▶ counted by reason, rate-limited log
         │ ok
         ▼
    per-robot bounded deque  ──full───▶ oldest dropped (counted)
         │
         └──────────── round-robin ───▶ Ingest.next_frame → integrate

Nothing raised in a callback escapes it; nothing malformed reaches the map. Frames of a
robot whose feature space is unknown are held in its queue until a ``get`` on
``robots/<robot>/feature_space`` answers (``queues.hold_unknown_space``); frames whose
feature space differs from the map's are rejected (maps never mix spaces). The first robot
space fetched creates the map.

A new per-frame check goes in :meth:`Ingest.on_frame` (reject with a short reason code: it
shows in ``stats().frames.rejected``); a new frame field's validation belongs in
:mod:`common.wire.frame`.
"""
from __future__ import annotations

import logging
import time

import cv2  # noqa: F401  (decode_frame's image codecs load OpenCV lazily: load it before the first frame)

from common.messages import MessageError, decode_feature_space, encode_feature_space
from common.wire import WireError, decode_frame
from mapper.state import MapperState, RobotState

log = logging.getLogger("rayfronts.mapper")


def reject_reason(err: Exception) -> str:
    """A short, stable reason code from a decode error (``'depth'``, ``'pose'``, ``'message'``...)."""
    text = str(err)
    if text.startswith("frame: "):
        text = text[len("frame: "):]
    head = text.split(":", 1)[0].strip().split(" ")[0]
    head = head.split(".")[0].split("[")[0]
    return head[:40] or "malformed"


class Ingest:
    """Zenoh callbacks for frames and liveliness, the feature-space thread, and the queues."""

    def __init__(self, state: MapperState):
        self.state = state
        self._rr = 0                         # round-robin start in next_frame

    # ============================================================ callbacks
    def on_frame(self, sample) -> None:
        s = self.state
        try:
            key_robot = s.keys.robot_from_key(str(sample.key_expr))
        except Exception:
            key_robot = None
        try:
            s.received += 1
            t0 = time.perf_counter()
            try:
                data = sample.payload.to_bytes()
                frame = decode_frame(data, limits=s.limits)
            except WireError as e:
                s.reject(key_robot if key_robot in s.robots else None, reject_reason(e), str(e))
                return
            s.timings["decode_ms"].add((time.perf_counter() - t0) * 1e3)
            if key_robot is None or frame.robot != key_robot:
                s.reject(None, "robot_mismatch", f"frame robot {frame.robot!r} on key {sample.key_expr}")
                return
            if frame.features is None:
                s.reject(key_robot, "no_features", "frame carries no features")
                return
            with s.qlock:
                st = s.robot(key_robot)
                st.received += 1
                if st.feature_space and frame.feature_space != st.feature_space:
                    # the edge may have restarted with another basis: refetch, reject meanwhile
                    st.fetch_after = 0.0
                    st.space_ok = False
                    st.feature_space = ""
                    s.space_wake.set()
                if len(st.queue) == st.queue.maxlen:
                    st.dropped += 1
                    s.dropped += 1
                st.queue.append((frame, time.time()))
                if not st.space_ok and not st.space_error:
                    # frames flow, so the edge's space is ready: fetch now rather than at the
                    # retry period (at most every 0.2 s), else frames pile up meanwhile
                    now = time.monotonic()
                    if st.fetch_after > now and now - st.fetch_started > 0.2:
                        st.fetch_after = 0.0
                        s.space_wake.set()
            s.wake.set()
        except Exception as e:  # never raise out of a callback
            s.reject(key_robot, "internal", repr(e))

    def on_alive(self, sample) -> None:
        s = self.state
        try:
            import zenoh

            robot = s.keys.robot_from_key(str(sample.key_expr))
            if robot is None:
                return
            with s.qlock:
                st = s.robot(robot)
                if sample.kind == zenoh.SampleKind.PUT:
                    st.present, st.seen_at, st.gone_at = True, time.time(), None
                    st.fetch_after = 0.0   # (re)fetch the space of a (re)started edge
                    log.info("robot %s present", robot)
                else:
                    st.present, st.gone_at = False, time.time()
                    log.info("robot %s gone", robot)
            s.wake.set()
            s.space_wake.set()
        except Exception as e:
            log.warning("liveliness callback: %s", e)

    def on_edge_status(self, sample) -> None:
        """An edge's own state (``robots/<robot>/edge_status``). A refusal or failure is logged
        once per (robot, state, reason), shown in stats (``robots.<r>.edge_state`` /
        ``edge_reason``), and stops the feature-space retries (and their warnings) for that
        robot until its edge comes back."""
        s = self.state
        try:
            from common.messages import decode_edge_status

            robot = s.keys.robot_from_key(str(sample.key_expr))
            if robot is None:
                return
            try:
                msg = decode_edge_status(sample.payload.to_bytes())
            except MessageError as e:
                s.warn(f"{robot}:edge_status", "bad edge status from %s: %s", robot, e)
                return
            if msg["robot"] != robot:
                return
            with s.qlock:
                st = s.robot(robot)
                changed = (st.edge_state, st.edge_reason) != (msg["state"], msg["reason"])
                st.edge_state, st.edge_reason = msg["state"], msg["reason"]
            if changed and msg["state"] in ("refused", "failed"):
                log.error("robot %s: its edge %s: %s", robot,
                          "refused to start" if msg["state"] == "refused" else "failed", msg["reason"])
            elif changed:
                log.info("robot %s: edge %s", robot, msg["state"])
        except Exception as e:  # never raise out of a callback
            log.warning("edge status callback: %s", e)

    # ====================================================== feature spaces
    def space_loop(self) -> None:
        """The feature-space thread: fetches the space of every robot that needs it."""
        s = self.state
        # its own event: the map worker's one is set by every frame and stays set while
        # frames are queued, which would turn this loop into a GIL-holding busy spin
        while not s.stop.is_set():
            s.space_wake.wait(0.5)
            s.space_wake.clear()
            now = time.monotonic()
            with s.qlock:
                todo = [st.name for st in s.robots.values()
                        if not st.space_ok and not st.space_error and st.fetch_after <= now
                        and st.edge_state not in ("refused", "failed")]
            for robot in todo:
                if s.stop.is_set():
                    return
                self.fetch_space(robot)

    def fetch_space(self, robot: str) -> None:
        from common.feature_space import FeatureSpace

        s = self.state
        st = s.robots[robot]
        st.fetch_started = time.monotonic()
        try:
            replies = list(s.session.get(s.keys.feature_space(robot), timeout=3.0))
        except Exception as e:
            st.fetch_after = time.monotonic() + 1.0
            log.debug("feature space get for %s failed: %s", robot, e)
            return
        body = None
        err = "no reply"
        for r in replies:
            if r.ok is None:
                continue
            try:
                got, body = decode_feature_space(r.ok.payload.to_bytes())
                break
            except MessageError as e:
                err = str(e)
        if body is None:
            st.fetch_after = time.monotonic() + 1.0
            s.warn(f"{robot}:space", "feature space of %s not available yet: %s", robot, err)
            return
        try:
            fs = FeatureSpace.from_body(body)
        except Exception as e:
            st.fetch_after = time.monotonic() + 5.0
            s.warn(f"{robot}:space", "feature space of %s is invalid: %s", robot, e)
            return
        fs_id = fs.id
        with s.lock:
            if s.map is None:
                s.create_map(fs, encode_feature_space(robot, body))
            ok = fs_id == s.space_id
        with s.qlock:
            st.feature_space = fs_id
            st.space_ok = ok
            st.space_error = "" if ok else f"robot space {fs_id} differs from the map's {s.space_id}"
        if ok:
            log.info("robot %s feature space %s", robot, fs_id)
            s.wake.set()
        else:
            log.error("robot %s: %s; its frames are rejected", robot, st.space_error)

    # ============================================================== queues
    def next_frame(self) -> tuple[RobotState, object, float] | None:
        """Round-robin over robots whose space matches the map; rejects frames of mismatched ones."""
        s = self.state
        with s.qlock:
            names = sorted(s.robots)
            if not names:
                return None
            start = self._rr
            for i in range(len(names)):
                st = s.robots[names[(start + i) % len(names)]]
                if not st.queue:
                    continue
                if st.space_error:
                    n = len(st.queue)
                    st.queue.clear()
                    st.rejected["feature_space_differs"] += n
                    s.rejected["feature_space_differs"] += n
                    continue
                if not st.space_ok:
                    if not s.cfg.queues.hold_unknown_space:
                        n = len(st.queue)
                        st.queue.clear()
                        st.rejected["feature_space_unknown"] += n
                        s.rejected["feature_space_unknown"] += n
                    continue
                frame, t_recv = st.queue.popleft()
                if frame.feature_space != st.feature_space:
                    st.rejected["feature_space_mismatch"] += 1
                    s.rejected["feature_space_mismatch"] += 1
                    continue
                self._rr = (start + i + 1) % len(names)
                return st, frame, t_recv
        return None
