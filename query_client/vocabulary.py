"""The client's vocabulary, one home for what ``rayfronts query`` / ``rayfronts search``, the
console, the demo, the benchmarks and the tests say alike: a query's and a search's keywords from
plain fields (no argparse: text as typed on a command line or in a URL, or numbers), a search
reply as its JSON object, and whether the mapper has settled.

World frame, metres, z up. Bad fields raise ``common.config.ConfigError`` with one line naming
the field by its ``rayfronts`` option (``--area``, ``--top-k``, ...)."""
from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Sequence

from common.config import ConfigError

if TYPE_CHECKING:
    from common.fleet_messages import FleetSearchReply
    from common.search_messages import SearchReply

#: the fields of a search reply's JSON object (``rayfronts search --json``, the console's /api/search)
SEARCH_JSON_FIELDS = ("found", "look_next", "beyond", "events", "frames_mapped", "map_version", "timings_ms",
                      "missing_shards")


def _text(value: str | Sequence[float]) -> str:
    return value if isinstance(value, str) else ",".join(repr(float(x)) for x in value)


def numbers(value: str | Sequence[float], n: int | None, what: str) -> list[float]:
    """``value`` ("x,y,z" text or a sequence of numbers) as floats; ``n``: how many it needs."""
    text = _text(value)
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise ConfigError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if n is not None and len(v) != n:
        raise ConfigError(f"{what} needs {n} comma-separated numbers, got {text!r}")
    return v


def _given(value: str | Sequence[float] | None) -> bool:
    return value is not None and value != ""


def search_fields(targets: Sequence[str], *, background: Sequence[str] | None = None, threshold: float = 0.5,
                  max_instances: int = 10, max_goals: int = 5, area: str | Sequence[float] | None = None,
                  z_band: str | Sequence[float] | None = None,
                  from_xyz: str | Sequence[float] | None = None) -> dict[str, Any]:
    """``Client.search`` / ``Client.watch_search`` keywords (besides ``targets``) from plain
    fields, checked as the mapper would check the request. ``area``: a box x0,y0,x1,y1 or a
    polygon x0,y0,x1,y1,x2,y2,... (>= 3 vertices); ``z_band`` z0,z1; ``from_xyz`` the robot's
    x,y,z; each as text or numbers, ``None`` or "" = not given."""
    from common.messages import MessageError
    from query_client.search import PlannerCalls

    kw: dict[str, Any] = dict(background=list(background) if background else None, threshold=threshold,
                              max_instances=max_instances, max_goals=max_goals)
    if area is not None and _given(area):
        a = numbers(area, None, "--area")
        if len(a) == 4:
            kw["area"] = a
        elif len(a) >= 6 and len(a) % 2 == 0:
            kw["area"] = [a[i:i + 2] for i in range(0, len(a), 2)]
        else:
            raise ConfigError(f"--area needs x0,y0,x1,y1 (a box) or >= 3 x,y vertices, got {_text(area)!r}")
    if z_band is not None and _given(z_band):
        kw["z_band"] = numbers(z_band, 2, "--z-band")
    if from_xyz is not None and _given(from_xyz):
        kw["from_xyz"] = numbers(from_xyz, 3, "--from")
    try:
        PlannerCalls.search_request(list(targets), **kw)
    except MessageError as e:
        raise ConfigError(str(e)) from None
    return kw


def fleet_robots(text: str | Sequence[str]) -> list[str]:
    """The robots of ``--fleet``: comma-separated ids ("all" = every robot present on the
    mapper: returned as []); an empty fleet or a bad id is a one-line ``ConfigError``."""
    from common.keys import InvalidKey, check_id

    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else list(text))]
    items = [t for t in items if t]
    if not items:
        raise ConfigError("--fleet is empty: name the robots (--fleet r1,r2,r3) or say --fleet all")
    if items == ["all"]:
        return []
    try:
        return [check_id(t, "robot id in --fleet") for t in items]
    except InvalidKey as e:
        raise ConfigError(str(e)) from None


