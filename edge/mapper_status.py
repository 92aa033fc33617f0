"""The edge's side of the mapper's per-robot status (``mapper/robots/<robot>/status``,
``common.robot_messages``): log what the mapper does with this robot's frames when it changes, and
``publish.rate_hz=auto`` — publish at the rate the mapper advises instead of flooding a
queue that drops.

:class:`StatusWatcher` is fed the status samples (a Zenoh subscriber callback); it logs a
line when a shard's ``(state, reason)`` changes — INFO for accepted / pending, WARNING for
refused / evicted, so a refused robot is told why once — and keeps the latest advised
rate. :class:`AutoRate` turns advised rates into the pacing rate: it starts at
``start_hz``, follows the mapper's advice smoothed (half way each update), within
``[min_hz, max_hz]``; with several shards the smallest advice of the shards that map this
robot's frames wins. Without any status (no mapper, an older mapper) it stays at
``start_hz``.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("rayfronts.edge")


class AutoRate:
    """Publish rate that follows the mapper's advice (see module doc)."""

    def __init__(self, start_hz: float = 10.0, min_hz: float = 0.2, max_hz: float = 100.0):
        self.min_hz, self.max_hz = float(min_hz), float(max_hz)
        self.rate = min(max(float(start_hz), self.min_hz), self.max_hz)
        self._lock = threading.Lock()
        self.updates = 0

    def advise(self, hz: float | None) -> float:
        """Move halfway towards the advised rate ``hz`` (clamped; None or <= 0 ignored); the new rate in Hz."""
        with self._lock:
            if hz is not None and hz > 0:
                target = min(max(float(hz), self.min_hz), self.max_hz)
                self.rate = 0.5 * self.rate + 0.5 * target
                self.updates += 1
            return self.rate

    def current(self) -> float:
        """The rate to publish at now, Hz."""
        with self._lock:
            return self.rate


class StatusWatcher:
    """Logs changes of the mapper's status for one robot and feeds :class:`AutoRate`."""

    def __init__(self, robot: str, auto: AutoRate | None = None, logger: logging.Logger | None = None):
        self.robot = robot
        self.auto = auto
        self.log = logger or log
        self._last: dict[str, tuple] = {}
        self._advice: dict[str, tuple[float, float]] = {}    # shard -> (advised hz, monotonic time)
        self.latest: dict[str, dict] = {}
        self.bad = 0
        self._logged_rate = auto.current() if auto is not None else 0.0
        self._lock = threading.Lock()

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh subscriber callback (never raises)."""
        try:
            self.on_payload(sample.payload.to_bytes())
        except Exception as e:
            self.bad += 1
            self.log.debug("mapper status: %s", e)

    def on_payload(self, data: bytes) -> dict | None:
        from common.robot_messages import FleetMessageError, decode_robot_status

        try:
            st = decode_robot_status(data)
        except FleetMessageError as e:
            self.bad += 1
            self.log.debug("bad mapper status for %s: %s", self.robot, e)
            return None
        if st.get("robot") != self.robot:
            return None
        shard = str(st.get("shard", ""))
        key = (st["state"], st.get("reason", ""))
        with self._lock:
            changed = self._last.get(shard) != key
            self._last[shard] = key
            self.latest[shard] = st
            adv = st.get("advised_hz")
            if adv is not None and st["state"] == "accepted":
                self._advice[shard] = (float(adv), time.monotonic())
            now = time.monotonic()
            live = [a for a, t in self._advice.values() if now - t < 10.0]
        where = f" (shard {shard})" if shard else ""
        if changed:
            state, reason = key
            if state in ("refused", "evicted"):
                self.log.warning("mapper%s %s this robot's frames: %s", where, state, reason or "no reason given")
            else:
                extra = " (re-projected into the map's PCA basis)" if st.get("reprojected") and "re-projected" \
                    not in key[1] else ""
                self.log.info("mapper%s: robot %s %s%s%s", where, self.robot, state,
                              f": {reason}" if reason else "", extra)
        if self.auto is not None and live:
            before = self.auto.current()
            now_rate = self.auto.advise(min(live))
            if abs(now_rate - self._logged_rate) > 0.2 * max(self._logged_rate, 0.1):
                self._logged_rate = now_rate
                self.log.info("publish rate (auto): %.1f Hz (mapper advises %.1f Hz, was %.1f Hz)",
                              now_rate, min(live), before)
        return st
