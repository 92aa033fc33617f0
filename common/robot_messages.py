"""Fleet and shard contracts shared by edge, mapper and query client: keys, the per-robot
status message the mapper publishes, the world_from_robot request, and the shard info a
mapper attaches to its query replies.

Keys (under the deployment prefix, next to ``common.keys``)::

    <p>/mapper/robots/<robot>/status            mapper publishes: what it does with the robot's
                                                frames (accepted / pending / refused / evicted,
                                                why, counts, rates, advised publish rate)
    <p>/mapper/robots/<robot>/world_from_robot  mapper queryable: get = the robot's transform;
                                                get with a payload = set it

The *edge's own* state (starting / running / refused / failed) is on
``<p>/robots/<robot>/edge_status`` (``common.keys.KeySpace.edge_status``); the two are
distinct: the edge says what it is doing, the mapper what it does with its frames. With
several mapper shards each publishes the status of the robots whose frames reach it, with
its shard name in the body.

Shards answer ``<p>/mapper/query`` together: one Zenoh ``get`` reaches every shard's
queryable; each reply carries, as its Zenoh *attachment*, :func:`encode_shard_info` (shard
name, the map's minimum score and the search-volume parameters) so the client can merge
the answers (``query_client.merge``).
"""
from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Sequence

from common.keys import KeySpace, check_id
from common.wire import WireError, decode_message, encode_message

if TYPE_CHECKING:
    import numpy as np

SCHEMA_ROBOT_STATUS = "rayfronts.robot_status"
SCHEMA_ROBOT_TRANSFORM = "rayfronts.robot_transform"
VERSION = 1
ROBOT_STATES = ("pending", "accepted", "refused", "evicted")
MAX_REASON_CHARS = 2000


class FleetMessageError(ValueError):
    """A status / transform message that does not decode or validate."""


# ------------------------------------------------------------------ keys
def robot_status_key(keys: KeySpace, robot: str) -> str:
    return f"{keys.prefix}/mapper/robots/{check_id(robot)}/status"


def robot_status_all(keys: KeySpace) -> str:
    return f"{keys.prefix}/mapper/robots/*/status"


def robot_transform_key(keys: KeySpace, robot: str) -> str:
    return f"{keys.prefix}/mapper/robots/{check_id(robot)}/world_from_robot"


def robot_transform_all(keys: KeySpace) -> str:
    return f"{keys.prefix}/mapper/robots/*/world_from_robot"


def robot_from_mapper_key(keys: KeySpace, key: object) -> str | None:
    """Robot id of a ``<p>/mapper/robots/<robot>/<leaf>`` key, else None."""
    from common.keys import is_valid_id

    s = str(key)
    root = f"{keys.prefix}/mapper/robots/"
    if not s.startswith(root):
        return None
    parts = s[len(root):].split("/")
    return parts[0] if len(parts) == 2 and is_valid_id(parts[0]) else None


# ------------------------------------------------------------------ messages
def _decode(data: bytes | bytearray | memoryview, schema: str) -> dict:
    try:
        got, v, body = decode_message(bytes(data))
    except WireError as e:
        raise FleetMessageError(f"{schema}: {e}") from None
    if got == "rayfronts.error":
        raise FleetMessageError(f"remote error: {body.get('error', '?') if isinstance(body, dict) else body}")
    if got != schema or v != VERSION or not isinstance(body, dict):
        raise FleetMessageError(f"expected {schema} v{VERSION}, got {got!r} v{v!r}")
    return body


def encode_robot_status(status: dict) -> bytes:
    """The body of ``mapper.robot_registry.robot_status`` (numbers, strings, a dict of reject counts)."""
    if status.get("state") not in ROBOT_STATES:
        raise FleetMessageError(f"robot state must be one of {ROBOT_STATES}, got {status.get('state')!r}")
    body = dict(status)
    body["reason"] = str(body.get("reason", ""))[:MAX_REASON_CHARS]
    return encode_message(SCHEMA_ROBOT_STATUS, VERSION, body)