def fleet_fields(robots: str | Sequence[str], targets: Sequence[str], *, target_count: int = 1,
                 footprint_m: float = 0.0, from_xyz: str | Sequence[float] | None = None,
                 max_goals: int | None = None, **search: Any) -> dict[str, Any]:
    """``Client.fleet_search`` / ``Client.watch_fleet_search`` keywords (besides ``targets``):
    :func:`search_fields`' (``search``: background, threshold, max_instances, area, z_band)
    plus ``robots`` (:func:`fleet_robots`), ``target_count``, ``footprint_m`` and ``max_goals``
    (look-next candidates, None = 20); ``from_xyz`` is refused (each robot's own position is used)."""
    from common.fleet_messages import DEFAULT_CANDIDATES
    from common.messages import MessageError
    from query_client.fleet_search import FleetCalls

    if from_xyz is not None and _given(from_xyz):
        raise ConfigError("--from has no meaning with --fleet: each robot's own position is used")
    kw = search_fields(targets, **search)
    kw.update(robots=fleet_robots(robots), target_count=target_count, footprint_m=footprint_m,
              max_goals=DEFAULT_CANDIDATES if max_goals is None else max_goals)
    try:
        FleetCalls.fleet_search_request(list(targets), **kw)
    except MessageError as e:
        raise ConfigError(str(e)) from None
    return kw


def query_fields(text: str | None, image: str | None = None, top_k: int = 5, *,
                 example: str = ', e.g. rayfronts query "water tower"') -> dict[str, Any]:
    """``Client.query`` / ``Client.watch`` keywords from plain fields: a query ``text`` or an
    ``image`` file path (not both; neither is for the caller to refuse; the file itself is
    checked by ``Client.query`` or the caller's ``read_query_image``), ``top_k`` >= 1 answers
    per kind; ``example`` ends the message of an empty text (how to give one)."""
    if text is not None and not text.strip():
        raise ConfigError(f"the query text is empty; say what to look for{example}")
    if top_k < 1:
        raise ConfigError(f"--top-k must be >= 1 (got {top_k})")
    if text is not None and image is not None:
        raise ConfigError("give either a query text or --image PATH, not both")
    return {"text": text, "image": image, "top_k": int(top_k)}


def search_reply_json(r: SearchReply) -> dict[str, Any]:
    """A ``SearchReply`` as the JSON object ``rayfronts search --json`` prints (plain types)."""
    d = r.to_dict()
    return {k: d[k] for k in SEARCH_JSON_FIELDS}


def search_reply_text(r: SearchReply) -> str:
    """:func:`search_reply_json` as one line of JSON text."""
    return json.dumps(search_reply_json(r))


def fleet_reply_json(r: FleetSearchReply) -> dict[str, Any]:
    """A ``FleetSearchReply`` as the JSON object ``rayfronts search --fleet ... --json`` prints
    (plain types; fields ``common.fleet_messages.FLEET_JSON_FIELDS``)."""
    return r.to_dict()


def fleet_reply_text(r: FleetSearchReply) -> str:
    """:func:`fleet_reply_json` as one line of JSON text."""
    return json.dumps(fleet_reply_json(r))


def _outside_shard(stats: dict) -> int:
    """Frames a shard received outside its region (its robots' ``outside_shard``; 0 unsharded)."""
    return sum(int(r.get("outside_shard", 0)) for r in stats["robots"].values())


def settled(stats: dict, mapped: int = 1, received: int = 0) -> bool:
    """Whether a mapper's ``stats`` (``Client.stats``) say it has settled: every frame it received
    mapped, dropped, rejected or (a shard) outside its region, no robot queue holding a frame,
    the map flushed (``flushed_version == map_version``), at least ``mapped`` frames mapped and
    ``received`` received. ``mapped`` counts the frames of a restored snapshot too, ``received``
    only this process's: the accounting is ``mapped + dropped + rejected + outside_shard >=
    received``."""
    f = stats["frames"]
    return (f["mapped"] >= mapped and f["received"] >= received
            and f["mapped"] + f["dropped"] + f["rejected_total"] + _outside_shard(stats) >= f["received"]
            and not any(r["queue"] for r in stats["robots"].values())
            and stats["flushed_version"] == stats["map_version"])


def settled_line(stats: dict) -> str:
    """The counts :func:`settled` looks at, as one line (for a timeout's message)."""
    f = stats["frames"]
    queued = sum(r["queue"] for r in stats["robots"].values())
    return (f"received {f['received']}, mapped {f['mapped']}, dropped {f['dropped']}, rejected "
            f"{f['rejected_total']}, outside shard {_outside_shard(stats)}, queued {queued}, map version "
            f"{stats['map_version']} flushed {stats['flushed_version']}")
