"""The edge's publisher: the one-slot latest-frame queue between the pipeline and the network,
the publisher thread that sends each frame with ``CongestionControl.BLOCK``, and the key each
frame goes on (a tile key, a key addressed to the shards that own it, or the plain frames key;
docs/key_space.md#shards).

The pipeline thread hands frame ``n+1`` to the :class:`LatestSlot` while this thread sends frame
``n``: a newer frame replaces an unsent older one (counted as ``replaced``), so the encoder never
waits on the network and a slow link drops whole old frames, never fragments of new ones
(docs/key_space.md#topology)."""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from common.zenoh_session import close_quietly, undeclare_all

if TYPE_CHECKING:
    from common.frame import Frame
    from common.keys import KeySpace
    from edge.config import EdgeConfig

log = logging.getLogger("rayfronts.edge")

#: publish.tile_m > 0: tile publishers kept declared (least recently used undeclared beyond)
TILE_PUBLISHERS = 16
#: a new tile- or shard-routed publisher waits at most this long (s) for a matching subscriber
NEW_KEY_WAIT_S = 1.0


class LatestSlot:
    """A one-slot queue holding only the newest item; ``put`` never blocks.

    A put over an item nobody took yet replaces it and counts in ``replaced``."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False
        self.replaced = 0
        self.put_count = 0

    def put(self, item: Any) -> None:
        """Hold ``item`` (not None), replacing an untaken one."""
        with self._cond:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self.put_count += 1
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> Any:
        """The newest item, or None after ``timeout`` / once closed and empty."""
        with self._cond:
            end = None if timeout is None else time.monotonic() + timeout
            while self._item is None and not self._closed:
                rem = None if end is None else end - time.monotonic()
                if rem is not None and rem <= 0:
                    return None
                self._cond.wait(rem)
            item, self._item = self._item, None
            self._cond.notify_all()
            return item

    def wait_empty(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the item to be taken; True if the slot is empty."""
        with self._cond:
            return self._cond.wait_for(lambda: self._item is None, timeout)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def pending(self) -> bool:
        return self._item is not None