def decode_robot_status(data: bytes | bytearray | memoryview) -> dict:
    """Inverse of :func:`encode_robot_status` (validated)."""
    body = _decode(data, SCHEMA_ROBOT_STATUS)
    if body.get("state") not in ROBOT_STATES:
        raise FleetMessageError(f"{SCHEMA_ROBOT_STATUS}: unknown state {body.get('state')!r}")
    if not isinstance(body.get("robot"), str) or not isinstance(body.get("reason", ""), str):
        raise FleetMessageError(f"{SCHEMA_ROBOT_STATUS}: needs 'robot' and 'reason' strings")
    for k in ("received", "mapped", "dropped"):
        v = body.get(k, 0)
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise FleetMessageError(f"{SCHEMA_ROBOT_STATUS}: '{k}' must be a count, got {v!r}")
    a = body.get("advised_hz")
    if a is not None and (isinstance(a, bool) or not isinstance(a, (int, float)) or not math.isfinite(a) or a < 0):
        raise FleetMessageError(f"{SCHEMA_ROBOT_STATUS}: bad advised_hz {a!r}")
    return body


def encode_transform_request(world_from_robot: np.ndarray | Sequence | None = None) -> bytes:
    """Set (16 numbers, row-major) or, with None, only read a robot's transform."""
    body: dict = {}
    if world_from_robot is not None:
        vals = [float(v) for v in (world_from_robot.reshape(-1).tolist() if hasattr(world_from_robot, "reshape")
                                   else _flatten(world_from_robot))]
        if len(vals) != 16:
            raise FleetMessageError(f"world_from_robot needs 16 numbers, got {len(vals)}")
        body["world_from_robot"] = vals
    return encode_message(SCHEMA_ROBOT_TRANSFORM, VERSION, body)


def _flatten(v: Sequence) -> list:
    out = []
    for x in v:
        out.extend(_flatten(x) if isinstance(x, (list, tuple)) else [x])
    return out


def decode_transform_request(data: bytes | bytearray | memoryview) -> list[float] | None:
    """→ the 16 numbers to set, or None (a read)."""
    body = _decode(data, SCHEMA_ROBOT_TRANSFORM)
    v = body.get("world_from_robot")
    if v is None:
        return None
    if not isinstance(v, list) or len(v) != 16 or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise FleetMessageError(f"{SCHEMA_ROBOT_TRANSFORM}: 'world_from_robot' must be 16 numbers")
    return [float(x) for x in v]


def encode_transform_reply(robot: str, world_from_robot: Sequence[float] | None) -> bytes:
    """``world_from_robot``: 16 numbers or None (identity: the robot has none)."""
    return encode_message(SCHEMA_ROBOT_TRANSFORM, VERSION,
                          {"robot": robot, "world_from_robot": None if world_from_robot is None
                           else [float(x) for x in world_from_robot]})


def decode_transform_reply(data: bytes | bytearray | memoryview) -> list[float] | None:
    """→ the robot's 16 numbers (row-major world_from_robot), or None (identity)."""
    body = _decode(data, SCHEMA_ROBOT_TRANSFORM)
    v = body.get("world_from_robot")
    if v is not None and (not isinstance(v, list) or len(v) != 16):
        raise FleetMessageError(f"{SCHEMA_ROBOT_TRANSFORM}: bad reply {v!r}")
    return v


# ------------------------------------------------------------------ shard info
SHARD_INFO_KEYS = ("shard", "score_min", "ray_score_min", "half_angle_deg", "search_range_m", "search_cell_m",
                   "search_samples", "search_rays", "cluster_rel_score", "vox_size", "region", "tile_m", "tiles",
                   "robots")


def encode_shard_info(info: dict) -> bytes:
    """Small JSON object attached to a shard's query reply (see module doc)."""
    return json.dumps({k: info[k] for k in SHARD_INFO_KEYS if k in info}).encode()


def decode_shard_info(data: bytes | bytearray | memoryview | None) -> dict:
    """{} for a reply without (valid) shard info (an older or unsharded mapper)."""
    if not data:
        return {}
    try:
        d = json.loads(bytes(data).decode())
    except (ValueError, UnicodeDecodeError):
        return {}
    return {k: d[k] for k in SHARD_INFO_KEYS if k in d} if isinstance(d, dict) else {}
