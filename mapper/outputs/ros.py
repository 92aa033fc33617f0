"""The map out to ROS 2 (``ros.enabled=true``): RViz2 on the robot's network shows it live,
with no ROS install on the mapper (module map: :mod:`mapper.state`; ARCHITECTURE.md).

Topics (under ``ros.topic_prefix``, default ``/rayfronts``), in the world frame
``ros.frame_id`` (the map's world: z up, metres):

* ``/rayfronts/voxels`` — sensor_msgs/PointCloud2, fields x, y, z (float32) and rgb (float32
  holding 0x00RRGGBB, as PCL / RViz2 expect): the semantic voxel centres with their colour;
* ``/rayfronts/frontiers`` — PointCloud2 x, y, z: frontier centres;
* ``/rayfronts/rays`` — visualization_msgs/MarkerArray: a DELETEALL marker, then one ARROW
  per semantic ray from its frontier along its direction (``ros.ray_length`` m), coloured by
  the ray's accumulated weight (blue = lightest ... red = heaviest, scaled to the heaviest);
* ``/rayfronts/query/<id>`` — PointCloud2 x, y, z, score (float32) of each standing query's
  top voxels, each time the query server refreshes it (``mapper/queries/<id>``);
* ``/rayfronts/query_text`` (subscribed) — std_msgs/String: adds a standing text query with
  id ``ros_<text, non-alphanumerics as _>`` and ``ros.query_top_k`` voxels;
* the planners' search and costmap (``<prefix>/search_text`` in; ``/search/*`` and
  ``/costmap`` out): :mod:`mapper.outputs.ros_search`, when the mapper's search service is given;
* per robot (``ros.robots.<id>``): its search, Nav2 goal, feedback and costmap on its own
  namespace (:mod:`mapper.outputs.ros_robots`); upstream RayFronts' messaging-service topics
  (``ros.msg_serv``, :mod:`mapper.outputs.ros_msg_serv`); docs/ros2.md.

Layers go out at ``ros.rate_hz`` from their own thread (``mapper-ros``) when the map changed
(integrated or flushed),
limited by ``layers.max_voxels`` / ``ros.max_rays`` (seeded subsample, as the layer messages).
Keys (``ros.keys``): rmw_zenoh (``<ros.domain>/<topic>/<dds type>/<type hash>``, the hash of
``ros.distro``: Jazzy ``RIHS01_...`` or Humble ``TypeHashNotSupported``; plus the node /
publisher / subscription liveliness tokens ``@ros2_lv/...`` that ``ros2 topic list`` reads,
and the per-sample attachment: each publisher's own sequence number from 1 and its gid, the
hash of its token key; docs/key_space.md) or bridge (``<topic>``, no tokens). Messages are built with
rosbags' typestore of ``ros.distro`` (Jazzy's Marker has fields Humble's lacks). The
session is the mapper's own unless ``ros.connect`` names the robot's router (client session).
"""
from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Sequence

import numpy as np
import numpy.typing as npt

from common.config import field_, section
from common.zenoh_session import close_quietly, undeclare_all
from mapper.outputs.ros_markers import POINTCLOUD2, MsgTypes, header_msg, marker_extra_fields, pointcloud2
from mapper.outputs.ros_msg_serv import MsgServSection

if TYPE_CHECKING:
    import zenoh

    from semantic_map.map import RayFrontsMap

log = logging.getLogger("rayfronts.mapper")

MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
STRING = "std_msgs/msg/String"


