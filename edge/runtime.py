"""The edge process: source → encoder → PCA compression → frame message → Zenoh.

Threads:

* the main (pipeline) thread reads the source, encodes, compresses and serialises frame
  ``n+1`` while
* the publisher thread sends frame ``n`` with ``CongestionControl.BLOCK``. They meet in a
  one-slot :class:`LatestSlot`: a newer frame replaces an unsent older one (counted as
  ``replaced``), so the encoder never waits on the network and a slow link drops whole old
  frames, never fragments of new ones (docs/key_space.md#topology).
* a connector thread opens the Zenoh session (client mode retries until the base station
  answers) and declares the liveliness token ``robots/<robot>/alive`` and the
  ``robots/<robot>/feature_space`` queryable. Zenoh re-establishes a lost link by itself.

torch runs with ``cfg.threads`` intra-op threads (auto: 1 for the label encoder or a GPU
encoder, whose CPU work is small ops where extra threads only spin against the other
processes; torch's default for a CPU encoder). Each frame's meta carries ``t_send`` (wall
clock at hand-off, for the mapper's latency) and ``cpu_s`` (this process's CPU time, for
the mapper's per-robot edge CPU per frame).

Start-up checks and reporting (``check_setup``): the encoder × ``encoder.output`` × PCA
combination is validated before the first frame is encoded (PCA output dimension within the
encoder's feature dimension, a basis file fitted on the features this encoder/output gives and
with the configured ``pca.out_dim``, enough samples for an online fit); a failing check, a
missing model or basis file, or a source that cannot open is a *refusal*: one error line
naming the combination, exit code 2. An exception while running is a *failure* (exit code 1).
Either way the edge puts its state on ``robots/<robot>/edge_status``
(``common.messages.encode_edge_status``: starting / running / done / refused / failed + the
reason) before it undeclares its liveliness token, so the mapper can name the reason once. The
image-level vector sent with each frame is in the dense features' space
(``encode_with_global(..., global_space="features")``), compressed by the same PCA.

The edge imports neither rerun nor the mapper.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Literal

import numpy as np

from common.config import check_threads, field_, section
from common.zenoh_session import ZenohConfig, close_quietly, undeclare_all
from edge.sources.config import SourceConfig
from encoders.config import EncoderConfig

if TYPE_CHECKING:
    import torch
    import zenoh

    from common.feature_space import FeatureSpace
    from common.frame import Frame
    from common.pca import PCA
    from encoders import ImageEncoder

log = logging.getLogger("rayfronts.edge")

#: publish.tile_m > 0: tile publishers kept declared (least recently used undeclared beyond)
TILE_PUBLISHERS = 16
#: a new tile- or shard-routed publisher waits at most this long (s) for a matching subscriber
NEW_KEY_WAIT_S = 1.0


# ------------------------------------------------------------------------- config
@dataclass
class PcaSection:
    basis: str = field_("", "PCA basis: a file (from `rayfronts edge fit-pca`); 'map' = adopt the map's basis (the "
                            "mapper's feature space; refused if it has none of this encoder family); empty = "
                            "adopt the map's basis when it has one of this encoder family and pca.out_dim, else "
                            "fit online over the first frames")
    map_wait_s: float = field_(3.0, "how long the edge asks the mapper for the map's basis (pca.basis empty or "
                                    "'map') before fitting its own (empty) or refusing ('map')")
    fit_frames: int = field_(8, "frames used to fit the basis online when no basis file is given")
    out_dim: int = field_(100, "PCA output dimension (features per pixel on the wire); 0 = no PCA")
    pixels_per_frame: int = field_(4096, "feature vectors sampled per frame for the online fit")
    save_fitted: str = field_("", "write the online-fitted basis to this file (reuse it with pca.basis)")


@dataclass
class PublishSection:
    rate_hz: float | Literal["auto"] = field_(
        -1.0, "frames per second to pace the source; 0 = as fast as possible; -1 = per source (10 Hz for the "
              "synthetic world, as fast as possible for datasets); auto = the rate the mapper advises on "
              "mapper/robots/<robot>/status (what it maps of this robot without dropping), from 10 Hz")
    loop: bool = field_(False, "restart the source when it ends")
    max_frames: int = field_(0, "stop after this many frames (0 = until the source ends)")
    block_wait_s: float = field_(30.0, "how long a blocked put may wait before Zenoh closes the link "
                                       "(transport/link/tx/queue/congestion_control/block/wait_before_close)")
    linger_s: float = field_(1.0, "after the source ends, keep serving the feature space this long so the "
                                  "last frames can be fetched/mapped")
    connect_retry_s: float = field_(0.5, "retry period after a failed session open")
    jpeg_quality: int = field_(80, "JPEG quality of the RGB image on the wire (the map only colours voxels with it; "
                                   "80 halves a noisy 640x480 image against 90)")
    feature_codec: str = field_("q16z", "features on the wire (frame v2, common.wire.frame): 'q16z' (per-channel "
                                        "int16 + zlib: ~8 KB for a 640x480 PCA-100 label frame, cosine change ~2e-5), "
                                        "'q8z' (int8 + zlib, ~4 KB, changes up to ~0.006) or 'f16' (float16, 240 KB)")
    status_wait_s: float = field_(3.0, "when the edge refuses to start or fails: how long it waits for the "
                                       "Zenoh session to put the reason on robots/<robot>/edge_status")
    tile_m: float = field_(0.0, "publish each frame on robots/<robot>/frames/<i>_<j>, (i, j) = floor(x / tile_m), "
                                "floor(y / tile_m) of the camera centre in the robot's own pose frame, so Zenoh "
                                "routes it to the shards owning that tile (docs/key_space.md#shards); 0 = plain "
                                "robots/<robot>/frames")
    shard_routing: bool = field_(True, "with publish.tile_m = 0: learn the mapper shards' regions (their "
                                       "announcements on mapper/shards/<name>/routing) and send each frame only to "
                                       "the shards that own its camera centre (docs/key_space.md#shards); false = "
                                       "every frame on the plain key")
    wait_subscriber_s: float = field_(5.0, "before the first frame of a session, wait up to this long for a "
                                           "subscriber (a mapper) to match the frames key (Zenoh matching "
                                           "status), so frames sent while the route forms are not lost; then "
                                           "send anyway (0 = do not wait)")
    lossless: bool = field_(False, "the encoder waits for the sender instead of replacing an unsent frame, so no "
                                   "frame is dropped at the edge: for replays, evaluation and tests (a live camera "
                                   "wants the newest frame: keep false)")


@dataclass
class RecordingSection:
    dir: str = field_("", "record exactly what is sent to this directory (common.recording); empty = off")
    overwrite: bool = field_(False, "replace an existing recording in dir")


@dataclass
class EdgeConfig:
    """Configuration of ``rayfronts edge``."""

    robot: str = field_("", "robot id ([A-Za-z0-9_-]+) naming the Zenoh keys and stamped on frames; "
                            "empty = source.robot")
    threads: int = field_(0, "torch CPU threads of the edge process (intra-op, process-wide); 0 = auto: 1 when "
                             "the encoder is the label encoder or runs on a GPU (torch then only does small glue "
                             "ops on the CPU, and more threads fight the other processes for the cores), else "
                             "torch's default (all cores, for a CPU encoder)")
    source: SourceConfig = section(SourceConfig, "where frames come from")
    encoder: EncoderConfig = section(EncoderConfig, "the image encoder (encoder.device = torch device)")
    pca: PcaSection = section(PcaSection, "PCA compression of the dense features")
    zenoh: ZenohConfig = section(ZenohConfig, "Zenoh session (the edge is normally a client)")
    publish: PublishSection = section(PublishSection, "publishing and pacing")
    recording: RecordingSection = section(RecordingSection, "optional recording of what was sent")


def edge_config_schema() -> type[EdgeConfig]:
    """The ``EdgeConfig`` dataclass."""
    return EdgeConfig


def resolve_threads(cfg: EdgeConfig) -> int:
    """The edge's torch thread count for ``cfg.threads`` (see ``EdgeConfig.threads``); 0
    means leave torch's default."""
    n = check_threads(int(getattr(cfg, "threads", 0)), "threads")
    if n > 0:
        return n
    enc = cfg.encoder
    if enc.kind == "label" or not str(enc.device).startswith("cpu"):
        return 1
    return 0


