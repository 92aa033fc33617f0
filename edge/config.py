"""The ``rayfronts edge`` config schema (``EdgeConfig`` and its sections: ``pca``, ``publish``,
``recording``; ``source``, ``encoder`` and ``zenoh`` are the shared schemas) and the choices
read straight off it (torch thread count, PCA basis file). Rates in Hz, times in seconds."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from common.config import check_threads, field_, section
from common.zenoh_session import ZenohConfig
from edge.sources.config import SourceConfig
from encoders.config import EncoderConfig


@dataclass
class PcaSection:
    """``pca.*``: how the dense features are compressed before they go on the wire."""

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
    """``publish.*``: pacing (Hz), the wire format, the keys a frame goes on, waits (s)."""

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
    """``recording.*``: a copy of exactly what was sent (``common.recording``)."""

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


def basis_file(cfg: EdgeConfig) -> str:
    """The PCA basis file of ``pca.basis`` ("" when empty or ``map``)."""
    return "" if cfg.pca.basis in ("", "map") else cfg.pca.basis