@dataclass
class RosSection:
    enabled: bool = field_(False, "publish the map as ROS 2 topics over Zenoh (RViz2, no ROS install here)")
    domain: int = field_(0, "ROS_DOMAIN_ID of the robot network (rmw_zenoh keys)")
    frame_id: str = field_("map", "header.frame_id of every message (the map's world frame in tf)")
    keys: Literal["rmw_zenoh", "bridge"] = field_(
        "rmw_zenoh", "key layout: rmw_zenoh (<domain>/<topic>/<dds type>/<hash> + graph tokens) or bridge "
                     "(zenoh-bridge-ros2dds: <topic>)")
    distro: Literal["humble", "jazzy"] = field_(
        "jazzy", "ROS 2 distro of the subscribers: message definitions and type hash (jazzy: RIHS01_..., "
                 "humble: TypeHashNotSupported)")
    rate_hz: float = field_(1.0, "ROS layer publish rate (when the map changed); 0 = only standing queries")
    topic_prefix: str = field_("/rayfronts", "topic namespace: <prefix>/voxels, /frontiers, /rays, /query/<id>, "
                                             "/query_text")
    connect: list[str] = field_([], "Zenoh endpoints of the robot's ROS router (client session); [] = publish "
                                    "on the mapper's own session")
    ray_length: float = field_(2.0, "length in metres of the ray arrows")
    max_rays: int = field_(2000, "at most this many ray arrows per MarkerArray (seeded subsample)")
    query_top_k: int = field_(1000, "voxels per standing query added from /rayfronts/query_text")
    node: str = field_("rayfronts_mapper", "ROS node name in the graph tokens")
    search_threshold: float = field_(0.5, "probability threshold of the standing search from <prefix>/search_text")
    search_max_instances: int = field_(10, "found instances published by the ROS search")
    search_max_goals: int = field_(5, "look-next goals published by the ROS search")
    costmap_z_band: list[float] = field_([0.2, 1.5], "z band [z0, z1] (m) of the <prefix>/costmap OccupancyGrid "
                                                      "([] = no costmap)")
    costmap_box: list[float] = field_([], "xy region [x0, y0, x1, y1] (m) of the costmap; [] = the extent of the "
                                          "map's observed voxels")
    costmap_stride: int = field_(1, "costmap cell size in map voxels")
    robots: dict[str, Any] = field_({}, "per-robot search, Nav2 goals and costmap: ros.robots.<id>.<key> "
                                        "(docs/ros2.md; keys: mapper.outputs.ros_robots.RosRobotSection)")
    msg_serv: MsgServSection = section(MsgServSection, "upstream RayFronts' ROS 2 messaging-service topics "
                                                        "(text queries in, similarity clouds out; docs/ros2.md)")

    def validate(self) -> "RosSection":
        """Refuses a ``ros.robots.<id>`` entry the ROS output cannot use (one line naming the key)."""
        from mapper.outputs.ros_robots import robot_sections

        robot_sections(self.robots)
        return self


# ------------------------------------------------------------------ message builders
def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 → (N,) float32 whose bits are 0x00RRGGBB (PCL's packed rgb)."""
    rgb = np.asarray(rgb, np.uint32).reshape(-1, 3)
    return ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).astype("<u4").view("<f4")


def weight_colour(w: npt.ArrayLike) -> np.ndarray:
    """Weights → (N, 4) RGBA in [0, 1]: blue (lightest) → green → red (heaviest), scaled to the max."""
    w = np.asarray(w, np.float64).reshape(-1)
    a = w / w.max() if len(w) and w.max() > 0 else np.zeros_like(w)
    r = np.clip(2 * a - 1, 0, 1)
    b = np.clip(1 - 2 * a, 0, 1)
    g = 1 - r - b
    return np.stack([r, g, b, np.ones_like(a)], 1)