# ---------------------------------------------------------------------- one slot
class LatestSlot:
    """A one-slot queue holding only the newest item; ``put`` never blocks.

    A put over an item nobody took yet replaces it and counts in ``replaced``."""

    def __init__(self):
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


# ------------------------------------------------------------------ start-up checks
class EdgeRefused(Exception):
    """The edge cannot start with this configuration; the text is the one-line reason."""


def _combo(cfg: EdgeConfig) -> str:
    e = cfg.encoder
    enc = f"encoder.kind={e.kind}" + (f" encoder.output={e.output}" if e.kind == "naradio" else "")
    pca = ("pca.out_dim=0 (no PCA)" if cfg.pca.out_dim <= 0 else
           f"pca.basis={cfg.pca.basis}" if cfg.pca.basis else f"pca.out_dim={cfg.pca.out_dim} (fitted online)")
    return f"{enc}, {pca}"


def basis_file(cfg: EdgeConfig) -> str:
    """The PCA basis file of ``pca.basis`` ("" when empty or ``map``)."""
    return "" if cfg.pca.basis in ("", "map") else cfg.pca.basis


def check_setup(cfg: EdgeConfig, encoder: ImageEncoder, pca: PCA | None) -> None:
    """Refuse (:class:`EdgeRefused`) an encoder × output × PCA combination that cannot run."""
    d = int(encoder.feature_dim)
    k = int(cfg.pca.out_dim)
    where = _combo(cfg)
    if k < 0:
        raise EdgeRefused(f"{where}: pca.out_dim must be >= 0 (0 = no PCA)")
    if cfg.publish.feature_codec not in ("q16z", "q8z", "f16"):
        raise EdgeRefused(f"publish.feature_codec={cfg.publish.feature_codec!r}: choose q16z, q8z or f16")
    if not 1 <= cfg.publish.jpeg_quality <= 100:
        raise EdgeRefused(f"publish.jpeg_quality={cfg.publish.jpeg_quality}: must be in 1..100")
    if k > d:
        raise EdgeRefused(f"{where}: pca.out_dim={k} exceeds the encoder's {d}-d features; use at most {d}")
    if pca is not None:
        if pca.in_dim != d:
            hint = ""
            if cfg.encoder.kind == "naradio":
                hint = (" (encoder.output=radio gives backbone-width features, output=language the language "
                        "head's width: fit the basis with the same output, `rayfronts edge fit-pca`)")
            raise EdgeRefused(f"{where}: the basis was fitted on {pca.in_dim}-d features but this encoder "
                              f"gives {d}-d features{hint}")
        if pca.out_dim != k:
            raise EdgeRefused(f"{where}: the basis has {pca.out_dim} components but pca.out_dim={k}; set "
                              f"pca.out_dim={pca.out_dim} to use this basis")
    elif k > 0 and not cfg.pca.basis:      # an online fit
        n = max(1, cfg.pca.fit_frames) * cfg.pca.pixels_per_frame
        if n <= k:
            raise EdgeRefused(f"{where}: an online fit over pca.fit_frames={cfg.pca.fit_frames} x "
                              f"pca.pixels_per_frame={cfg.pca.pixels_per_frame} = {n} samples cannot give {k} "
                              "components; raise them or give pca.basis")


