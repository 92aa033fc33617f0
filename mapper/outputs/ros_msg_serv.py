"""Drop-in for upstream RayFronts' ROS 2 messaging service (``ros.msg_serv.enabled``; the
mapping from their topics to ours is in docs/ros2.md): their subscribers and query senders
work unchanged. Part of the ROS 2 output (:mod:`mapper.outputs.ros`); similarities come
from the mapper's search service (:meth:`mapper.search_server.SearchServer.similarities`).

* ``text_query_topic`` (subscribed; default ``/rayfronts/msg_serv/new_text_query``) —
  std_msgs/String: one text query; a text already asked is ignored (upstream keeps a
  history); at most ``max_queries`` (then one-line error, counted);
* under ``topic_prefix`` (default ``/rayfronts/msg_serv``), sensor_msgs/PointCloud2 (float32
  fields), frame ``frame_id`` (default ``map``; our world: z up, metres — upstream publishes
  its internal RDF world under that name), each published only while some subscriber
  matches it (the Zenoh publisher's matching status), after map changes and new queries:

  * ``<prefix>/voxels_sim/q<i>_<label>``: x, y, z, sim — query ``i`` (0-based, in the order
    asked), ``label`` its text with every character outside ``[A-Za-z0-9_]`` as ``_``;
  * ``<prefix>/voxels_sim/all``: x, y, z, sim_0 … sim_{Q-1};
  * ``<prefix>/rays_sim/q<i>_<label>``: x, y, z (the ray's frontier), theta, phi (degrees:
    azimuth from +x toward +y, inclination from +z), sim; ``<prefix>/rays_sim/all`` likewise;
  * the same clouds under ``voxel_similarity/`` and ``ray_similarity/`` (``voxel_alias``,
    ``ray_alias``), each also published only while subscribed;
  * ``<prefix>/frontiers``: x, y, z;

  points whose best similarity over the queries is below ``publish_threshold`` are left out;
  ``sim`` is the softmax across the queries at ``search.temperature`` (upstream's
  ``compute_prob``; a single query scores 1 everywhere, as upstream's) or, with
  ``softmax=false``, the cosine.
"""
from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass

import numpy as np

from common.config import field_
from mapper.outputs.ros_markers import POINTCLOUD2

log = logging.getLogger("rayfronts.mapper")

STRING = "std_msgs/msg/String"


@dataclass
class MsgServSection:
    enabled: bool = field_(False, "serve upstream RayFronts' ROS 2 messaging-service topics (docs/ros2.md)")
    text_query_topic: str = field_("/rayfronts/msg_serv/new_text_query", "std_msgs/String text queries in")
    topic_prefix: str = field_("/rayfronts/msg_serv", "prefix of the similarity clouds (voxels_sim/, rays_sim/)")
    voxel_topic: str = field_("voxels_sim", "sub-namespace of the voxel clouds (upstream: voxels_sim)")
    ray_topic: str = field_("rays_sim", "sub-namespace of the ray clouds (upstream: rays_sim)")
    voxel_alias: str = field_("voxel_similarity", "a second sub-namespace serving the same voxel clouds "
                                                  "(\"\" = none)")
    ray_alias: str = field_("ray_similarity", "a second sub-namespace serving the same ray clouds (\"\" = none)")
    frame_id: str = field_("map", "header.frame_id of the clouds")
    publish_threshold: float = field_(0.0, "points whose best similarity is below this are left out "
                                           "(upstream's query_publish_threshold)")
    softmax: bool = field_(True, "sim = softmax across the queries (upstream's compute_prob); false = cosine")
    max_queries: int = field_(32, "text queries kept; more are refused (one line, counted)")


def label_of(text: str) -> str:
    """A query text as a topic name chunk: every character outside ``[A-Za-z0-9_]`` → ``_``."""
    return re.sub(r"[^A-Za-z0-9_]", "_", text) or "_"