def ray_markers(types: MsgTypes, frame_id: str, t: float, origin: npt.ArrayLike, direction: npt.ArrayLike,
                weight: npt.ArrayLike, length: float, distro: str) -> Any:
    """MarkerArray: DELETEALL, then one ARROW per ray (points = origin, origin + length·dir)."""
    marker_t: Any = types["visualization_msgs/msg/Marker"]
    vector3, point = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Point"]
    quaternion, colour_rgba = types["geometry_msgs/msg/Quaternion"], types["std_msgs/msg/ColorRGBA"]
    hdr = header_msg(types, frame_id, t)
    pose = types["geometry_msgs/msg/Pose"](position=point(x=0.0, y=0.0, z=0.0),
                                           orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    zero = types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    extra = marker_extra_fields(types, hdr)

    def marker(i: int, action: int, points: Sequence[Any] = (),
               colour: Sequence[float] = (0, 0, 0, 0)) -> Any:
        return marker_t(header=hdr, ns="rays", id=int(i), type=marker_t.ARROW, action=action, pose=pose,
                        scale=vector3(x=0.05, y=0.12, z=0.2),
                        color=colour_rgba(r=float(colour[0]), g=float(colour[1]), b=float(colour[2]),
                                          a=float(colour[3])),
                        lifetime=zero, frame_locked=False, points=list(points), colors=[], text="",
                        mesh_resource="", mesh_use_embedded_materials=False, **extra)

    o = np.asarray(origin, np.float64).reshape(-1, 3)
    tip = o + length * np.asarray(direction, np.float64).reshape(-1, 3)
    cols = weight_colour(weight)
    markers = [marker(0, marker_t.DELETEALL)]
    for i in range(len(o)):
        markers.append(marker(i + 1, marker_t.ADD, (point(x=o[i, 0], y=o[i, 1], z=o[i, 2]),
                                                    point(x=tip[i, 0], y=tip[i, 1], z=tip[i, 2])), cols[i]))
    return types[MARKER_ARRAY](markers=markers)


def query_id(text: str) -> str:
    """Standing-query id for a ROS query text (Zenoh-key and ROS-topic safe)."""
    slug = re.sub(r"[^A-Za-z0-9]+", "_", text.strip()).strip("_").lower()[:48]
    return f"ros_{slug or 'query'}"


def ray_arrays_weighted(m: RayFrontsMap, max_rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray origins, unit directions and weights (subsampled like the rays layer: seeded)."""
    ro, rd, rw = m.ray_geometry()
    o = ro.detach().cpu().numpy().astype(np.float32).reshape(-1, 3)
    d = rd.detach().cpu().numpy().astype(np.float32).reshape(-1, 3)
    w = rw.detach().cpu().numpy().astype(np.float32).reshape(-1)
    if len(o) > max_rays:
        idx = np.sort(np.random.default_rng(0).choice(len(o), max_rays, replace=False))
        o, d, w = o[idx], d[idx], w[idx]
    return o, d, w


# ------------------------------------------------------------------ the output
@dataclass
class _Pub:
    """One ROS publisher: its Zenoh publisher, liveliness token key, 16-byte gid (the token
    key's hash, :func:`common.ros2.keys.entity_gid`) and last sequence number (first sample: 1)."""

    zpub: Any
    token: str
    gid: bytes
    seq: int = 0


class RosOutput:
    """Publishes the shared map's layers and standing queries as ROS 2 topics; adds standing
    queries from ``<prefix>/query_text``. ``start()`` declares everything, ``close()`` undoes it."""

    # state: the mapper.state.MapperState (not imported for the annotation: mapper.service_config,
    # which mapper.state's annotations import, imports this module)
    # search: the mapper.search_server.SearchServer answering the search topics (None: none)
    def __init__(self, state, cfg: RosSection | None = None, search=None) -> None:
        from common.ros2 import cdr
        from common.ros2.keys import check_domain, check_layout, normalize_topic

        self.state = state
        self.cfg = cfg or state.cfg.ros
        check_layout(self.cfg.keys)
        self.domain = check_domain(self.cfg.domain)
        self.cdr = cdr
        self.T = cdr.types(self.cfg.distro)
        p = self.topic_prefix = normalize_topic(self.cfg.topic_prefix)
        self.topics = {"voxels": (f"{p}/voxels", POINTCLOUD2), "frontiers": (f"{p}/frontiers", POINTCLOUD2),
                       "rays": (f"{p}/rays", MARKER_ARRAY)}
        self.query_topic_prefix = f"{p}/query"
        self.query_text_topic = f"{p}/query_text"
        self.session: zenoh.Session | None = None          # set by start()
        self._own_session: zenoh.Session | None = None
        self._pubs: dict[str, _Pub] = {}
        self._entities: list = []
        self._eid = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_version: tuple[int, int] | None = None
        self.published: dict[str, int] = {}
        self.errors = 0
        self.search = None
        self.robots = None
        self.msg_serv = None
        if search is not None:
            from mapper.outputs.ros_robots import RosRobots
            from mapper.outputs.ros_search import RosSearch

            self.search = RosSearch(self, search)
            self.robots = RosRobots(self, search)
            if self.cfg.msg_serv.enabled:
                from mapper.outputs.ros_msg_serv import MsgServ

                self.msg_serv = MsgServ(self, search)

    # -------------------------------------------------------------- zenoh entities
    def _key(self, topic: str, msgtype: str) -> str:
        from common.ros2.keys import publish_key

        return publish_key(topic, msgtype, self.cfg.keys, self.domain, self.cdr.type_hash(msgtype, self.cfg.distro))

    def _token(self, kind: str, topic: str | None = None, msgtype: str | None = None, qos: str = "") -> str:
        """Declare the rmw_zenoh liveliness token of an entity (``qos``: its QoS component,
        "" = rmw_zenoh's defaults); its key ("" in the bridge layout)."""
        from common.ros2.keys import DEFAULT_QOS, RMW_ZENOH, liveliness_token

        if self.cfg.keys != RMW_ZENOH:
            return ""
        self._eid += 1
        assert self.session is not None, "RosOutput.start() opens the session first"
        key = liveliness_token(self.domain, str(self.session.zid()), 0, 0 if kind == "NN" else self._eid, kind,
                               self.cfg.node, topic=topic, msgtype=msgtype,
                               type_hash=self.cdr.type_hash(msgtype, self.cfg.distro) if msgtype else "",
                               qos=qos or DEFAULT_QOS)
        self._entities.append(self.session.liveliness().declare_token(key))
        return key

    def _publisher(self, topic: str, msgtype: str, latched: bool = False) -> _Pub:
        """The publisher of ``topic`` (declared with its token on first use): its own gid and
        sequence counter, as an rmw_zenoh publisher has (docs/key_space.md, ROS 2).

        ``latched``: reliable + transient-local with depth 1 (what Nav2's static layer and
        map_server use), as rmw_zenoh implements it: a Zenoh advanced publisher that caches
        the last sample for late subscribers (rmw_zenoh's transient-local subscriptions are
        advanced subscribers that query that cache), is detectable through liveliness and
        sends sporadic heartbeats (500 ms) for sample-miss detection; its token says
        ``:1:,1:,:,:,,``."""
        from common.ros2.keys import TRANSIENT_LOCAL, entity_gid, qos_component

        pub = self._pubs.get(topic)
        if pub is None:
            key = self._key(topic, msgtype)
            assert self.session is not None, "RosOutput.start() opens the session first"
            zpub: Any                                    # a Publisher or an AdvancedPublisher (_Pub.zpub)
            if latched:
                import zenoh
                from zenoh import ext

                zpub = ext.declare_advanced_publisher(
                    self.session, key, reliability=zenoh.Reliability.RELIABLE, cache=ext.CacheConfig(max_samples=1),
                    publisher_detection=True,
                    # zenoh's stub requires heartbeat too; at runtime either one may be given
                    sample_miss_detection=ext.MissDetectionConfig(sporadic_heartbeat=0.5))  # type: ignore[call-arg]
            else:
                zpub = self.session.declare_publisher(key)
            self._entities.append(zpub)
            token = self._token("MP", topic, msgtype, qos_component(durability=TRANSIENT_LOCAL, depth=1) if latched
                                else "")
            pub = self._pubs[topic] = _Pub(zpub, token, entity_gid(token) if token else bytes(16))
        return pub

    def start(self) -> "RosOutput":
        from common.ros2.keys import subscribe_key

        state = self.state
        if self.cfg.connect:
            from common.zenoh_session import ZenohConfig, open_session

            self._own_session = open_session(ZenohConfig(mode="client", connect=list(self.cfg.connect)),
                                             stop=state.stop, default_mode="client")
        self.session = self._own_session or state.session
        assert self.session is not None and state.keys is not None, "start the mapper (or set ros.connect) first"
        self._token("NN")
        for topic, msgtype in self.topics.values():
            self._publisher(topic, msgtype)
        self._entities.append(self.session.declare_subscriber(
            subscribe_key(self.query_text_topic, self.cfg.keys, self.domain), self._on_query_text))
        self._token("MS", self.query_text_topic, STRING)
        self._entities.append(self.session.declare_subscriber(state.keys.mapper_queries_all, self._on_standing))
        if self.search is not None:
            from mapper.outputs.ros_search import OCCUPANCY_GRID

            for topic, msgtype in self.search.topics.values():
                self._publisher(topic, msgtype, latched=msgtype == OCCUPANCY_GRID)
            self._entities += self.search.start()
            assert self.robots is not None            # made with the search
            self._entities += self.robots.start()
            if self.msg_serv is not None:
                self._entities += self.msg_serv.start()
        if self.cfg.rate_hz > 0:
            self._thread = threading.Thread(target=self._loop, name="mapper-ros", daemon=True)
            self._thread.start()
        log.info("ROS 2 output: %s layout, domain %d, %s, topics %s", self.cfg.keys, self.domain, self.cfg.distro,
                 ", ".join(t for t, _ in self.topics.values()))
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        with self._lock:
            ents, self._entities = self._entities, []
            self._pubs = {}
        undeclare_all(reversed(ents))
        close_quietly(self._own_session)
        self._own_session = None
        self.session = None

    # -------------------------------------------------------------- publishing
    def _put(self, topic: str, msgtype: str, msg, latched: bool = False) -> None:
        """Serialise and publish ``msg`` on ``topic`` (``latched``: see :meth:`_publisher`)."""
        from common.ros2.keys import RMW_ZENOH

        data = self.cdr.serialize(msg, msgtype, self.cfg.distro)
        with self._lock:
            if self.session is None:
                return
            pub = self._publisher(topic, msgtype, latched)
            pub.seq += 1
            att = None
            if self.cfg.keys == RMW_ZENOH:
                att = self.cdr.attachment(pub.seq, time.time_ns(), pub.gid)
            pub.zpub.put(data, attachment=att)
        self.published[topic] = self.published.get(topic, 0) + 1

    def layer_messages(self) -> dict:
        """{topic: (type, message)} for the current map (None before the map exists)."""
        from mapper.service_map import layer_arrays

        state = self.state
        with state.lock:
            if state.map is None:
                return {}
            vox, _ = layer_arrays(state.map, "voxels", state.cfg.layers)
            fr, _ = layer_arrays(state.map, "frontiers", state.cfg.layers)
            o, d, w = ray_arrays_weighted(state.map, self.cfg.max_rays)
        t, T, fid = time.time(), self.T, self.cfg.frame_id
        return {
            self.topics["voxels"][0]: (POINTCLOUD2, pointcloud2(T, fid, t, vox["xyz"], {"rgb": pack_rgb(vox["rgb"])})),
            self.topics["frontiers"][0]: (POINTCLOUD2, pointcloud2(T, fid, t, fr["xyz"])),
            self.topics["rays"][0]: (MARKER_ARRAY, ray_markers(T, fid, t, o, d, w, self.cfg.ray_length,
                                                               self.cfg.distro)),
        }

    def publish_layers(self) -> None:
        for topic, (msgtype, msg) in self.layer_messages().items():
            self._put(topic, msgtype, msg)
        if self.search is not None and self.cfg.costmap_z_band:
            cm = self.search.costmap_message()
            if cm is not None:
                self._put(cm[0], *cm[1], latched=True)
        if self.robots is not None:
            self.robots.update_all()
        if self.msg_serv is not None:
            self.msg_serv.publish()

    def _loop(self) -> None:
        state = self.state
        period = 1.0 / self.cfg.rate_hz
        while not self._stop.wait(period) and not state.stop.is_set():
            ver = (state.version, state.flushed_version)  # a flush changes the map without bumping version
            if state.map is None or ver == self._last_version:
                continue
            try:
                self._last_version = ver
                self.publish_layers()
            except Exception as e:
                self.errors += 1
                state.warn("ros", "ROS 2 layer publishing failed: %s", e)

    def _on_standing(self, sample: zenoh.Sample) -> None:
        """A standing query result (``mapper/queries/<id>``) → ``<prefix>/query/<id>`` PointCloud2."""
        from common.messages import decode_query_result

        try:
            res = decode_query_result(sample.payload.to_bytes())
            qid = res.id or str(sample.key_expr).rsplit("/", 1)[-1]
            msg = pointcloud2(self.T, self.cfg.frame_id, time.time(), res.voxel_xyz,
                              {"score": np.asarray(res.voxel_score, np.float32)})
            self._put(f"{self.query_topic_prefix}/{qid}", POINTCLOUD2, msg)
        except Exception as e:  # never raise out of a Zenoh callback
            self.errors += 1
            self.state.warn("ros", "ROS 2 standing-query output failed: %s", e)

    def _on_query_text(self, sample: zenoh.Sample) -> None:
        """std_msgs/String on ``<prefix>/query_text`` → a standing text query."""
        from common.messages import QueryRequest

        state = self.state
        try:
            msg = self.cdr.deserialize(sample.payload.to_bytes(), STRING)
            text = str(msg.data).strip()
            if not text:
                raise ValueError("empty query text")
            req = QueryRequest(text=text, top_k=int(self.cfg.query_top_k), standing=True, id=query_id(text)).validate()
            state.standing[req.id] = req
            state.standing_due.set()
            log.info("ROS 2: standing query %r from %s (results on %s/%s)", text, self.query_text_topic,
                     self.query_topic_prefix, req.id)
        except Exception as e:
            self.errors += 1
            state.warn("ros-query", "ROS 2 query on %s rejected: %s", self.query_text_topic, e)
