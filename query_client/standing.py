"""The handle of a standing query or search (``Client.watch`` / ``Client.watch_search``) and
the per-shard latest answers a standing request merges (docs/key_space.md#shards)."""
from __future__ import annotations

import dataclasses
import logging
import threading
from typing import Any, Callable

from common.zenoh_session import undeclare_all

log = logging.getLogger("rayfronts.client")


class StandingHandle:
    """A standing request registered under ``id``; ``cancel()`` (or leaving the ``with``
    block) stops receiving and asks the mapper to drop it (``cancel_key`` / ``cancel_payload``).
    ``reregistered`` counts the times it was registered again after a mapper came back."""

    def __init__(self, client: Any, sid: str, sub: Any, cancel_key: str, cancel_payload: bytes, what: str):
        self.client, self.id, self._sub, self.active = client, sid, sub, True
        self.reregistered = 0
        self._alive_sub = None
        self._cancel = (cancel_key, cancel_payload, what)

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