def check_first_features(cfg: EdgeConfig, feats: torch.Tensor) -> None:
    """After the first frame: an online PCA fit needs more feature vectors than components."""
    k = int(cfg.pca.out_dim)
    if k > 0 and not cfg.pca.basis:
        per = min(int(feats.shape[-1] * feats.shape[-2]), cfg.pca.pixels_per_frame)
        n = per * max(1, cfg.pca.fit_frames)
        if n <= k:
            raise EdgeRefused(f"{_combo(cfg)}: the encoder gives {per} feature vectors per frame, so an online "
                              f"fit over {cfg.pca.fit_frames} frames has {n} samples for {k} components; raise "
                              "pca.fit_frames, lower pca.out_dim or give pca.basis")


# ------------------------------------------------------------------ compression
def compress_features(pca: PCA | None, feats: torch.Tensor | np.ndarray) -> np.ndarray:
    """(C, h, w) encoder features → (D, h, w) float16 PCA coefficients (``pca=None``: cast only)."""
    import torch

    f = feats if isinstance(feats, torch.Tensor) else torch.as_tensor(np.asarray(feats))
    c, h, w = f.shape
    if pca is None:
        return f.to(torch.float16).cpu().numpy()
    flat = f.reshape(c, h * w).T.to(torch.float32)
    z = pca.compress(flat)
    z = z if isinstance(z, torch.Tensor) else torch.as_tensor(np.asarray(z))
    return z.T.reshape(-1, h, w).to(torch.float16).cpu().numpy()


