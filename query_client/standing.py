"""The handle of a standing query or search (``Client.watch`` / ``Client.watch_search``), the
renewal of its lease (``mapper.leases``: the mapper ends a standing request whose client
stops renewing it), and the per-shard latest answers a standing request merges
(docs/key_space.md#shards)."""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Any, Callable

from common.messages import MessageError
from common.zenoh_session import undeclare_all

log = logging.getLogger("rayfronts.client")

#: the text of the mapper's error for a renewal it does not know (mapper.leases.Leases.renew)
UNKNOWN_LEASE = "register it again"


class StandingHandle:
    """A standing request registered under ``id``; ``cancel()`` (or leaving the ``with``
    block) stops receiving and asks the mapper to drop it (``cancel_key`` / ``cancel_payload``).
    ``reregistered`` counts the times it was registered again after a mapper came back, or
    after the mapper said it did not know it any more (its lease had run out)."""

    def __init__(self, client: Any, sid: str, sub: Any, cancel_key: str, cancel_payload: bytes, what: str):
        self.client, self.id, self._sub, self.active = client, sid, sub, True
        self.reregistered = 0
        self.renewed = 0
        self._alive_sub = None
        self._cancel = (cancel_key, cancel_payload, what)
        self._lease: tuple[bytes, bytes, Callable[[bytes], Any], float] | None = None
        self._next_renew = float("inf")

    def lease(self, register_payload: bytes, renew_payload: bytes, decode: Callable[[bytes], Any],
              period_s: float) -> None:
        """Renew every ``period_s`` seconds with ``renew_payload`` (on the cancel key); a mapper
        that no longer knows the id gets ``register_payload`` again. ``decode`` reads a reply."""
        self._lease = (register_payload, renew_payload, decode, float(period_s))
        self._next_renew = time.monotonic() + float(period_s)

    def renew_if_due(self, now: float) -> None:
        """Send the renewal when it is due (the client's renewal thread calls this)."""
        if not self.active or self._lease is None or now < self._next_renew:
            return
        register, renew, decode, period = self._lease
        self._next_renew = now + period
        key, _, what = self._cancel
        try:
            oks, errs = self.client._get_all(key, renew, None)
        except Exception as e:
            log.warning("%s %s: renewal failed: %s", what, self.id, e)
            return
        lost = False
        for data, _ in oks:
            try:
                decode(data)
            except MessageError as e:
                lost = lost or UNKNOWN_LEASE in str(e)
                if UNKNOWN_LEASE not in str(e):
                    log.warning("%s %s: renewal refused: %s", what, self.id, e)
        if lost and self.active:
            log.info("%s %s: the mapper had dropped it; registering it again", what, self.id)
            self.client._get_all(key, register, None)
            self.reregistered += 1
        elif oks:
            self.renewed += 1

    def cancel(self) -> None:
        if not self.active:
            return
        self.active = False
        undeclare_all((self._sub, self._alive_sub))
        key, payload, what = self._cancel
        try:   # every shard holds it: cancel on all of them
            self.client._get_all(key, payload, 2.0)
        except Exception as e:
            log.debug("cancel %s %s: %s", what, self.id, e)
        watches = getattr(self.client, "_watches", None)
        if watches is not None:
            watches.discard(self)

    def __enter__(self) -> StandingHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()


def renew_loop(watches: Callable[[], list], stop: threading.Event, every_s: float = 0.5) -> None:
    """Until ``stop``: every ``every_s`` seconds, renew the handles ``watches()`` returns that
    are due (a client's renewal thread)."""
    while not stop.wait(every_s):
        now = time.monotonic()
        for h in watches():
            try:
                h.renew_if_due(now)
            except Exception as e:  # keep renewing the others
                log.warning("standing %s: %s", getattr(h, "id", "?"), e)


class ShardLatest:
    """Each mapper shard's latest answer to one standing request (the shards publish on the same
    key, each with its shard info as the attachment): every new answer, and every shard whose
    liveliness token goes away (its answer dropped), passes ``merge(list of (answer, info))`` to
    ``callback`` with ``missing_shards`` = the shards the client saw that have no answer here.
    Nothing is passed on before :meth:`first`."""

    def __init__(self, client: Any, merge: Callable[[list], Any], callback: Callable[[Any], None], what: str):
        self.client, self.merge, self.callback, self.what = client, merge, callback, what
        self.latest: dict[str, tuple] = {}
        self.ready = threading.Event()
        self.sub: Any = None
        self.handle: Any = None

    def put(self, answer: Any, info: dict) -> None:
        with self.client._lock:
            self.latest[str(info.get("shard", ""))] = (answer, info)
        if self.ready.is_set():     # before the first answer, only collect
            self.publish()

    def publish(self) -> None:
        with self.client._lock:
            res = dataclasses.replace(self.merge(list(self.latest.values())))   # never change a kept answer
            res.missing_shards = sorted(self.client._shards_seen - set(self.latest))
        try:
            self.callback(res)
        except Exception as e:  # a callback's bug must not end the stream
            log.warning("%s callback: %s", self.what, e)

    def first(self, got: list[tuple], handle: Any) -> None:
        """The registration's answers ``[(answer, info)]``: kept, then passed on once; from now
        on shards leaving are followed."""
        with self.client._lock:
            for answer, info in got:
                self.latest.setdefault(str(info.get("shard", "")), (answer, info))
            self.handle = handle
            self.client._shard_listeners.append(self.on_shard)
        self.ready.set()
        self.publish()

    def on_shard(self, name: str, alive: bool) -> None:
        """Client shard listener: a shard whose token went away is dropped and named missing."""
        if self.handle is None or not self.handle.active:
            with self.client._lock:
                if self.on_shard in self.client._shard_listeners:
                    self.client._shard_listeners.remove(self.on_shard)
            return
        if not alive and self.ready.is_set():
            with self.client._lock:
                self.latest.pop(name, None)
            self.publish()