@dataclass
class EdgeStats:
    """The edge's counters (logged at the end of a run); times in milliseconds."""

    frames_read: int = 0             #: frames the source gave
    frames_skipped: int = 0          #: frames the source could not read/decode (skipped, counted)
    frames_encoded: int = 0          #: frames through the encoder and PCA
    frames_sent: int = 0             #: frames put on the wire
    frames_replaced: int = 0         #: encoded frames replaced by a newer one before sending
    bytes_sent: int = 0              #: wire bytes of the sent frames
    put_errors: int = 0              #: failed Zenoh puts
    encode_ms_last: float = 0.0
    put_ms_last: float = 0.0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class FramePublisher:
    """Sends what the pipeline puts in :attr:`slot` on the frame's key, from its own thread
    (:meth:`loop`). :meth:`attach` / :meth:`detach` follow the Zenoh session (the connection
    calls them; ``connected`` is set while one is attached); ``recorder`` (a
    ``common.recording.RecordingWriter``) gets exactly the bytes sent; ``on_sent(frame, nbytes, t_put)`` is called
    after each put."""

    def __init__(self, cfg: EdgeConfig, stop: threading.Event, connected: threading.Event, stats: EdgeStats,
                 on_sent: Callable[[Any, int, float], None] | None = None):
        self.cfg = cfg
        self.stop = stop
        self.connected = connected      # set while a session is open and attached
        self.stats = stats
        self.on_sent = on_sent
        self.slot = LatestSlot()
        self.recorder: Any = None
        self._session: Any = None
        self._keys: KeySpace | None = None
        self._publisher: Any = None
        self._tile_pubs: dict[str, Any] = {}      # tile-routed / shard-routed key -> publisher (LRU)
        self._routes: Any = None                  # edge.shard_routes.ShardRoutes of the session
        self._routes_stop = threading.Event()
        self._matched = False   # a subscriber matched the frames key in this session (see wait_matching)

    # ------------------------------------------------------------- the session
    def attach(self, session: Any, keys: KeySpace) -> None:
        """Declare the plain frames publisher on a new session and, with ``publish.shard_routing``
        (and no tiles), start following the shards' routing announcements."""
        import zenoh

        robot = self.cfg.robot
        self._publisher = session.declare_publisher(
            keys.frames(robot), congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA,
            express=False)
        self._session, self._keys = session, keys
        self._matched = False   # the first frame of this session waits for a subscriber
        if self.cfg.publish.shard_routing and self.cfg.publish.tile_m <= 0:
            from edge.shard_routes import ShardRoutes

            self._routes_stop = threading.Event()
            self._routes = ShardRoutes(session, keys, robot, self._routes_stop).start()
            if self._routes.shards():
                log.info("routing frames to the shards that own them: %s", ", ".join(self._routes.shards()))

    def detach(self) -> None:
        """Stop routing and undeclare this session's publishers (before the session closes)."""
        self._routes_stop.set()
        self._routes = None
        undeclare_all((self._publisher, *self._tile_pubs.values()))
        self._publisher, self._tile_pubs, self._session = None, {}, None

    # ------------------------------------------------------------- the thread
    def wait_matching(self, pub: Any, limit_s: float | None = None) -> None:
        """Wait up to ``publish.wait_subscriber_s`` (or ``limit_s``, if smaller) until ``pub`` has
        a matching subscriber (asked once per session and once per new routed publisher: the
        caller then sends, matched or not)."""
        wait = max(0.0, float(self.cfg.publish.wait_subscriber_s))
        deadline = time.monotonic() + (wait if limit_s is None else min(wait, limit_s))
        while True:
            try:
                if pub.matching_status.matching:
                    return
            except Exception as e:           # a session closing under us: send as before
                log.debug("matching status unavailable: %s", e)
                return
            if time.monotonic() >= deadline or self.stop.is_set():
                log.info("no subscriber matches %s yet; sending anyway", pub.key_expr)
                return
            time.sleep(0.05)

    def loop(self) -> None:
        """The publisher thread: send each frame taken from the slot until stopped and drained."""
        while True:
            item = self.slot.get(timeout=0.2)
            if item is None:
                if self.stop.is_set() and not self.slot.pending:
                    return
                continue
            frame, data = item
            while not self.connected.wait(0.2):
                if self.stop.is_set():
                    return
            pub = self.frame_publisher(frame)
            if not self._matched:
                self.wait_matching(pub)
                self._matched = True
            t0 = time.time()
            try:
                pub.put(data)
            except Exception as e:
                self.stats.put_errors += 1
                log.warning("put failed: %s", e)
                continue
            self._sent(frame, data, t0)

    def _sent(self, frame: Frame, data: bytes, t0: float) -> None:
        self.stats.put_ms_last = (time.time() - t0) * 1e3
        self.stats.frames_sent += 1
        self.stats.bytes_sent += len(data)
        if self.recorder is not None:
            try:
                self.recorder.write_encoded(data)  # exactly the bytes that were sent
            except Exception as e:
                log.error("recording failed, disabled: %s", e)
                self.recorder = None
        if self.on_sent is not None:
            self.on_sent(frame, len(data), t0)

    def frame_publisher(self, frame: Frame) -> Any:
        """The publisher of ``frame``'s key: with ``publish.tile_m`` > 0 the key of the tile of its
        camera centre (robot's pose frame); else, with ``publish.shard_routing``, the key
        addressed to the shards owning it (:mod:`edge.shard_routes`); else (or when no shard owns
        it) the plain frames key. Keyed publishers are declared lazily and cached (at most
        ``TILE_PUBLISHERS``; the least recently used one is undeclared)."""
        tile_m = float(self.cfg.publish.tile_m)
        robot = self.cfg.robot
        keys = self._keys
        assert keys is not None, "attach() comes first"
        if tile_m > 0:
            c = np.asarray(frame.pose, np.float64)[:3, 3]
            key = keys.frames_tile(robot, (math.floor(c[0] / tile_m), math.floor(c[1] / tile_m)))
        else:
            routes = self._routes
            shards = routes.targets(frame.pose) if routes is not None else []
            if not shards:
                return self._publisher
            key = keys.frames_routed(robot, shards)
        import zenoh

        pubs = self._tile_pubs
        pub = pubs.pop(key, None)
        if pub is None:
            pub = self._session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                  priority=zenoh.Priority.DATA, express=False)
            # a put on a key declared just now may go out before the router has told this client
            # about the subscribers of that key (the frame would reach nobody): wait a moment
            self.wait_matching(pub, NEW_KEY_WAIT_S)
            while len(pubs) >= TILE_PUBLISHERS:
                undeclare_all((pubs.pop(next(iter(pubs))),))
        pubs[key] = pub                     # most recently used last
        return pub

    def close_recording(self) -> None:
        close_quietly(self.recorder, "the recording")
        self.recorder = None
