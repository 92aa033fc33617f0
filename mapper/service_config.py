"""Configuration of ``rayfronts mapper`` (:class:`MapperConfig`)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

from common.config import check_threads, field_, section
from common.zenoh_session import ZenohConfig
from mapper.leases import StandingLimits
from mapper.outputs.ros import RosSection
from mapper.robot_registry import FleetSection
from mapper.search_config import SearchSection
from mapper.shards import ShardSection
from semantic_map.config import MapConfig


@dataclass
class QueueSection:
    per_robot: int = field_(8, "frames buffered per robot; when full the OLDEST frame is dropped (counted)")
    hold_unknown_space: bool = field_(True, "hold frames of a robot whose feature space is not known yet "
                                            "(else reject them)")
    max_message_mb: float = field_(64.0, "frame messages larger than this are rejected")
    idle_flush_s: float = field_(2.0, "when no frame arrived for this long (s), integrate what the map still buffers "
                                      "(accumulation periods) so queries see every frame; 0 = never. Keep it above "
                                      "the robots' frame interval, or the accumulation periods lose their meaning")


@dataclass
class LayersSection:
    rate_hz: float = field_(1.0, "map layers (voxels, frontiers, rays, occupancy) publish rate; 0 = off")
    max_voxels: int = field_(200_000, "voxels layer is subsampled to at most this many points")
    max_rays: int = field_(50_000, "rays layer is subsampled to at most this many rays")


@dataclass
class QuerySection(StandingLimits):
    standing_rate_hz: float = field_(1.0, "standing queries are re-run at most this often after map updates")
    cluster_candidates: int = field_(2000, "top voxels considered when grouping voxel hits into clusters")
    cluster_rel_score: float = field_(0.9, "only voxels scoring >= this fraction of the best (after min-max "
                                           "normalisation over the map) are clustered")
    search_range_m: float = field_(200.0, "cones of ray hits are cut at this distance when computing the "
                                          "search volume (m)")
    search_rays: int = field_(10, "top rays whose cones make up the search volume")
    templates: Literal["auto", "none", "single", "imagenet80"] = field_(
        "auto", "prompt templates of text queries: auto = the paper's 80 ImageNet/NACLIP templates for language "
                "encoders (naradio), raw text for the label encoder; or none | single | imagenet80")
    softmax_set: Literal["queries", "negatives"] = field_(
        "queries", "what a softmax query is normalised against: 'queries' = the other standing queries (the "
                   "paper; a lone query scores 1 everywhere), 'negatives' = the phrases in softmax_negatives")
    softmax_negatives: list[str] = field_(["object", "things", "stuff", "texture"], "phrases of softmax_set=negatives")
    image_model_dir: str = field_("", "image queries on NARADIO maps: directory with the edge's RADIO checkpoint "
                                      "(default $RAYFRONTS_MODEL_DIR or ~/.cache/rayfronts/models)")
    search_cell_m: float = field_(2.0, "finest spacing of the sample lattice that measures the union of cones (m)")
    search_samples: int = field_(100_000, "sample points (all cones together) that measure the search volume; caps "
                                          "its cost (exact for one cone, disjoint or identical cones)")
    threads: int = field_(0, "torch CPU threads of a query's computations (scoring N voxels is one big matrix "
                             "product); 0 = auto: the CPUs this process may use, at most 16")
    lock_timeout_s: float = field_(0.25, "a query waits at most this long for the map lock (held while a frame is "
                                         "integrated); after that it is answered from the last map snapshot, whose "
                                         "frames_mapped the result carries")


@dataclass
class SnapshotSection:
    dir: str = field_("", "snapshot directory (empty = no snapshots)")
    period_s: float = field_(0.0, "save a snapshot this often (s), when the map or the instance trackers changed; "
                                  "0 = only on request")
    restore: bool = field_(True, "restore the latest snapshot in dir on start")
    keep: int = field_(2, "snapshots kept (older ones are deleted)")
    on_exit: bool = field_(True, "save a snapshot on clean shutdown")
    map_config: Literal["error", "snapshot", "command_line"] = field_(
        "error", "when the restored snapshot's map config differs from this one: 'error' = refuse to start, naming "
                 "the keys; 'snapshot' = restore the map with its saved config; 'command_line' = start an empty map "
                 "with this config (the snapshot stays on disk until newer ones replace it)")


@dataclass
class RerunSection:
    file: str = field_("", "write a rerun recording (.rrd) here; empty = off")
    serve_grpc: bool = field_(False, "serve the live recording over gRPC for a viewer (rerun --connect URL)")
    serve_web: bool = field_(False, "also serve the rerun web viewer, connected to the live stream "
                                    "(implies the gRPC server)")
    grpc_port: int = field_(9876, "gRPC port of the rerun server")
    web_port: int = field_(9090, "HTTP port of the rerun web viewer (serve_web)")
    bind: str = field_("127.0.0.1", "address the rerun gRPC and web servers listen on: 127.0.0.1 = this "
                                    "machine only; 0.0.0.0 = every interface (a viewer on another machine)")
    server_memory_limit: str = field_("512MiB", "the rerun server keeps at most this much of the stream for "
                                                "late viewers (oldest data dropped first)")
    every_n_frames: int = field_(1, "log camera/rgb/depth every n-th frame per robot")
    app_id: str = field_("rayfronts", "rerun application id")


@dataclass
class MapperConfig:
    """Configuration of ``rayfronts mapper``."""

    preset: str = field_("default", "map preset under the map section (default, online, throughput, offline)")
    map: MapConfig = section(MapConfig, "RayFronts map parameters (semantic_map.config.MapConfig)")
    device: str = field_("cpu", "torch device of the map and the text encoder (cpu, cuda, cuda:1)")
    occupancy_backend: str = field_("auto", "occupancy grid: auto (OpenVDB if built, else torch), vdb, torch")
    text_model_dir: str = field_("", "directory of the text model when the feature space needs one on disk")
    threads: int = field_(0, "torch CPU threads of the mapping thread (and the process default); 0 = auto: 1 "
                             "on machines with <= 4 cores (a frame's tensors are small: more threads only fight "
                             "the edge/router processes and the Zenoh threads for the cores), else half the "
                             "cores, at most 8. Queries use query.threads")
    pipeline: bool = field_(True, "two-stage integration (mapper.pipeline): the next frame's geometry and sampling "
                                  "run on a second thread while the current one is fused; same map, drained "
                                  "whenever the input queue is empty")
    zenoh: ZenohConfig = section(ZenohConfig, "Zenoh session (router mode = this process is the base station router)")
    queues: QueueSection = section(QueueSection, "per-robot input queues")
    layers: LayersSection = section(LayersSection, "map layers published for viewers and planners")
    query: QuerySection = section(QuerySection, "queries and standing queries")
    snapshots: SnapshotSection = section(SnapshotSection, "snapshots (atomic) and restore on start")
    rerun: RerunSection = section(RerunSection, "rerun logging")
    fleet: FleetSection = section(FleetSection, "several robots in one map: PCA re-projection, world_from_robot, "
                                                "per-robot status, bounds on per-robot state")
    shard: ShardSection = section(ShardSection, "this mapper as one shard of several (region, tiles, robots)")
    ros: RosSection = section(RosSection, "the map and standing queries as ROS 2 topics over Zenoh (RViz2)")
    search: SearchSection = section(SearchSection, "search for planners: background phrases, look-next and "
                                                   "triangulation parameters, occupancy request bounds")


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def resolve_threads(threads: int, cpu_count: int | None = None) -> int:
    """Torch threads of the mapping thread for config value ``threads`` (``MapperConfig.threads``;
    ``cpu_count`` defaults to the CPUs this process may use)."""
    threads = check_threads(threads, "threads")
    if threads > 0:
        return threads
    n = cpu_count if cpu_count is not None else _cpus()
    return 1 if n <= 4 else min(8, n // 2)


def resolve_query_threads(threads: int, cpu_count: int | None = None) -> int:
    """Torch threads of a query for config value ``query.threads``."""
    threads = check_threads(threads, "query.threads")
    if threads > 0:
        return threads
    return max(1, min(16, cpu_count if cpu_count is not None else _cpus()))


def set_torch_threads(cfg: MapperConfig, query: bool = False) -> int:
    """Set the calling thread's torch intra-op threads: ``cfg.query.threads`` for a query,
    else ``cfg.threads`` (mapping thread, process default). torch keeps the OpenMP count
    per thread once a thread has run parallel work (MKL's count is process-wide: the
    last caller's). Returns the count."""
    import torch

    if query:
        n = resolve_query_threads(int(getattr(cfg.query, "threads", 0)))
    else:
        n = resolve_threads(int(getattr(cfg, "threads", 0)))
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def freeze_startup_objects() -> int:
    """Put every object the process holds so far (modules, configuration, the map's set-up)
    out of the cyclic garbage collector's reach (``gc.freeze``), after one collection: a full
    collection later walks only the objects made since. Without it, at 1M voxels a full
    collection over the ~400k start-up objects took ~285 ms in the middle of a search
    (``docs/results/search.md``). Returns the number of objects frozen."""
    import gc

    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def mapper_config_schema() -> type[MapperConfig]:
    return MapperConfig


def load_mapper_config(path: str | Path | None = None, overrides: Sequence[str] | None = ()) -> MapperConfig:
    """Defaults → preset (from ``preset=`` in the file or overrides) → YAML → overrides."""
    from common.config import load_config, load_yaml, parse_override
    from semantic_map.config import PRESETS

    schema = mapper_config_schema()
    preset = "default"
    data = load_yaml(path) if path else {}
    if isinstance(data.get("preset"), str):
        preset = data["preset"]
    for item in overrides or ():
        d = parse_override(item)
        if isinstance(d.get("preset"), str):
            preset = d["preset"]
    if preset not in PRESETS:
        from common.config import ConfigError

        raise ConfigError(f"unknown map preset {preset!r}; one of {', '.join(PRESETS)}")
    base = {"map": dict(PRESETS[preset])}
    cfg = load_config(schema, path, overrides, base=base)
    if hasattr(cfg.map, "validate"):
        cfg.map.validate()
    cfg.search.validate()
    cfg.ros.validate()
    return cfg
