"""The handle of a standing query or search (``Client.watch`` / ``Client.watch_search``)."""
from __future__ import annotations

import logging
from typing import Any

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
        try:
            self.client._get_one(key, payload, 2.0)
        except Exception as e:
            log.debug("cancel %s %s: %s", what, self.id, e)
        watches = getattr(self.client, "_watches", None)
        if watches is not None:
            watches.discard(self)

    def __enter__(self) -> StandingHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()
