"""Python API of the operator side (and of planners): ``query_client.Client``.

>>> from query_client import Client
>>> with Client(connect="tcp/base:7447") as c:
...     r = c.query("water tower", top_k=5)
...     r.cluster_xyz, r.cluster_score, r.ray_origin, r.ray_direction, r.search_volume_m3
...     h = c.watch("vehicle", lambda res: print(res.cluster_xyz[:1]))
...     ...; h.cancel()

All positions are metres in the mapper's world frame (z up). Errors from the mapper raise
:class:`QueryError`; no mapper answering raises :class:`MapperUnavailable`.
"""
from __future__ import annotations

import logging
import os
import threading
import uuid
from typing import Any, Callable, Sequence, cast

import numpy as np

from common.messages import (
    MessageError,
    QueryRequest,
    QueryResult,
    decode_layer,
    decode_query_result,
    decode_snapshot_reply,
    decode_stats,
    encode_query_request,
    encode_snapshot_request,
)
from query_client.fleet_search import FleetCalls
from query_client.search import PlannerCalls
from query_client.standing import ShardLatest, StandingHandle

log = logging.getLogger("rayfronts.query_client")

__all__ = ["Client", "QueryResult", "QueryError", "QueryImageError", "MapperUnavailable", "WatchHandle",
           "read_query_image"]


class QueryError(RuntimeError):
    """The mapper answered with an error (the text is the mapper's)."""


class MapperUnavailable(QueryError):
    """No mapper answered within the timeout."""


class QueryImageError(QueryError):
    """A query image that cannot be sent (missing, empty, too big, not an image file)."""


