"""The edge's Zenoh side apart from the frames: opening the session (client mode retries until
the base station answers, so the start order is free; Zenoh re-establishes a lost link by
itself), the liveliness token ``robots/<robot>/alive``, the ``robots/<robot>/feature_space``
queryable, the edge's state on ``robots/<robot>/edge_status`` (put and queryable:
starting / running / done / refused / failed + the reason), the mapper's per-robot status
(``edge.mapper_status``) and asking the mapper for the map's feature space
(docs/key_space.md)."""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable

from common.zenoh_session import close_quietly, undeclare_all

if TYPE_CHECKING:
    import zenoh

    from common.feature_space import FeatureSpace
    from common.keys import KeySpace
    from edge.config import EdgeConfig
    from edge.mapper_status import StatusWatcher

log = logging.getLogger("rayfronts.edge")


class EdgeConnection:
    """The session of one edge and what it declares besides the frame publishers.

    ``attach(session, keys)`` / ``detach()`` (the publisher's) run when a session opens (before
    :attr:`connected` is set) and before it closes. ``phase()`` says what the pipeline is doing
    (in the feature-space "not ready" reply)."""

    def __init__(self, cfg: EdgeConfig, stop: threading.Event, connected: threading.Event,
                 mapper_status: StatusWatcher, attach: Callable[[Any, KeySpace], None], detach: Callable[[], None],
                 phase: Callable[[], str]):
        self.cfg = cfg
        self.stop = stop
        self.connected = connected      # set once the session is open and everything declared
        self.mapper_status = mapper_status
        self._attach, self._detach, self._phase = attach, detach, phase
        self.session: Any = None
        self.keys: KeySpace | None = None
        self._declared: tuple = ()
        self._status_pub: Any = None
        self._fs_reply: bytes | None = None
        self._fs_lock = threading.Lock()
        self.state = ("starting", "")
        self._state_lock = threading.Lock()

    def loop(self) -> None:
        """The connector thread: open the session (retrying every ``publish.connect_retry_s``),
        declare, attach the publisher, then set :attr:`connected`."""
        from common.keys import KeySpace
        from common.zenoh_session import open_session

        self.keys = KeySpace(self.cfg.zenoh.prefix)
        extra = {"transport/link/tx/queue/congestion_control/block/wait_before_close":
                 int(self.cfg.publish.block_wait_s * 1e6)}
        while not self.stop.is_set():
            try:  # client mode: retries until the base station answers (start order is free)
                s = open_session(self.cfg.zenoh, stop=self.stop, extra=extra, default_mode="client")
            except Exception as e:
                if self.stop.is_set():
                    return
                log.warning("cannot open the zenoh session (%s); retrying", e)
                self.stop.wait(self.cfg.publish.connect_retry_s)
                continue
            try:
                self._declare(s, self.keys)
                self._attach(s, self.keys)
            except Exception:
                s.close()
                raise
            self.session = s
            if self.stop.is_set():  # closed while we were connecting
                self.close()
                return
            log.info("edge %s connected (zid %s)", self.cfg.robot, s.zid())
            self.connected.set()
            return

    def _declare(self, s: Any, keys: KeySpace) -> None:
        from common.robot_messages import robot_status_key

        robot = self.cfg.robot
        queryable = s.declare_queryable(keys.feature_space(robot), self._on_feature_space)
        self._status_pub = s.declare_publisher(keys.edge_status(robot))
        status_q = s.declare_queryable(keys.edge_status(robot), self._on_status)
        token = s.liveliness().declare_token(keys.alive(robot))
        # what the mapper does with our frames (logged on change; publish.rate_hz=auto)
        status_sub = s.declare_subscriber(robot_status_key(keys, robot), self.mapper_status.on_sample)
        self._declared = (status_sub, token, queryable, status_q, self._status_pub)

    # ------------------------------------------------------------ feature space
    def serve_feature_space(self, reply: bytes) -> None:
        """Answer ``robots/<robot>/feature_space`` with ``reply`` (an encoded feature space) from now on."""
        with self._fs_lock:
            self._fs_reply = reply

    def _on_feature_space(self, query: zenoh.Query) -> None:
        from common.messages import encode_error

        try:
            with self._fs_lock:
                reply = self._fs_reply
            payload = reply if reply is not None else encode_error(f"feature space not ready ({self._phase()})")
            query.reply(query.key_expr, payload)
        except Exception as e:  # never raise out of a callback
            log.warning("feature_space reply failed: %s", e)

    def ask_map_space(self, timeout: float) -> tuple[FeatureSpace | None, str]:
        """(the map's feature space, "") from the first mapper shard that has one, else
        (None, why); waits up to ``timeout`` s for the session first."""
        from common.feature_space import FeatureSpace
        from common.messages import MessageError, decode_feature_space

        end = time.monotonic() + timeout
        if not self.connected.wait(timeout) or self.session is None or self.keys is None:
            return None, "no mapper answered"
        why = "no mapper answered"
        try:
            replies = list(self.session.get(self.keys.mapper_feature_space, timeout=max(0.1, end - time.monotonic())))
        except Exception as e:
            return None, f"asking the mapper failed: {e}"
        for r in replies:
            if r.ok is None:
                continue
            try:
                _, body = decode_feature_space(r.ok.payload.to_bytes())
                return FeatureSpace.from_body(body), ""
            except (MessageError, ValueError) as e:
                why = f"the mapper has no map yet ({' '.join(str(e).split())[:120]})"
        return None, why

    # ------------------------------------------------------------ edge status
    def _status_bytes(self) -> bytes:
        from common.messages import encode_edge_status

        with self._state_lock:
            state, reason = self.state
        return encode_edge_status(self.cfg.robot, state, reason, time.time())

    def _on_status(self, query: zenoh.Query) -> None:
        try:
            query.reply(query.key_expr, self._status_bytes())
        except Exception as e:  # never raise out of a callback
            log.warning("edge_status reply failed: %s", e)

    def set_state(self, state: str, reason: str = "", wait_s: float = 0.0) -> None:
        """Record the edge's state and put it on ``robots/<robot>/edge_status`` (waiting up to
        ``wait_s`` for the session when it is not connected yet)."""
        with self._state_lock:
            self.state = (state, reason)
        if not self.connected.is_set() and wait_s > 0:
            self.connected.wait(wait_s)
        pub = self._status_pub
        if pub is None or not self.connected.is_set():
            return
        try:
            pub.put(self._status_bytes())
        except Exception as e:
            log.warning("edge_status put failed: %s", e)

    def close(self) -> None:
        """Detach the publisher, undeclare everything and close the session (idempotent)."""
        s, self.session = self.session, None
        self._detach()
        if s is not None:
            undeclare_all(self._declared)
            self._declared, self._status_pub = (), None
            close_quietly(s)