def angles_deg(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (N, 3) → (theta: azimuth from +x toward +y, phi: inclination from +z), degrees."""
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    theta = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    phi = np.degrees(np.arccos(np.clip(d[:, 2], -1.0, 1.0)))
    return theta.astype(np.float32), phi.astype(np.float32)


class MsgServ:
    """The messaging-service topics of a :class:`mapper.outputs.ros.RosOutput` (``out``),
    answered by the search service ``search``."""

    def __init__(self, out, search) -> None:
        from common.ros2.keys import normalize_topic

        self.out, self.search = out, search
        self.cfg: MsgServSection = out.cfg.msg_serv
        self.query_topic = normalize_topic(self.cfg.text_query_topic)
        self.prefix = normalize_topic(self.cfg.topic_prefix)
        self.queries: list[str] = []
        self.rejected = 0
        self.last_error = ""
        self._lock = threading.Lock()

    def start(self) -> list:
        """Subscribe the text queries; returns the Zenoh entities."""
        from common.ros2.keys import subscribe_key

        o = self.out
        ents = [o.session.declare_subscriber(subscribe_key(self.query_topic, o.cfg.keys, o.domain), self._on_text)]
        o._token("MS", self.query_topic, STRING)
        o._publisher(f"{self.prefix}/frontiers", POINTCLOUD2)
        return ents

    def _on_text(self, sample) -> None:
        """std_msgs/String → a new query (then everything is published in a thread)."""
        o = self.out
        try:
            text = str(o.cdr.deserialize(sample.payload.to_bytes(), STRING).data).strip()
            if not text:
                raise ValueError("empty query text")
            with self._lock:
                if text in self.queries:
                    return
                if len(self.queries) >= self.cfg.max_queries:
                    raise ValueError(f"{len(self.queries)} queries already (ros.msg_serv.max_queries); restart the "
                                     f"mapper or raise the limit")
                self.queries.append(text)
                i = len(self.queries) - 1
            for sub in self.subs():                                  # declared now: subscribers can match
                o._publisher(f"{self.prefix}/{sub}/q{i}_{label_of(text)}", POINTCLOUD2)
            log.info("ROS 2 messaging service: query q%d %r", i, text)
        except Exception as e:
            self.rejected += 1
            o.errors += 1
            self.last_error = f"ROS 2 text query on {self.query_topic} rejected: {' '.join(str(e).split())}"
            o.state.warn("ros-msg-serv", "%s", self.last_error)
            return
        threading.Thread(target=self.publish, name="mapper-ros-msgserv", daemon=True).start()

    def subs(self, kind: str = "") -> list[str]:
        """The sub-namespaces of the voxel (``kind="voxel"``), ray (``"ray"``) or all clouds:
        upstream's names and their aliases."""
        c = self.cfg
        names = {"voxel": [c.voxel_topic, c.voxel_alias], "ray": [c.ray_topic, c.ray_alias]}
        chosen = names[kind] if kind else names["voxel"] + names["ray"]
        return [n for n in dict.fromkeys(chosen) if n]

    def topics(self) -> list[str]:
        """Every similarity topic of the current queries (``all`` included)."""
        out = []
        for sub in self.subs():
            out.append(f"{self.prefix}/{sub}/all")
            out += [f"{self.prefix}/{sub}/q{i}_{label_of(t)}" for i, t in enumerate(self.queries)]
        return out

    def _wanted(self, topic: str) -> bool:
        """Whether some subscriber matches ``topic``'s publisher (declared here on first use)."""
        pub = self.out._publisher(topic, POINTCLOUD2)
        try:
            return bool(pub.zpub.matching_status.matching)
        except Exception:       # a publisher without matching status: publish
            return True

    def messages(self) -> dict:
        """{topic: (type, PointCloud2)} of every wanted topic (nothing wanted: {})."""
        from mapper.outputs.ros_markers import pointcloud2
        from mapper.service_map import layer_arrays

        o, c = self.out, self.cfg
        out: dict = {}
        st = o.state
        if self._wanted(f"{self.prefix}/frontiers") and st.map is not None:
            with st.lock:
                fr, _ = layer_arrays(st.map, "frontiers", st.cfg.layers)
            out[f"{self.prefix}/frontiers"] = (POINTCLOUD2, pointcloud2(o.T, c.frame_id, time.time(), fr["xyz"]))
        with self._lock:
            texts = list(self.queries)
        wanted = {t for t in self.topics() if self._wanted(t)} if texts else set()
        if not wanted:
            return out
        vxyz, vs, ro, rd, rs = self.search.similarities(texts, c.softmax)
        theta, phi = angles_deg(rd)
        for sub in self.subs("voxel"):
            out.update(self._clouds(sub, vxyz, vs, {}, texts, wanted))
        for sub in self.subs("ray"):
            out.update(self._clouds(sub, ro, rs, {"theta": theta, "phi": phi}, texts, wanted))
        return out

    def _clouds(self, sub: str, xyz: np.ndarray, sim: np.ndarray, extra: dict, texts: list[str],
                wanted: set[str]) -> dict:
        """The wanted clouds of ``<prefix>/<sub>/``: points (N, 3), scores (Q, N), extra fields
        (name → (N,)) before ``sim``; points below ``publish_threshold`` left out."""
        from mapper.outputs.ros_markers import pointcloud2

        o, c, t = self.out, self.cfg, time.time()
        keep = sim.max(0) >= c.publish_threshold if sim.shape[1] else np.zeros(0, bool)
        kx = np.asarray(xyz).reshape(-1, 3)[keep]
        ke = {k: v[keep] for k, v in extra.items()}
        out = {}
        if f"{self.prefix}/{sub}/all" in wanted:
            out[f"{self.prefix}/{sub}/all"] = (POINTCLOUD2, pointcloud2(
                o.T, c.frame_id, t, kx, {**ke, **{f"sim_{i}": sim[i, keep] for i in range(len(texts))}}))
        for i, text in enumerate(texts):
            topic = f"{self.prefix}/{sub}/q{i}_{label_of(text)}"
            if topic in wanted:
                out[topic] = (POINTCLOUD2, pointcloud2(o.T, c.frame_id, t, kx, {**ke, "sim": sim[i, keep]}))
        return out

    def publish(self) -> None:
        """Publish every wanted topic (the output's thread after map changes, or after a query)."""
        from common.messages import MessageError

        try:
            for topic, (msgtype, msg) in self.messages().items():
                self.out._put(topic, msgtype, msg)
        except MessageError as e:       # an empty map: published once it has frames
            log.debug("ROS 2 messaging service: %s", e)
        except Exception as e:
            self.out.errors += 1
            self.out.state.warn("ros-msg-serv-out", "ROS 2 messaging-service output failed: %s", e)
