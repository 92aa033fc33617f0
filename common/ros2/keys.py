"""Zenoh keys for ROS 2 topics (rmw_zenoh and bridge layouts) and rmw_zenoh graph tokens.

See :mod:`common.ros2` for the layouts. Pure string functions, no Zenoh import.
"""
from __future__ import annotations

import re

RMW_ZENOH = "rmw_zenoh"
BRIDGE = "bridge"
LAYOUTS = (RMW_ZENOH, BRIDGE)
ADMIN_SPACE = "@ros2_lv"
TYPE_HASH_NONE = "TypeHashNotSupported"
#: rmw_zenoh's QoS component with every policy at its default (reliable, volatile,
#: keep-last, default depth, no deadline / lifespan, automatic liveliness).
DEFAULT_QOS = "::,:,:,:,,"
#: rmw's QoS policy values (``rmw/types.h``), as rmw_zenoh writes them in a token's QoS component
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
#: rmw_zenoh's default profile (its ``QoS::default_qos``): reliable, volatile, keep-last 42
DEFAULT_DEPTH = 42
ENTITY_KINDS = {"NN": "node", "MP": "publisher", "MS": "subscription", "SS": "service", "SC": "client"}

_BAD = re.compile(r"[*$?#\s]")


class RosKeyError(ValueError):
    """A topic, type or key cannot be mapped (the message says which and why)."""


def check_layout(layout: str) -> str:
    if layout not in LAYOUTS:
        raise RosKeyError(f"ROS key layout {layout!r} is not one of {', '.join(LAYOUTS)}")
    return layout


def check_domain(domain: int | str) -> int:
    d = int(domain)
    if not 0 <= d <= 232:
        raise RosKeyError(f"ROS domain id must be in 0..232, got {domain}")
    return d


def topic_chunks(topic: str) -> str:
    """``/camera/color/image_raw`` → ``camera/color/image_raw`` (validated)."""
    t = str(topic).strip()
    body = t.lstrip("/")
    if not body or _BAD.search(body) or "//" in body or body.endswith("/"):
        raise RosKeyError(f"not a usable ROS topic name: {topic!r}")
    return body


def normalize_topic(topic: str) -> str:
    """The ROS topic with exactly one leading slash."""
    return "/" + topic_chunks(topic)