# ---------------------------------------------------------------------- runtime
@dataclass
class EdgeStats:
    frames_read: int = 0
    frames_skipped: int = 0          # frames the source could not read/decode (skipped, counted)
    frames_encoded: int = 0
    frames_sent: int = 0
    frames_replaced: int = 0
    bytes_sent: int = 0
    put_errors: int = 0
    encode_ms_last: float = 0.0
    put_ms_last: float = 0.0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class _RunState:
    """What :meth:`EdgeRuntime._run` carries from frame to frame."""

    rate: float  # frames per second (0 = as fast as possible)
    next_t: float  # time.monotonic() of the next paced send
    seq: int = 0
    encoder: Any = None  # ImageEncoder once loaded
    pca: Any = None  # PCA or None
    fs: Any = None  # FeatureSpace once known
    fitter: Any = None  # OnlinePCAFitter while fitting PCA online
    pending: list = dataclasses.field(default_factory=list)  # frames held while fitting PCA online


class EdgeRuntime:
    """Runs the edge pipeline until the source ends or ``stop`` is set.

    ``frames`` (optional) replaces the configured source (tests, benchmarks);
    ``on_sent(frame, nbytes, t_put)`` is called by the publisher thread after each put."""

    def __init__(self, cfg, stop: threading.Event | None = None, frames: Iterable[Frame] | None = None,
                 class_names: list[str] | None = None,
                 on_sent: Callable[[Any, int, float], None] | None = None):
        if not cfg.robot:
            cfg = dataclasses.replace(cfg, robot=cfg.source.robot)
        self.cfg = cfg
        self.stop = stop or threading.Event()
        self._frames = frames
        self._class_names = class_names
        self.on_sent = on_sent
        self.stats = EdgeStats()
        self.slot = LatestSlot()
        self.session = None
        self._publisher = None
        self._tile_pubs: dict[str, object] = {}   # tile-routed / shard-routed key -> publisher (LRU)
        self._routes = None                       # edge.shard_routes.ShardRoutes of the session
        self._routes_stop = threading.Event()
        self._token = None
        self._queryable = None
        self._connected = threading.Event()
        self._matched = False   # a subscriber matched the frames key in this session (see _wait_matching)
        self._fs_reply: bytes | None = None
        self._fs_lock = threading.Lock()
        self.feature_space = None
        self.keys = None
        self._recorder = None
        self._threads: list[threading.Thread] = []
        from edge.fleet_status import AutoRate, StatusWatcher

        # the mapper's per-robot status: logged on change; publish.rate_hz=auto follows its advice
        self.auto_rate = AutoRate() if cfg.publish.rate_hz == "auto" else None
        self.mapper_status = StatusWatcher(cfg.robot, self.auto_rate)
        self._mapper_status_sub = None
        self._started = False
        self._status_q = None
        self._status_pub = None
        self._state = ("starting", "")
        self._state_lock = threading.Lock()
        self.phase = "waiting for the first source frame"   # what the pipeline is doing (said in
        # the feature-space "not ready" reply and logged on each change)

    def _set_phase(self, phase: str) -> None:
        self.phase = phase
        log.info("edge %s: %s", self.cfg.robot, phase)

    # ---------------------------------------------------------------- zenoh side
    def _connect_loop(self) -> None:
        import zenoh

        from common.fleet import robot_status_key
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
            robot = self.cfg.robot
            try:
                self._publisher = s.declare_publisher(
                    self.keys.frames(robot),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.DATA, express=False)
                self._queryable = s.declare_queryable(self.keys.feature_space(robot), self._on_feature_space)
                self._status_pub = s.declare_publisher(self.keys.edge_status(robot))
                self._status_q = s.declare_queryable(self.keys.edge_status(robot), self._on_status)
                self._token = s.liveliness().declare_token(self.keys.alive(robot))
                # what the mapper does with our frames (logged on change; publish.rate_hz=auto)
                self._mapper_status_sub = s.declare_subscriber(robot_status_key(self.keys, robot),
                                                               self.mapper_status.on_sample)
            except Exception:
                s.close()
                raise
            self.session = s
            self._matched = False   # the first frame of this session waits for a subscriber
            if self.cfg.publish.shard_routing and self.cfg.publish.tile_m <= 0:
                from edge.shard_routes import ShardRoutes

                self._routes_stop = threading.Event()
                self._routes = ShardRoutes(s, self.keys, robot, self._routes_stop).start()
                if self._routes.shards():
                    log.info("routing frames to the shards that own them: %s", ", ".join(self._routes.shards()))
            if self.stop.is_set():  # closed while we were connecting
                self._close_session()
                return
            log.info("edge %s connected (zid %s)", robot, s.zid())
            self._connected.set()
            return

    def _on_feature_space(self, query: zenoh.Query) -> None:
        from common.messages import encode_error

        try:
            with self._fs_lock:
                reply = self._fs_reply
            payload = reply if reply is not None else encode_error(f"feature space not ready ({self.phase})")
            query.reply(query.key_expr, payload)
        except Exception as e:  # never raise out of a callback
            log.warning("feature_space reply failed: %s", e)

    def _status_bytes(self) -> bytes:
        from common.messages import encode_edge_status

        with self._state_lock:
            state, reason = self._state
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
            self._state = (state, reason)
        if not self._connected.is_set() and wait_s > 0:
            self._connected.wait(wait_s)
        pub = self._status_pub
        if pub is None or not self._connected.is_set():
            return
        try:
            pub.put(self._status_bytes())
        except Exception as e:
            log.warning("edge_status put failed: %s", e)

    def _wait_matching(self, pub, limit_s: float | None = None) -> None:
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

    def _publish_loop(self) -> None:
        while True:
            item = self.slot.get(timeout=0.2)
            if item is None:
                if self.stop.is_set() and not self.slot.pending:
                    return
                continue
            frame, data = item
            while not self._connected.wait(0.2):
                if self.stop.is_set():
                    return
            pub = self._frame_publisher(frame)
            if not self._matched:
                self._wait_matching(pub)
                self._matched = True
            t0 = time.time()
            try:
                pub.put(data)
            except Exception as e:
                self.stats.put_errors += 1
                log.warning("put failed: %s", e)
                continue
            self.stats.put_ms_last = (time.time() - t0) * 1e3
            self.stats.frames_sent += 1
            self.stats.bytes_sent += len(data)
            if self._recorder is not None:
                try:
                    self._recorder.write_encoded(data)  # exactly the bytes that were sent
                except Exception as e:
                    log.error("recording failed, disabled: %s", e)
                    self._recorder = None
            if self.on_sent is not None:
                self.on_sent(frame, len(data), t0)

    def _frame_publisher(self, frame: Frame):
        """The publisher of ``frame``'s key: with ``publish.tile_m`` > 0 the key of the tile of its
        camera centre (robot's pose frame); else, with ``publish.shard_routing``, the key
        addressed to the shards owning it (:mod:`edge.shard_routes`); else (or when no shard owns
        it) the plain frames key. Keyed publishers are declared lazily and cached (at most
        ``TILE_PUBLISHERS``; the least recently used one is undeclared)."""
        tile_m = float(self.cfg.publish.tile_m)
        robot = self.cfg.robot
        if tile_m > 0:
            c = np.asarray(frame.pose, np.float64)[:3, 3]
            key = self.keys.frames_tile(robot, (math.floor(c[0] / tile_m), math.floor(c[1] / tile_m)))
        else:
            routes = self._routes
            shards = routes.targets(frame.pose) if routes is not None else []
            if not shards:
                return self._publisher
            key = self.keys.frames_routed(robot, shards)
        import zenoh

        pubs = self._tile_pubs
        pub = pubs.pop(key, None)
        if pub is None:
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                 priority=zenoh.Priority.DATA, express=False)
            # a put on a key declared just now may go out before the router has told this client
            # about the subscribers of that key (the frame would reach nobody): wait a moment
            self._wait_matching(pub, NEW_KEY_WAIT_S)
            while len(pubs) >= TILE_PUBLISHERS:
                undeclare_all((pubs.pop(next(iter(pubs))),))
        pubs[key] = pub                     # most recently used last
        return pub

    # -------------------------------------------------------------- pipeline side
    def _open_source(self) -> tuple[Iterable[Frame], list[str] | None]:
        if self._frames is not None:
            return self._frames, self._class_names
        from edge.sources import open_source

        extra = {}
        if self.cfg.source.kind in ("ros2", "sim_camera"):  # live: the edge's Zenoh settings and its stop event
            extra = {"zenoh": self.cfg.zenoh, "stop": self.stop}
        src = open_source(self.cfg.source, **extra)
        return src, list(getattr(src, "class_names", None) or []) or None

    def _rate(self) -> float:
        r = self.cfg.publish.rate_hz
        if r == "auto":
            return self.auto_rate.current()
        if r >= 0:
            return r
        return 10.0 if getattr(self.cfg.source, "kind", "") == "synthetic" else 0.0

    def _iter_frames(self) -> Iterator[tuple[Frame, list[str] | None]]:
        n = 0
        skipped0 = 0
        while not self.stop.is_set():
            src, names = self._open_source()
            got = False
            for fr in src:
                got = True
                # frames the source skipped as corrupt (FrameSource.skipped) are counted, not fatal
                self.stats.frames_skipped = skipped0 + int(getattr(src, "skipped", {}).get("corrupt frame", 0))
                yield fr, names
                n += 1
                if self.stop.is_set() or (self.cfg.publish.max_frames and n >= self.cfg.publish.max_frames):
                    return
            skipped0 += int(getattr(src, "skipped", {}).get("corrupt frame", 0))
            self.stats.frames_skipped = skipped0
            if not self.cfg.publish.loop or not got or self._frames is not None:
                return

    def _build_feature_space(self, encoder: ImageEncoder, pca: PCA | None) -> FeatureSpace:
        from common.feature_space import FeatureSpace
        from common.messages import encode_feature_space

        fs = FeatureSpace.for_encoder(encoder, pca)
        self.feature_space = fs
        with self._fs_lock:
            self._fs_reply = encode_feature_space(self.cfg.robot, fs.to_body())
        log.info("feature space %s (dim %d)", fs.id, fs.dim)
        self._set_phase("sending frames")
        return fs

    def run(self) -> int:
        """Run to the end of the source (or ``stop``); returns a process exit code: 0 done,
        2 refused at start-up, 1 failed while running (state and reason on ``edge_status``)."""
        from common.config import ConfigError
        from common.model_files import ModelFileError
        from common.pca import PCAError

        try:
            return self._run()
        except (EdgeRefused, ConfigError, PCAError, ModelFileError, FileNotFoundError, ValueError) as e:
            if not self._started:
                reason = str(e).splitlines()[0] if str(e) else type(e).__name__
                log.error("edge %s refused to start: %s", self.cfg.robot, reason)
                self._report_end("refused", reason)
                return 2
            return self._failed(e)
        except Exception as e:
            return self._failed(e)
        finally:
            self.close()

    def _failed(self, e: BaseException) -> int:
        reason = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}".rstrip(": ")
        log.error("edge %s failed after %d frames: %s", self.cfg.robot, self.stats.frames_encoded, reason,
                  exc_info=True)
        self._report_end("failed", reason)
        return 1

    def _report_end(self, state: str, reason: str) -> None:
        """Put the final state (waiting briefly for the session) and give Zenoh a moment to
        send it before the session closes."""
        self.set_state(state, reason, wait_s=self.cfg.publish.status_wait_s)
        if self._connected.is_set():
            time.sleep(0.3)

    def _run(self) -> int:
        import torch

        cfg = self.cfg
        n_threads = resolve_threads(cfg)
        if n_threads and torch.get_num_threads() != n_threads:
            torch.set_num_threads(n_threads)
        self._start_workers()
        self._started = False
        st = _RunState(rate=self._rate(), next_t=time.monotonic())
        try:
            for fr, names in self._iter_frames():
                self.stats.frames_read += 1
                if st.encoder is None:
                    self._load_encoder(st, names)
                t0 = time.perf_counter()
                with torch.inference_mode():
                    # one forward pass gives the dense map and the image-level vector
                    feats, gfeat = st.encoder.encode_with_global(fr.rgb, fr.labels, global_space="features")
                if not self._started:
                    if st.fitter is not None:
                        check_first_features(cfg, feats)
                    self._started = True
                    self.set_state("running")
                self.stats.frames_encoded += 1
                todo = self._frames_to_send(st, fr, feats, gfeat)
                if todo is None:  # held while fitting PCA online
                    continue
                self._send_frames(st, todo, t0)
                if self.stop.is_set():
                    break
            self._finish_run()
        finally:
            self.slot.close()  # run() reports a refusal/failure on the still open session, then closes
        self.stats.frames_replaced = self.slot.replaced
        log.info("edge %s done: %s", cfg.robot, self.stats.as_dict())
        return 0

    def _start_workers(self) -> None:
        """Start the connector and publisher threads; open the recording if one is configured."""
        cfg = self.cfg
        conn = threading.Thread(target=self._connect_loop, name="edge-connect", daemon=True)
        pub = threading.Thread(target=self._publish_loop, name="edge-publisher", daemon=True)
        conn.start()
        pub.start()
        self._threads = [conn, pub]
        if cfg.recording.dir:
            from common.recording import RecordingWriter

            self._recorder = RecordingWriter(Path(cfg.recording.dir), robot=cfg.robot, source=cfg.source.kind,
                                             overwrite=cfg.recording.overwrite)

    def _load_encoder(self, st: _RunState, names: list[str] | None) -> None:
        """Build the encoder (for the source's class ``names``) and the PCA: a basis file, none,
        or an online fitter (``st.fs`` stays None until the fit is done)."""
        from common.pca import PCA
        from encoders import make_encoder

        cfg = self.cfg
        self._set_phase(f"loading the {cfg.encoder.kind} encoder")
        st.encoder = make_encoder(cfg.encoder, class_names=names)
        if basis_file(cfg) and cfg.pca.out_dim > 0:
            st.pca = PCA.load(basis_file(cfg))
        elif cfg.pca.basis in ("", "map") and cfg.pca.out_dim > 0:
            st.pca = self._map_basis(st.encoder, required=cfg.pca.basis == "map")
            if st.pca is not None and st.pca.out_dim != cfg.pca.out_dim:   # only with pca.basis=map
                log.info("pca.out_dim=%d -> %d: the map's basis", cfg.pca.out_dim, st.pca.out_dim)
                self.cfg = cfg = dataclasses.replace(cfg, pca=dataclasses.replace(cfg.pca, out_dim=st.pca.out_dim))
        check_setup(cfg, st.encoder, st.pca)
        if cfg.pca.out_dim <= 0:
            st.fs = self._build_feature_space(st.encoder, None)
        elif st.pca is not None:
            st.fs = self._build_feature_space(st.encoder, st.pca)
        else:
            from common.pca import OnlinePCAFitter

            log.warning("no PCA basis file given: fitting PCA-%d online over the first %d frames "
                        "(frames are held until then; give pca.basis for a fixed, shared basis)",
                        cfg.pca.out_dim, cfg.pca.fit_frames)
            st.fitter = OnlinePCAFitter(cfg.pca.out_dim, max(1, cfg.pca.fit_frames),
                                        cfg.pca.pixels_per_frame)
            self._set_phase(f"fitting PCA-{cfg.pca.out_dim} online over the first "
                            f"{max(1, cfg.pca.fit_frames)} frames")

    def _map_basis(self, encoder: ImageEncoder, required: bool) -> PCA | None:
        """The map's PCA basis, asked on ``<p>/mapper/feature_space`` for up to
        ``pca.map_wait_s``: adopted when the map's encoder family is this encoder's (and, unless
        ``required`` (``pca.basis=map``), its components are ``pca.out_dim``); else None, or
        :class:`EdgeRefused` when required."""
        from common.feature_space import FeatureSpace, compatibility

        cfg = self.cfg
        self._set_phase("asking the mapper for the map's PCA basis")
        wait = max(0.1, float(cfg.pca.map_wait_s))
        end = time.monotonic() + wait
        map_fs, why = None, "no mapper answered"
        if self._connected.wait(wait) and self.session is not None:
            map_fs, why = self._ask_map_space(max(0.1, end - time.monotonic()))
        if map_fs is not None:
            why = compatibility(map_fs, FeatureSpace.for_encoder(encoder, None))
            if not why and map_fs.pca is None:
                why = "the map stores uncompressed features"
            if not why and not required and map_fs.pca.out_dim != cfg.pca.out_dim:
                why = f"the map's basis has {map_fs.pca.out_dim} components, pca.out_dim={cfg.pca.out_dim}"
        if not why:
            log.info("adopting the map's PCA basis (feature space %s): no re-projection at the mapper", map_fs.id)
            return map_fs.pca
        if required:
            raise EdgeRefused(f"pca.basis=map: cannot adopt the map's basis: {why}")
        log.info("not adopting the map's PCA basis (%s): fitting one online", why)
        return None

    def _ask_map_space(self, timeout: float) -> tuple[FeatureSpace | None, str]:
        """(the map's feature space, "") from the first mapper shard that has one, else
        (None, why)."""
        from common.feature_space import FeatureSpace
        from common.messages import MessageError, decode_feature_space

        why = "no mapper answered"
        try:
            replies = list(self.session.get(self.keys.mapper_feature_space, timeout=timeout))
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

    def _frames_to_send(self, st: _RunState, fr: Frame, feats: torch.Tensor,
                        gfeat: torch.Tensor | None) -> list | None:
        """``[(frame, features, global feature)]`` to send now: this frame, or while fitting PCA
        online None (held) until the fit is done, then the whole backlog."""
        if st.fs is not None:
            return [(fr, feats, gfeat)]
        st.pending.append((fr, feats, gfeat))
        if not st.fitter.add(feats):
            return None
        st.pca = st.fitter.fit()
        if self.cfg.pca.save_fitted:
            st.pca.save(self.cfg.pca.save_fitted)
        st.fs = self._build_feature_space(st.encoder, st.pca)
        todo, st.pending = st.pending, []
        return todo

    def _send_frames(self, st: _RunState, todo: list, t0: float) -> None:
        """Compress, encode, pace and hand ``todo`` to the publisher (``t0``: perf_counter at the
        encoder call); returns early when stopped."""
        import torch

        from common.wire import encode_frame

        cfg = self.cfg
        for fr_i, feats_i, g_i in todo:
            out = dataclasses.replace(
                fr_i, robot=cfg.robot, seq=st.seq, features=compress_features(st.pca, feats_i),
                feature_space=st.fs.id,
                global_feature=None if g_i is None else compress_features(
                    st.pca, torch.as_tensor(g_i).reshape(-1, 1, 1)).reshape(-1))
            # t_send: hand-off wall clock (latency); cpu_s: this process's CPU time so far
            # (the mapper reports the edge's CPU per frame from it)
            out.meta = {**(out.meta or {}), "t_send": time.time(), "cpu_s": time.process_time()}
            data = encode_frame(out, feature_codec=cfg.publish.feature_codec,
                                jpeg_quality=cfg.publish.jpeg_quality)
            self.stats.encode_ms_last = (time.perf_counter() - t0) * 1e3
            st.seq += 1
            if self._pace(st):
                return
            # a backlog held during the PCA fit, or publish.lossless: hand over without replacing
            if len(todo) > 1 or cfg.publish.lossless:
                while self.slot.pending and not self.stop.is_set():
                    self.slot.wait_empty(0.2)
            self.slot.put((out, data))
            self.stats.frames_replaced = self.slot.replaced

    def _pace(self, st: _RunState) -> bool:
        """Wait for the next send time at the current rate (Hz; 0 = no pacing); True if stopped meanwhile."""
        if self.auto_rate is not None:
            st.rate = self.auto_rate.current()
        if st.rate > 0:
            st.next_t += 1.0 / st.rate
            delay = st.next_t - time.monotonic()
            if delay > 0:
                if self.stop.wait(delay):
                    return True
            else:
                st.next_t = time.monotonic()
        return False

    def _finish_run(self) -> None:
        """Drain: let the publisher send the last frame, then linger for late feature-space gets."""
        cfg = self.cfg
        end = time.monotonic() + 30.0
        while self.slot.pending and not self.stop.is_set() and time.monotonic() < end:
            time.sleep(0.05)
        if not self.stop.is_set():
            self.stop.wait(cfg.publish.linger_s)
        if not self._started and not self.stop.is_set():
            raise EdgeRefused(f"the source ({cfg.source.kind}) yielded no frames")
        self.set_state("done")

    def close(self) -> None:
        """Stop the threads and close the Zenoh session (idempotent; never hangs)."""
        self.stop.set()
        self.slot.close()
        for t in self._threads:
            t.join(timeout=5.0)
        close_quietly(self._recorder, "the recording")
        self._recorder = None
        self._close_session()

    def _close_session(self) -> None:
        s, self.session = self.session, None
        self._routes_stop.set()
        self._routes = None
        if s is not None:
            undeclare_all((self._mapper_status_sub,
                           self._token, self._queryable, self._status_q, self._status_pub, self._publisher,
                           *self._tile_pubs.values()))
            self._tile_pubs = {}
            close_quietly(s)
