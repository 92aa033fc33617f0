"""Where the edge sends a frame when the map is split over shards (docs/key_space.md#shards).

Every :data:`common.shard_routing.ROUTING_PERIOD_S` the edge asks
``<p>/mapper/shards/*/routing`` for the shards' announcements (what each owns, its halo, the
``world_from_robot`` it applies to this robot) and addresses each frame to the shards that own
its camera centre (:func:`common.shard_routing.route_targets`), on
``<p>/robots/<robot>/frames/s.<a>.<b>.``; the Zenoh routers deliver it only to those shards. A
frame no known shard owns, or sent before any announcement is known, goes on the plain frame
key, which every shard also takes. An announcement not heard for three periods is forgotten.

The edge also follows the shards' liveliness tokens (``<p>/mapper/shards/<name>``): while a
shard is alive whose announcement it has not heard (it just started, or it did not answer in
time), every frame goes on the plain key, so that no frame that shard owns is routed past it;
a new token triggers a refresh at once.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from common.shard_routing import ROUTING_PERIOD_S, ShardRegion, ShardRoutingError, decode_shard_routing, route_targets

log = logging.getLogger("rayfronts.edge")


class ShardRoutes:
    """The shards' announcements as this edge last heard them (thread-safe)."""

    def __init__(self, session: Any, keys: Any, robot: str, stop: threading.Event,
                 period_s: float = ROUTING_PERIOD_S):
        self.session, self.keys, self.robot, self.stop = session, keys, robot, stop
        self.period_s = float(period_s)
        self._lock = threading.Lock()
        self._regions: dict[str, tuple[ShardRegion, float]] = {}    # name -> (announcement, heard at)
        self.bad = 0                                                 # announcements that did not decode
        self._alive: set[str] = set()                                # shards whose token is there now
        self._thread: threading.Thread | None = None
        self._token_sub: Any = None
        self._wake = threading.Event()

    def refresh(self, timeout: float = 1.0) -> int:
        """Ask every shard once; returns how many answered."""
        got: list[ShardRegion] = []
        try:
            import zenoh

            for r in self.session.get(self.keys.mapper_shard_routing_all, timeout=timeout,
                                      target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE):
                if r.ok is None:
                    continue
                try:
                    got.append(decode_shard_routing(r.ok.payload.to_bytes()))
                except ShardRoutingError as e:
                    self.bad += 1
                    log.warning("shard routing announcement ignored: %s", e)
        except Exception as e:  # a closing session: keep what we know
            log.debug("shard routing get failed: %s", e)
            return 0
        now = time.monotonic()
        with self._lock:
            for reg in got:
                self._regions[reg.name] = (reg, now)
            for name in [n for n, (_, t) in self._regions.items() if now - t > 3 * self.period_s]:
                del self._regions[name]
        return len(got)

    def _on_token(self, sample: Any) -> None:
        name = self.keys.shard_from_key(str(sample.key_expr))
        if not name:
            return
        with self._lock:
            if str(sample.kind).endswith("PUT"):
                self._alive.add(name)
                self._wake.set()            # a new shard: ask for its announcement now
            else:
                self._alive.discard(name)

    def start(self) -> ShardRoutes:
        """Follow the shards' tokens, refresh now, then every ``period_s`` (and when a shard
        appears) on the thread ``edge-routes`` until ``stop``."""
        from common.zenoh_session import follow_tokens

        try:
            self._token_sub = follow_tokens(self.session, self.keys.mapper_shards_all, self._on_token)
        except Exception as e:  # without tokens: route by the announcements heard
            log.warning("cannot follow the mapper shards' liveliness: %s", e)
        self.refresh()

        def loop() -> None:
            while not self.stop.is_set():
                self._wake.wait(self.period_s)
                self._wake.clear()
                if not self.stop.is_set():
                    self.refresh()
            if self._token_sub is not None:
                try:
                    self._token_sub.undeclare()
                except Exception as e:
                    log.debug("undeclare: %s", e)

        self._thread = threading.Thread(target=loop, name="edge-routes", daemon=True)
        self._thread.start()
        return self

    def shards(self) -> list[str]:
        with self._lock:
            return sorted(self._regions)

    def targets(self, pose: np.ndarray) -> list[str]:
        """Shards a frame at ``pose`` (4×4, the robot's own pose frame) goes to; empty = plain key."""
        with self._lock:
            if not self._alive <= set(self._regions):      # a live shard we have not heard: plain key
                return []
            regions = [r for r, _ in self._regions.values()]
        return route_targets(regions, self.robot, np.asarray(pose, np.float64)[:3, 3])