#: leading bytes of the image formats the mapper decodes (OpenCV)
_IMAGE_MAGIC = (b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n", b"BM", b"RIFF", b"II*\x00", b"MM\x00*")


def read_query_image(image: bytes | str | os.PathLike) -> bytes:
    """The encoded bytes of a query image (a path or the bytes themselves), checked here so a
    bad input fails with one clear line before anything is sent: missing or unreadable file,
    zero size, over ``common.messages.MAX_IMAGE_BYTES``, not a JPEG/PNG/BMP/WebP/TIFF file.
    The pixels are decoded (and their size limited) on the mapper; the client needs no image
    library and no torch."""
    from common.messages import MAX_IMAGE_BYTES

    if isinstance(image, (bytes, bytearray, memoryview)):
        data, what = bytes(image), "query image"
    else:
        path = os.fspath(image)
        what = f"query image {path}"
        try:
            size = os.path.getsize(path)
        except OSError as e:
            raise QueryImageError(f"{what}: {e.strerror or e}") from None
        if size > MAX_IMAGE_BYTES:
            raise QueryImageError(f"{what} is {size} bytes, over the limit of {MAX_IMAGE_BYTES} bytes")
        try:
            with open(path, "rb") as f:
                data = f.read(MAX_IMAGE_BYTES + 1)
        except OSError as e:
            raise QueryImageError(f"{what}: {e.strerror or e}") from None
    if not data:
        raise QueryImageError(f"{what} is empty (0 bytes)")
    if len(data) > MAX_IMAGE_BYTES:
        raise QueryImageError(f"{what} is {len(data)} bytes, over the limit of {MAX_IMAGE_BYTES} bytes")
    if not data.startswith(_IMAGE_MAGIC) or (data.startswith(b"RIFF") and data[8:12] != b"WEBP"):
        raise QueryImageError(f"{what} is not an image file (expected JPEG, PNG, BMP, WebP or TIFF)")
    return data


class WatchHandle(StandingHandle):
    """A standing query; ``cancel()`` (or leaving the ``with`` block) stops it."""

    def __init__(self, client: "Client", qid: str, sub):
        super().__init__(client, qid, sub, client.keys.mapper_query,
                         encode_query_request(QueryRequest(cancel=True, id=qid)), "standing query")


class Client(PlannerCalls, FleetCalls):
    """A Zenoh client of the mapper. ``zenoh_cfg`` (a ``ZenohConfig``) or ``connect``
    (endpoint string or list) say where the router is; ``prefix`` the key space.

    ``robot``: ask as robot ``<id>``'s onboard planner (search and occupancy on the robot's
    own keys, which a ``robot-<id>`` certificate may ask; docs/key_space.md). ``lease_s``: the
    lease of this client's standing queries and searches; a thread renews them every
    ``lease_s / 3`` s, so the mapper ends them about ``lease_s`` after the client is gone."""

    _query_error = QueryError          # what the planner calls (query_client.search) raise

    def __init__(self, zenoh_cfg=None, *, connect: str | list[str] | None = None, prefix: str | None = None,
                 timeout: float = 10.0, connect_timeout_ms: int = 10_000, robot: str | None = None,
                 lease_s: float = 30.0):
        import dataclasses

        from common.keys import KeySpace, check_id
        from common.messages import MAX_LEASE_S
        from common.zenoh_session import ZenohConfig, open_session

        self.robot = None if robot is None else check_id(robot)
        if not 0.0 < float(lease_s) <= MAX_LEASE_S:
            raise ValueError(f"lease_s must be seconds in (0, {MAX_LEASE_S:g}], got {lease_s!r}")
        self.lease_s = float(lease_s)
        self._stop = threading.Event()
        self._renewer: threading.Thread | None = None

        cfg = zenoh_cfg if zenoh_cfg is not None else ZenohConfig(connect_timeout_ms=connect_timeout_ms)
        ch: dict[str, Any] = {}
        if connect is not None:
            ch["connect"] = [connect] if isinstance(connect, str) else list(connect)
        if prefix is not None:
            ch["prefix"] = prefix
        cfg = dataclasses.replace(cfg, **ch)
        self.cfg = cfg
        self.keys = KeySpace(cfg.prefix)
        self.timeout = timeout
        self.session = open_session(cfg, default_mode="client")
        # who registers this client's standing requests (the mapper's per-client cap)
        self.client_id = f"robot-{self.robot}" if self.robot else f"c{self.session.info.zid()}"[:64]
        self._watches: set[StandingHandle] = set()
        self._lock = threading.Lock()
        self._shards_seen: set[str] = set()       # mapper shards whose liveliness token was ever seen
        self._shards_alive: set[str] = set()      # ... and whose token is there now
        self._shard_listeners: list[Callable[[str, bool], None]] = []
        self._shard_infos: dict[str, dict] = {}  # shard name -> its latest shard info (region, ...)
        self._shard_sub = None
        self._follow_shards()

    # ------------------------------------------------------------------ plumbing
    def _get_one(self, key: str, payload: bytes | None, timeout: float | None) -> bytes:
        import zenoh

        kw: dict[str, Any] = {"timeout": float(timeout or self.timeout), "consolidation": zenoh.ConsolidationMode.NONE}
        if payload is not None:
            kw["payload"] = payload
        errs = []
        for r in self.session.get(key, **kw):
            if r.ok is not None:
                return r.ok.payload.to_bytes()
            errs.append(r.err.payload.to_string() if r.err is not None else "?")
        if errs:
            raise MapperUnavailable(f"no answer on {key}: {'; '.join(errs)}")
        raise self._no_answer(key)

    def _no_answer(self, key: str) -> MapperUnavailable:
        """The one-line error of a ``get`` on ``key`` that nobody answered."""
        return MapperUnavailable(f"no mapper answered on {key} (is it running and reachable? with access control: "
                                 f"is this certificate allowed to ask {key}? a robot may ask only "
                                 f"{self.keys.prefix}/mapper/robots/<its own id>/...)")

    def _get_all(self, key: str, payload: bytes | None, timeout: float | None) -> tuple[list, list[str]]:
        """Every reply to one ``get`` (all queryables on ``key``: every mapper shard):
        ``([(payload bytes, attachment bytes or None)], [error texts])``."""
        import zenoh

        kw: dict[str, Any] = {"timeout": float(timeout or self.timeout),
                              "consolidation": zenoh.ConsolidationMode.NONE, "target": zenoh.QueryTarget.ALL}
        if payload is not None:
            kw["payload"] = payload
        oks, errs = [], []
        for r in self.session.get(key, **kw):
            if r.ok is not None:
                att = r.ok.attachment
                oks.append((r.ok.payload.to_bytes(), att.to_bytes() if att is not None else None))
            else:
                errs.append(r.err.payload.to_string() if r.err is not None else "?")
        return oks, errs

    def _lease(self, handle: StandingHandle, register: bytes, renew: bytes, decode) -> None:
        """Keep ``handle``'s lease: renew it every ``lease_s / 3`` s from this client's renewal
        thread (started on the first standing request) until it is cancelled or the client closes."""
        handle.lease(register, renew, decode, self.lease_s / 3.0)
        with self._lock:
            self._watches.add(handle)
            if self._renewer is None:
                from query_client.standing import renew_loop

                self._renewer = threading.Thread(target=renew_loop, args=(lambda: list(self._watches), self._stop),
                                                 name="rayfronts-renew", daemon=True)
                self._renewer.start()

    # ------------------------------------------------------------------ shards
    def _on_shard_token(self, sample) -> None:
        name = self.keys.shard_from_key(str(sample.key_expr))
        if not name:
            return
        alive = str(sample.kind).endswith("PUT")
        with self._lock:
            self._shards_seen.add(name)
            (self._shards_alive.add if alive else self._shards_alive.discard)(name)
            listeners = list(self._shard_listeners)
        for fn in listeners:
            try:
                fn(name, alive)
            except Exception as e:  # never raise out of a zenoh callback
                log.warning("shard listener: %s", e)

    def _follow_shards(self) -> None:
        """Learn the mapper shards (``<p>/mapper/shards/<name>`` liveliness tokens,
        docs/key_space.md#shards): the ones there now, then every arrival and departure."""
        from common.zenoh_session import follow_tokens

        try:
            self._shard_sub = follow_tokens(self.session, self.keys.mapper_shards_all, self._on_shard_token)
        except Exception as e:  # queries still work; missing_shards stays empty
            log.warning("cannot follow the mapper shards' liveliness: %s", e)

    def shards(self) -> tuple[list[str], list[str]]:
        """``(alive, seen)``: mapper shard names alive now and ever seen by this client."""
        with self._lock:
            return sorted(self._shards_alive), sorted(self._shards_seen)

    def _missing(self, answered: set[str]) -> list[str]:
        with self._lock:
            return sorted(self._shards_seen - answered)

    # ------------------------------------------------------------------ queries
    def query(self, text: str | None = None, image: bytes | str | None = None, top_k: int = 10,
              timeout: float | None = None, *, embedding: np.ndarray | None = None,
              softmax: bool = False) -> QueryResult:
        """Run one query now. ``image`` = encoded image bytes or a file path (checked by
        :func:`read_query_image`; the mapper embeds it in the map's feature space)."""
        if image is not None:
            image = read_query_image(image)
        req = QueryRequest(text=text, image=image, embedding=embedding, top_k=int(top_k), softmax=softmax)
        oks, errs = self._get_all(self.keys.mapper_query, encode_query_request(req), timeout)
        return self._merged(oks, errs, int(top_k))

    def _collect(self, key: str, oks: list, errs: list[str], decode: Callable) -> list[tuple]:
        """``[(decoded answer, shard info)]`` of one fan-out ``get`` (``_get_all``); shards answering
        with an error (e.g. an empty map) are left out while one answers; none answering raises
        ``QueryError`` (their errors) or ``MapperUnavailable``. Remembers each shard's info (its
        region, for a later answer it misses)."""
        from common.robot_messages import decode_shard_info

        got, bad = [], []
        for data, att in oks:
            try:
                got.append((decode(data), decode_shard_info(att)))
            except MessageError as e:
                bad.append(str(e).removeprefix("remote error: "))
        if got:
            with self._lock:
                for _, info in got:
                    if info.get("shard"):
                        self._shard_infos[str(info["shard"])] = info
            return got
        if bad:
            raise QueryError("; ".join(dict.fromkeys(bad)))
        if errs:
            raise MapperUnavailable(f"no answer on {key}: {'; '.join(errs)}")
        raise self._no_answer(key)

    def _missing_infos(self, answered: set[str]) -> list[dict]:
        """Remembered shard infos of the shards seen that are not in ``answered``."""
        with self._lock:
            return [i for n, i in self._shard_infos.items() if n in self._shards_seen and n not in answered]

    def _merged(self, oks: list, errs: list[str], top_k: int) -> QueryResult:
        """One result from the replies of one or several mappers (shards: ``query_client.merge``)."""
        import dataclasses

        from query_client.merge import merge_results

        got = self._collect(self.keys.mapper_query, oks, errs, decode_query_result)
        res = merge_results(got, top_k)
        if res is got[0][0] and len(got) == 1:
            res = dataclasses.replace(res)
        res.missing_shards = self._missing({str(i.get("shard", "")) for _, i in got})
        return res

    def _standing(self, sid: str, key: str, decode: Callable, merge: Callable[[list], Any], what: str,
                  callback: Callable) -> ShardLatest:
        """The per-shard latest answers of standing request ``sid`` published on ``key``, merged
        with ``merge`` and passed to ``callback`` on every change (``query_client.standing``)."""
        from common.robot_messages import decode_shard_info

        latest = ShardLatest(self, merge, callback, what)

        def on_sample(sample) -> None:
            try:
                att = sample.attachment
                latest.put(decode(sample.payload.to_bytes()), decode_shard_info(att.to_bytes() if att else None))
            except Exception as e:  # never raise out of a zenoh callback
                log.warning("%s: %s", what, e)

        latest.sub = self.session.declare_subscriber(key, on_sample)
        return latest

    def watch(self, text: str | None, callback: Callable[[QueryResult], None], *, image: bytes | str | None = None,
              top_k: int = 10, qid: str | None = None, timeout: float | None = None) -> WatchHandle:
        """Register a standing query: ``callback(QueryResult)`` runs now and on each refresh
        (on a Zenoh thread; keep it short). With shards, each shard's latest result is kept and
        the merge passed on (a shard whose token goes away is dropped and named missing)."""
        from query_client.merge import merge_results

        qid = qid or "q" + uuid.uuid4().hex[:12]
        if image is not None:
            image = read_query_image(image)
        latest = self._standing(qid, self.keys.mapper_queries(qid), decode_query_result,
                                lambda items: merge_results(items, int(top_k)) if items else QueryResult(id=qid),
                                f"standing query {qid}", callback)
        handle = WatchHandle(self, qid, latest.sub)
        self._watches.add(handle)
        req = QueryRequest(text=text, image=image, top_k=int(top_k), standing=True, id=qid, lease_s=self.lease_s,
                           client=self.client_id)
        try:
            oks, errs = self._get_all(self.keys.mapper_query, encode_query_request(req), timeout)
            latest.first(self._collect(self.keys.mapper_query, oks, errs, decode_query_result), handle)
        except Exception:
            handle.cancel()
            raise
        handle._alive_sub = self._follow_mapper(handle, self.keys.mapper_query, encode_query_request(req),
                                                f"standing query {qid}", timeout)
        self._lease(handle, encode_query_request(req), encode_query_request(QueryRequest(renew=True, id=qid)),
                    decode_query_result)
        return handle

    def _follow_mapper(self, handle, key: str, payload: bytes, what: str, timeout: float | None):
        """Send the standing request ``payload`` on ``key`` again whenever a mapper's liveliness
        token appears (a mapper that restarted without it in its snapshot would otherwise never
        refresh it); a mapper that restored it answers the same id, so registering twice is
        harmless. ``handle``: has ``active`` and counts ``reregistered``."""
        import threading

        def register() -> None:
            try:
                self._get_all(key, payload, timeout)
                handle.reregistered += 1
                log.info("%s registered again with a returning mapper", what)
            except Exception as e:
                log.warning("%s: registering again failed: %s", what, e)

        def on_token(sample) -> None:
            if handle.active and str(sample.kind).endswith("PUT"):
                threading.Thread(target=register, name="rereg", daemon=True).start()

        try:
            return self.session.liveliness().declare_subscriber(self.keys.mapper_alive, on_token)
        except Exception as e:  # the watch still works; it just will not follow restarts
            log.warning("%s: cannot follow the mapper's liveliness: %s", what, e)
            return None

    # ------------------------------------------------------------------ map state
    def stats(self, timeout: float | None = None) -> dict:
        return decode_stats(self._get_one(self.keys.stats, None, timeout))

    def wait_settled(self, mapped: int = 1, received: int = 0, timeout: float = 60.0, every: float = 0.5) -> dict:
        """Poll :meth:`stats` until the mapper has settled (``query_client.vocabulary.settled``:
        every frame it received mapped, dropped or rejected, no queue holding one, the map
        flushed; at least ``mapped`` frames mapped and ``received`` received) and return those
        stats. No answer counts as not yet; after ``timeout`` s raise ``TimeoutError`` with the
        last counts."""
        import time

        from query_client.vocabulary import settled, settled_line

        end = time.monotonic() + timeout
        last: str = "no stats yet"
        while True:
            try:
                st = self.stats(timeout=min(5.0, max(0.5, end - time.monotonic())))
                if settled(st, mapped, received):
                    return st
                last = settled_line(st)
            except QueryError as e:
                last = str(e)
            if time.monotonic() + every > end:
                raise TimeoutError(f"the mapper did not settle within {timeout:g} s (wanted >= {mapped} frames "
                                   f"mapped, >= {received} received; last: {last})")
            time.sleep(every)

    def stats_all(self, timeout: float | None = None) -> dict[str, dict]:
        """Every mapper's stats by shard name (``stats["fleet"]["shard"]``; ``""`` for an
        unsharded mapper). Raises :class:`MapperUnavailable` when none answers."""
        oks, errs = self._get_all(self.keys.stats, None, timeout)
        out = {}
        for data, _ in oks:
            st = decode_stats(data)
            out[str((st.get("fleet") or {}).get("shard") or "")] = st
        if not out:
            raise MapperUnavailable(f"no mapper answered on {self.keys.stats}: {'; '.join(errs) or 'no reply'}")
        return out

    def snapshot(self, save: bool = False, timeout: float | None = None) -> dict:
        """Describe the last snapshot, or (``save=True``) make one now."""
        data = self._get_one(self.keys.snapshot, encode_snapshot_request("save" if save else "describe"),
                             timeout or max(self.timeout, 60.0))
        try:
            return decode_snapshot_reply(data)
        except MessageError as e:
            raise QueryError(str(e)) from None

    def layer(self, name: str, timeout: float | None = None) -> tuple[dict, dict]:
        """Current arrays and meta of a map layer (voxels, frontiers, rays, occupancy)."""
        try:
            _, arrays, meta = decode_layer(self._get_one(self.keys.layers(name), None, timeout))
        except MessageError as e:
            raise QueryError(str(e)) from None
        return {k: np.array(v) for k, v in arrays.items()}, meta

    def frontiers(self, timeout: float | None = None) -> np.ndarray:
        """(F, 3) frontier positions (metres)."""
        return self.layer("frontiers", timeout)[0]["xyz"]

    def ray_fronts(self, text: str | None = None, top_k: int = 1000,
                   timeout: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Semantic ray frontiers: ``(origins (R,3), unit directions (R,3), scores (R,) or None)``.

        Without ``text`` all rays of the layer (subsampled by the mapper's layer limit) and no
        scores; with ``text`` the ``top_k`` rays best matching it with their scores."""
        if text is None:
            a = self.layer("rays", timeout)[0]
            return a["origin"], a["direction"], None
        r = self.query(text, top_k=top_k, timeout=timeout)
        return r.ray_origin, r.ray_direction, r.ray_score

    def world_from_robot(self, robot: str, value: np.ndarray | Sequence[float] | None = None,
                         timeout: float | None = None) -> np.ndarray | None:
        """The mapper's ``world_from_robot`` of ``robot`` (4x4 array, or None: identity); with
        ``value`` (a 4x4 rigid transform or 16 numbers) set it first, at run time. With several
        shards every shard that answers sets it."""
        from common.robot_messages import (
            FleetMessageError,
            decode_transform_reply,
            encode_transform_request,
            robot_transform_key,
        )

        oks, errs = self._get_all(robot_transform_key(self.keys, robot),
                                  encode_transform_request(None if value is None else np.asarray(value, float)),
                                  timeout)
        if not oks:
            raise MapperUnavailable(f"no mapper answered world_from_robot for {robot}: {'; '.join(errs)}")
        try:
            vals = [decode_transform_reply(d) for d, _ in oks][0]
        except FleetMessageError as e:
            raise QueryError(str(e)) from None
        return None if vals is None else np.asarray(vals, float).reshape(4, 4)

    def robots(self, timeout: float = 2.0) -> list[str]:
        """Robots whose edge is alive now (liveliness)."""
        out = []
        for r in self.session.liveliness().get(self.keys.alive_all, timeout=timeout):
            if r.ok is not None:
                name = self.keys.robot_from_key(str(r.ok.key_expr))
                if name:
                    out.append(name)
        return sorted(set(out))

    def mapper_alive(self, timeout: float = 2.0) -> bool:
        return any(r.ok is not None for r in self.session.liveliness().get(self.keys.mapper_alive, timeout=timeout))

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        self._stop.set()
        for h in list(self._watches):
            h.cancel()
        s, self.session = self.session, cast(Any, None)    # closed: no call works after close()
        if s is not None:
            try:
                s.close()
            except Exception:
                pass

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