def dds_type(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_`` (rmw_zenoh's type name)."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise RosKeyError(f"not a ROS message type: {msgtype!r} (expected pkg/msg/Name)")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def ros_type(dds: str) -> str | None:
    """``sensor_msgs::msg::dds_::Image_`` → ``sensor_msgs/msg/Image`` (None if not of that form)."""
    parts = dds.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_") and len(parts[3]) > 1:
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    if len(parts) == 3 and parts[2]:  # some tools omit the dds_ level
        return f"{parts[0]}/{parts[1]}/{parts[2].rstrip('_')}"
    return None


def subscribe_key(topic: str, layout: str, domain: int = 0) -> str:
    """Key expression matching every sample of ``topic`` (any type, any type hash)."""
    body = topic_chunks(topic)
    if check_layout(layout) == BRIDGE:
        return body
    return f"{check_domain(domain)}/{body}/*/*"


def publish_key(topic: str, msgtype: str, layout: str, domain: int = 0, type_hash: str = TYPE_HASH_NONE) -> str:
    """The data key a publisher of ``topic`` (ROS type ``msgtype``) puts samples on in ``layout``."""
    body = topic_chunks(topic)
    if check_layout(layout) == BRIDGE:
        return body
    return f"{check_domain(domain)}/{body}/{dds_type(msgtype)}/{type_hash or TYPE_HASH_NONE}"


def parse_key(key: str, layout: str, domain: int = 0) -> tuple[str, str | None, str | None]:
    """A data key → ``(topic with leading slash, ROS type or None, type hash or None)``."""
    key = str(key)
    if check_layout(layout) == BRIDGE:
        return "/" + key.strip("/"), None, None
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != str(check_domain(domain)):
        raise RosKeyError(f"{key!r} is not an rmw_zenoh data key of domain {domain}")
    return "/" + "/".join(parts[1:-2]), ros_type(parts[-2]), parts[-1]


def qos_component(reliability: int = RELIABLE, durability: int = VOLATILE, history: int = KEEP_LAST,
                  depth: int = DEFAULT_DEPTH) -> str:
    """rmw_zenoh's QoS component of a topic token:
    ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>``,
    each policy written as its rmw enum value only where it differs from rmw_zenoh's default
    profile (reliable, volatile, keep-last 42; no deadline / lifespan, automatic liveliness), else
    empty. ``qos_component()`` is :data:`DEFAULT_QOS`; Nav2's map topics (reliable,
    transient-local, depth 1) are ``":1:,1:,:,:,,"``."""
    def part(value: int, default: int) -> str:
        return "" if int(value) == default else str(int(value))

    return (f"{part(reliability, RELIABLE)}:{part(durability, VOLATILE)}:{part(history, KEEP_LAST)},"
            f"{part(depth, DEFAULT_DEPTH)}:,:,:,,")


def parse_qos(component: str) -> dict:
    """Inverse of :func:`qos_component` for the policies it writes: ``{"reliability",
    "durability", "history", "depth"}`` as rmw enum values (defaults filled in); RosKeyError
    when it is not of that form."""
    parts = str(component).split(":")
    hist = parts[2].split(",") if len(parts) == 6 else []
    if len(hist) != 2:
        raise RosKeyError(f"not an rmw_zenoh QoS component: {component!r}")
    try:
        return {"reliability": int(parts[0] or RELIABLE), "durability": int(parts[1] or VOLATILE),
                "history": int(hist[0] or KEEP_LAST), "depth": int(hist[1] or DEFAULT_DEPTH)}
    except ValueError:
        raise RosKeyError(f"not an rmw_zenoh QoS component: {component!r}") from None


# ------------------------------------------------------------------ graph tokens
def mangle(name: str) -> str:
    """A name as one key chunk: ``/`` → ``%``; empty → ``%``."""
    return name.replace("/", "%") if name else "%"


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


def liveliness_token(domain: int, zid: str, nid: int, eid: int, kind: str, node: str, namespace: str = "/",
                     enclave: str = "/", topic: str | None = None, msgtype: str | None = None,
                     type_hash: str = TYPE_HASH_NONE, qos: str = DEFAULT_QOS) -> str:
    """The rmw_zenoh liveliness key of a node (``NN``) or a topic entity (``MP``/``MS``)."""
    if kind not in ENTITY_KINDS:
        raise RosKeyError(f"entity kind {kind!r} is not one of {', '.join(ENTITY_KINDS)}")
    parts = [ADMIN_SPACE, str(check_domain(domain)), str(zid), str(int(nid)), str(int(eid)), kind,
             mangle(enclave), mangle(namespace), mangle(node)]
    if kind != "NN":
        if not topic or not msgtype:
            raise RosKeyError(f"a {ENTITY_KINDS[kind]} token needs a topic and a type")
        parts += [mangle(normalize_topic(topic)), dds_type(msgtype), type_hash or TYPE_HASH_NONE, qos]
    return "/".join(parts)


def parse_liveliness(key: str) -> dict | None:
    """An rmw_zenoh liveliness key → dict (kind, domain, node, namespace, topic, type, type_hash,
    qos), or None if it is not one."""
    parts = str(key).split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or parts[5] not in ENTITY_KINDS:
        return None
    try:
        domain = int(parts[1])
    except ValueError:
        return None
    out = {"domain": domain, "zid": parts[2], "kind": ENTITY_KINDS[parts[5]], "enclave": demangle(parts[6]),
           "namespace": demangle(parts[7]), "node": demangle(parts[8])}
    if len(parts) >= 12:
        out["topic"] = demangle(parts[9])
        out["type"] = ros_type(parts[10]) or parts[10]
        out["type_hash"] = parts[11]
        out["qos"] = "/".join(parts[12:])
    return out


def entity_gid(liveliness_key: str) -> bytes:
    """The 16-byte gid rmw_zenoh gives an entity: the 128-bit XXH3 hash (seed 0) of its
    liveliness key (:func:`liveliness_token`), low 64 bits then high 64 bits, each little
    endian. Subscribers tell publishers apart by it (the attachment's gid; docs/key_space.md, ROS 2)."""
    try:
        import xxhash
    except ImportError as e:
        raise RosKeyError(f"rmw_zenoh gids need the 'xxhash' package (pip install 'rayfronts-zenoh[ros]'): {e}") \
            from None
    h = xxhash.xxh3_128(str(liveliness_key).encode()).intdigest()
    return (h & 0xFFFF_FFFF_FFFF_FFFF).to_bytes(8, "little") + (h >> 64).to_bytes(8, "little")
