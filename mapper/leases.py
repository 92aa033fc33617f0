"""Leases and caps of the standing requests clients register over Zenoh (standing queries
on ``<p>/mapper/query``, standing searches on ``<p>/mapper/search`` and the robot-scoped
``<p>/mapper/robots/<robot>/search``).

A registration holds a lease of ``lease_s`` seconds (the request's, else the section's
``lease_s``); a ``renew`` request for the id extends it; once it has run out the request is
dropped (:meth:`Leases.expired`), so a client that is gone stops costing the mapper
anything. Requests the mapper itself holds (the ROS output's) have no lease and live until
replaced. Caps: ``max_standing`` in total and ``max_standing_per_client`` per client (the
request's ``client`` id, or ``robot-<id>`` for a robot-scoped search); registering an id
again (a client re-registering after a restart) does not count twice. Times are
``time.monotonic()`` seconds. Every refusal is a one-line :class:`MessageError` naming the
limit's config key.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

from common.config import ConfigError, field_
from common.messages import MessageError


@dataclass(kw_only=True)
class StandingLimits:
    """The config keys of a kind of standing request that :class:`Leases` enforces, shared by
    the mapper's ``query`` and ``search`` sections (keyword-only fields: each section keeps its
    own fields first). A robot-scoped search counts for the client ``robot-<id>``."""

    lease_s: float = field_(30.0, "seconds a standing request lives after its registration or last renewal unless "
                                  "it names its own lease_s (query_client.Client renews every lease_s / 3)")
    max_standing: int = field_(64, "standing requests held at once (all clients); one more is refused")
    max_standing_per_client: int = field_(8, "standing requests one client (its 'client' id) may hold at once")

    def check_limits(self, section: str) -> None:
        """Refuse a limit that is not > 0 (one-line :class:`ConfigError` naming ``<section>.<key>``)."""
        for k in ("lease_s", "max_standing", "max_standing_per_client"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{section}.{k}={getattr(self, k)}: must be > 0")


@dataclass
class _Lease:
    client: str
    lease_s: float
    until: float


class Leases:
    """The leases of one kind of standing request (``what``: "standing query" or "standing
    search"; ``section``: its config section name, for the error texts)."""

    def __init__(self, what: str, section: str, default_s: float, max_total: int, max_per_client: int,
                 clock: Callable[[], float] = time.monotonic):
        self.what, self.section = what, section
        self.plural = what[:-1] + "ies" if what.endswith("y") else what + "es"
        self.default_s, self.max_total, self.max_per_client = float(default_s), int(max_total), int(max_per_client)
        self.clock = clock
        self._leases: dict[str, _Lease] = {}
        self._lock = threading.Lock()

    def admit(self, sid: str, client: str, lease_s: float, held: int) -> None:
        """Give ``sid`` (registered by ``client``) a lease, or raise :class:`MessageError` when
        a cap is reached; ``held``: the standing requests of this kind held now (leased or not)."""
        lease = float(lease_s) or self.default_s
        with self._lock:
            now = self.clock()
            if sid not in self._leases:
                if held >= self.max_total:
                    raise MessageError(f"too many {self.plural} on this mapper ({held}, limit "
                                       f"{self.section}.max_standing={self.max_total}): cancel one first")
                mine = sum(1 for v in self._leases.values() if v.client == client and v.until > now)
                if mine >= self.max_per_client:
                    raise MessageError(f"too many {self.plural} for client {client or '(unnamed)'!r} ({mine}, limit "
                                       f"{self.section}.max_standing_per_client={self.max_per_client}): "
                                       f"cancel one first")
            self._leases[sid] = _Lease(client, lease, now + lease)

    def restore(self, sid: str, client: str, lease_s: float) -> None:
        """A fresh lease for ``sid`` restored from a snapshot (no cap check): its client renews
        it, or it runs out like any other."""
        lease = float(lease_s) or self.default_s
        with self._lock:
            self._leases[sid] = _Lease(client, lease, self.clock() + lease)

    def renew(self, sid: str, known: bool) -> float:
        """Extend the lease of ``sid`` (``known``: whether it is registered); the new lease (s).
        An unknown id is a one-line error telling the client to register it again."""
        with self._lock:
            v = self._leases.get(sid)
            if not known or v is None:
                raise MessageError(f"no {self.what} {sid!r} to renew (expired, cancelled or never registered "
                                   f"on this mapper): register it again")
            v.until = self.clock() + v.lease_s
            return v.lease_s

    def drop(self, sid: str) -> None:
        with self._lock:
            self._leases.pop(sid, None)

    def expired(self) -> list[str]:
        """Ids whose lease has run out; they are forgotten here (the caller drops the requests)."""
        with self._lock:
            now = self.clock()
            out = [k for k, v in self._leases.items() if v.until <= now]
            for k in out:
                del self._leases[k]
        return out

    def live(self, sid: str) -> bool:
        """Whether ``sid`` may be kept (in a snapshot): a lease not run out, or no lease (the
        mapper's own requests)."""
        with self._lock:
            v = self._leases.get(sid)
            return v is None or v.until > self.clock()

    def describe(self) -> dict[str, float]:
        """Seconds left on each lease (for stats)."""
        with self._lock:
            now = self.clock()
            return {k: round(max(0.0, v.until - now), 3) for k, v in self._leases.items()}
