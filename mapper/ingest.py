"""Frames in: the frame subscriber, robot liveliness, per-robot queues and the feature-space
fetch of the mapper (module map: ARCHITECTURE.md).

Data path::

    Zenoh callback (per sample)   decode thread (mapper-decode)      map worker thread
    ──────────────────────────    ─────────────────────────────      ──────────────────
    bytes → bounded raw queue ──▶ decode_frame (validates) ─reject─▶ counted by reason
      (full: oldest dropped,        │ ok                              (WireError.reason)
       counted)                     ▼
                                  per-robot bounded deque ──full──▶ oldest dropped (counted)
                                    │
                                    └─────── round-robin ─────────▶ Ingest.next_frame → integrate

The Zenoh callback only copies the payload into a bounded queue (at most
:data:`RAW_QUEUE_MAX` messages and 4 x ``queues.max_message_mb`` bytes): decoding, which
costs ~3 ms for a real frame and is bounded for a hostile one (``common.wire``: < 10 ms CPU
for any rejected header), runs on the ``mapper-decode`` thread. When the queue is full the
callback waits for room (at most :data:`RAW_WAIT_S`; Zenoh then holds back that link's
publisher, as its ``BLOCK`` congestion control means), and only then drops the oldest
undecoded message (counted in ``frames.dropped``). So a flooding publisher is slowed down on
its own link instead of pushing other robots' frames out, and the Zenoh threads that carry
queries never decode anything.

Nothing raised in a callback escapes it; nothing malformed reaches the map. Frames of a
robot whose feature space is unknown are held in its queue until a ``get`` on
``robots/<robot>/feature_space`` answers (``queues.hold_unknown_space``); frames whose
feature space differs from the map's are rejected (maps never mix spaces). The first robot
space fetched creates the map.

A frame whose ``feature_space`` differs from its robot's known space is rejected and counted
(``feature_space_mismatch``) without touching the robot's state or its queue: only the
robot itself changes its space, by announcing it (its liveliness token appearing again, as
a restarted edge's does, makes the mapper fetch ``robots/<robot>/feature_space`` anew).

A new per-frame check goes in :meth:`Ingest.on_frame` (reject with a short reason code: it
shows in ``stats().frames.rejected``); a new frame field's validation belongs in
:mod:`common.wire.frame`.
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING

import cv2  # noqa: F401  (decode_frame's image codecs load OpenCV lazily: load it before the first frame)

from common.messages import MessageError, decode_feature_space, encode_feature_space
from common.wire import WireError, decode_frame
from mapper.state import MapperState, RobotState

if TYPE_CHECKING:
    import zenoh

    from common.frame import Frame

log = logging.getLogger("rayfronts.mapper")


#: frames waiting for the decode thread
RAW_QUEUE_MAX = 64
#: how long a frame callback waits for room in a full decode queue before dropping the oldest
RAW_WAIT_S = 2.0


def reject_reason(err: Exception) -> str:
    """A short, stable reason code from a decode error, from a fixed vocabulary
    (``frame.depth``, ``frame.pose``, ..., ``header``, ``schema``, ``version``, ``message``;
    see ``common.wire.WireError.reason``), never the attacker's text."""
    if isinstance(err, WireError):
        return err.reason
    from common.wire.envelope import reject_reason as _reason

    return _reason(str(err))


class Ingest:
    """Zenoh callbacks for frames and liveliness, the feature-space thread, and the queues."""

    def __init__(self, state: MapperState) -> None:
        self.state = state
        self._rr = 0                         # round-robin start in next_frame
        self._raw: collections.deque = collections.deque()   # (key, bytes, t_recv) for the decode thread
        self._raw_bytes = 0
        self._raw_lock = threading.Lock()
        self._raw_room = threading.Condition(self._raw_lock)   # notified when the decode thread takes one
        self._raw_ready = threading.Event()
        self.raw_dropped = 0                 # frames dropped before decoding (raw queue full)

    # ============================================================ callbacks
    def on_frame(self, sample: zenoh.Sample) -> None:
        """Zenoh callback: copy the payload into the bounded raw queue (nothing else)."""
        state = self.state
        try:
            key = str(sample.key_expr)
            data = sample.payload.to_bytes()
            t_recv = time.time()
            max_bytes = 4 * state.limits.max_message_bytes
            dropped = []
            with self._raw_lock:
                state.received += 1
                if len(self._raw) >= RAW_QUEUE_MAX:   # back-pressure on this link first
                    end = time.monotonic() + RAW_WAIT_S
                    while len(self._raw) >= RAW_QUEUE_MAX and not state.stop.is_set():
                        rem = end - time.monotonic()
                        if rem <= 0:
                            break
                        self._raw_room.wait(rem)
                self._raw.append((key, data, t_recv))
                self._raw_bytes += len(data)
                while len(self._raw) > RAW_QUEUE_MAX or (self._raw_bytes > max_bytes and len(self._raw) > 1):
                    old = self._raw.popleft()
                    self._raw_bytes -= len(old[1])
                    dropped.append(old[0])
            if dropped:
                self._count_raw_drops(dropped)
            self._raw_ready.set()
        except Exception as e:  # never raise out of a callback
            state.reject(None, "internal", repr(e))

    def _count_raw_drops(self, keys: list[str]) -> None:
        state = self.state
        with state.robots_lock:
            self.raw_dropped += len(keys)
            state.dropped += len(keys)
            for key in keys:
                try:
                    assert state.keys is not None      # frames arrive only after start()
                    st = state.robots.get(state.keys.robot_from_key(key) or "")
                except Exception:
                    st = None
                if st is not None:
                    st.dropped += 1
        state.warn("raw-queue", "decode backlog full: dropped %d undecoded frame(s)", len(keys))

    def decode_loop(self) -> None:
        """The decode thread: validates queued payloads and queues the frames per robot."""
        state = self.state
        while not state.stop.is_set():
            self._raw_ready.clear()
            with self._raw_lock:
                item = self._raw.popleft() if self._raw else None
                if item is not None:
                    self._raw_bytes -= len(item[1])
                    self._raw_room.notify()
            if item is None:
                self._raw_ready.wait(0.5)
                continue
            self.handle_frame(*item)

    def handle_frame(self, key: str, data: bytes, t_recv: float) -> None:
        """Decode and validate one frame message, then queue it for its robot (or reject it)."""
        state = self.state
        try:
            assert state.keys is not None              # frames arrive only after start()
            key_robot = state.keys.robot_from_key(key)
        except Exception:
            key_robot = None
        try:
            t0 = time.perf_counter()
            try:
                frame = decode_frame(data, limits=state.limits)
            except WireError as e:
                state.reject(key_robot if key_robot in state.robots else None, reject_reason(e), str(e))
                return
            state.timings["decode_ms"].add((time.perf_counter() - t0) * 1e3)
            if key_robot is None or frame.robot != key_robot:
                state.reject(None, "robot_mismatch", f"frame robot {frame.robot!r} on key {key[:200]}")
                return
            if frame.features is None:
                state.reject(key_robot, "no_features", "frame carries no features")
                return
            with state.robots_lock:
                st = state.robot(key_robot)
                st.received += 1
                if st.feature_space and frame.feature_space != st.feature_space:
                    # not the robot's announced space: reject, touching neither its state nor
                    # its queue (a restarted edge announces a new space through liveliness)
                    st.rejected["feature_space_mismatch"] += 1
                    state.rejected["feature_space_mismatch"] += 1
                    mismatch = True
                else:
                    mismatch = False
                    if len(st.queue) == st.queue.maxlen:
                        st.dropped += 1
                        state.dropped += 1
                    st.queue.append((frame, t_recv))
            if mismatch:
                state.warn(f"{key_robot}:feature_space_mismatch", "rejected frame from %s (feature_space_mismatch): "
                       "space %r, the robot announced %r", key_robot, frame.feature_space[:80], st.feature_space)
                return
            with state.robots_lock:
                if not st.space_ok and not st.space_error:
                    # frames flow, so the edge's space is ready: fetch now rather than at the
                    # retry period (at most every 0.2 s), else frames pile up meanwhile
                    now = time.monotonic()
                    if st.fetch_after > now and now - st.fetch_started > 0.2:
                        st.fetch_after = 0.0
                        state.space_wake.set()
            state.wake.set()
        except Exception as e:  # never raise out of a callback
            state.reject(key_robot, "internal", repr(e))

    def _sender(self, sample: zenoh.Sample) -> str | None:
        """The robot a per-robot key's sample comes from (None: not a robot key)."""
        assert self.state.keys is not None             # subscribed in start()
        return self.state.keys.robot_from_key(str(sample.key_expr))

    def on_alive(self, sample: zenoh.Sample) -> None:
        state = self.state
        try:
            import zenoh

            robot = self._sender(sample)
            if robot is None:
                return
            with state.robots_lock:
                st = state.robot(robot)
                if sample.kind == zenoh.SampleKind.PUT:
                    st.present, st.seen_at, st.gone_at = True, time.time(), None
                    # a (re)started edge announces its space anew: fetch it (frames are held
                    # meanwhile and checked against it in next_frame)
                    st.fetch_after = 0.0
                    st.space_ok, st.feature_space, st.space_error = False, "", ""
                    log.info("robot %s present; fetching its feature space", robot)
                else:
                    st.present, st.gone_at = False, time.time()
                    log.info("robot %s gone", robot)
            state.wake.set()
            state.space_wake.set()
        except Exception as e:
            log.warning("liveliness callback: %s", e)

    def on_edge_status(self, sample: zenoh.Sample) -> None:
        """An edge's own state (``robots/<robot>/edge_status``). A refusal or failure is logged
        once per (robot, state, reason), shown in stats (``robots.<r>.edge_state`` /
        ``edge_reason``), and stops the feature-space retries (and their warnings) for that
        robot until its edge comes back."""
        state = self.state
        try:
            from common.messages import decode_edge_status

            robot = self._sender(sample)
            if robot is None:
                return
            try:
                msg = decode_edge_status(sample.payload.to_bytes())
            except MessageError as e:
                state.warn(f"{robot}:edge_status", "bad edge status from %s: %s", robot, e)
                return
            if msg["robot"] != robot:
                return
            with state.robots_lock:
                st = state.robot(robot)
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
        state = self.state
        # its own event: the map worker's one is set by every frame and stays set while
        # frames are queued, which would turn this loop into a GIL-holding busy spin
        while not state.stop.is_set():
            state.space_wake.wait(0.5)
            state.space_wake.clear()
            now = time.monotonic()
            with state.robots_lock:
                todo = [st.name for st in state.robots.values()
                        if not st.space_ok and not st.space_error and st.fetch_after <= now
                        and st.edge_state not in ("refused", "failed")]
            for robot in todo:
                if state.stop.is_set():
                    return
                self.fetch_space(robot)

    def fetch_space(self, robot: str) -> None:
        from common.feature_space import FeatureSpace

        state = self.state
        st = state.robots[robot]
        st.fetch_started = time.monotonic()
        try:
            assert state.session is not None and state.keys is not None   # started
            replies = list(state.session.get(state.keys.feature_space(robot), timeout=3.0))
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
            state.warn(f"{robot}:space", "feature space of %s not available yet: %s", robot, err)
            return
        try:
            fs = FeatureSpace.from_body(body)
        except Exception as e:
            st.fetch_after = time.monotonic() + 5.0
            state.warn(f"{robot}:space", "feature space of %s is invalid: %s", robot, e)
            return
        fs_id = fs.id
        with state.lock:
            if state.map is None:
                state.create_map(fs, encode_feature_space(robot, body))
            if state.fleet is not None:   # same encoder family: accepted (re-projected if another basis)
                why = state.fleet.space_decided(st, fs)
            else:
                why = "" if fs_id == state.space_id else f"robot space {fs_id} differs from the map's {state.space_id}"
            map_id = state.space_id
        ok = not why
        with state.robots_lock:
            st.feature_space = fs_id
            st.space_ok = ok
            st.space_error = why
        if ok:
            log.info("robot %s feature space %s%s", robot, fs_id,
                     f" (re-projected into the map's {map_id})" if fs_id != map_id else "")
            state.wake.set()
        else:
            log.error("robot %s refused: %s; its frames are rejected", robot, why)

    # ============================================================== queues
    def next_frame(self) -> tuple[RobotState, Frame, float] | None:
        """Round-robin over robots whose space matches the map; rejects frames of mismatched ones."""
        state = self.state
        with state.robots_lock:
            names = sorted(state.robots)
            if not names:
                return None
            start = self._rr
            for i in range(len(names)):
                st = state.robots[names[(start + i) % len(names)]]
                if not st.queue:
                    continue
                if st.space_error:
                    n = len(st.queue)
                    st.queue.clear()
                    st.rejected["feature_space_differs"] += n
                    state.rejected["feature_space_differs"] += n
                    continue
                if not st.space_ok:
                    if not state.cfg.queues.hold_unknown_space:
                        n = len(st.queue)
                        st.queue.clear()
                        st.rejected["feature_space_unknown"] += n
                        state.rejected["feature_space_unknown"] += n
                    continue
                frame, t_recv = st.queue.popleft()
                if frame.feature_space != st.feature_space:
                    st.rejected["feature_space_mismatch"] += 1
                    state.rejected["feature_space_mismatch"] += 1
                    continue
                self._rr = (start + i + 1) % len(names)
                return st, frame, t_recv
        return None
