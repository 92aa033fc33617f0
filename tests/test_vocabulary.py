"""``query_client.vocabulary``: request keywords from plain fields (text as typed, or numbers,
give the same request), the search reply's JSON fields, and the settled predicate, each of its
conditions on its own. Pure functions: no mapper."""
from __future__ import annotations

import copy

import pytest

from common.config import ConfigError
from common.search_messages import SearchReply
from query_client.vocabulary import SEARCH_JSON_FIELDS, query_fields, search_fields, search_reply_json, settled


def test_search_fields_take_text_or_numbers_alike():
    as_text = search_fields(["car"], area="0,0,40,40", z_band="0,3", from_xyz="1,2,1.5", threshold=0.6)
    as_numbers = search_fields(["car"], area=[0, 0, 40, 40], z_band=[0, 3], from_xyz=[1, 2, 1.5], threshold=0.6)
    assert as_text == as_numbers
    assert as_text["area"] == [0.0, 0.0, 40.0, 40.0] and as_text["z_band"] == [0.0, 3.0]
    assert as_text["from_xyz"] == [1.0, 2.0, 1.5] and as_text["threshold"] == 0.6
    poly = search_fields(["car"], area="0,0,10,0,10,10")["area"]
    assert poly == [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]
    none = search_fields(["car"], area="", z_band=None, from_xyz="")     # "" = not given (an empty URL field)
    assert "area" not in none and "z_band" not in none and "from_xyz" not in none


@pytest.mark.parametrize("kw, needle", [
    (dict(area="1,2,3"), "--area needs"),
    (dict(area="a,b,c,d"), "--area must be comma-separated numbers"),
    (dict(from_xyz=[1, 2]), "--from needs 3"),
    (dict(z_band="3,1"), "z0 <= z1"),
    (dict(threshold=1.5), "threshold"),
])
def test_search_fields_refuse_bad_input_in_one_line(kw, needle):
    with pytest.raises(ConfigError) as e:
        search_fields(["car"], **kw)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_query_fields():
    assert query_fields("water tower", top_k=3) == {"text": "water tower", "image": None, "top_k": 3}
    for text, top_k, image, needle in [(" ", 5, None, "empty; say what to look for: ?q=x"), ("car", 0, None, "--top-k"),
                                       ("car", 5, "x.png", "not both")]:
        with pytest.raises(ConfigError) as e:
            query_fields(text, image, top_k, example=": ?q=x")
        assert needle in str(e.value)


def test_search_reply_json_has_exactly_the_cli_fields():
    r = SearchReply(id="a", found=[{"id": 1}], frames_mapped=3, map_version=4, timings_ms={"total": 1.0})
    d = search_reply_json(r)
    assert tuple(d) == SEARCH_JSON_FIELDS and d["found"] == [{"id": 1}] and d["frames_mapped"] == 3


def _stats() -> dict:
    return {"frames": {"received": 10, "mapped": 7, "dropped": 2, "rejected_total": 1},
            "robots": {"r0": {"queue": 0}, "r1": {"queue": 0}}, "map_version": 5, "flushed_version": 5}


@pytest.mark.parametrize("change", [
    lambda s: s["frames"].update(received=11),               # a frame on its way: not accounted yet
    lambda s: s["robots"]["r1"].update(queue=1),             # a frame queued
    lambda s: s.update(flushed_version=4),                   # the map not flushed
])
def test_settled_needs_every_condition(change):
    s = _stats()
    assert settled(s) and settled(s, mapped=7, received=10)
    assert not settled(s, mapped=8) and not settled(s, received=11)
    t = copy.deepcopy(s)
    change(t)
    assert not settled(t)


def test_settled_after_a_restore_counts_the_snapshot_frames_as_mapped():
    s = _stats()
    s["frames"].update(received=16, mapped=32, dropped=0, rejected_total=0)   # 16 restored + 16 new
    assert settled(s, mapped=32) and not settled(s, mapped=33)


def test_settled_on_a_shard_counts_the_frames_outside_its_region():
    s = _stats()
    s["frames"].update(received=14)                              # 4 more, all outside this shard's region
    assert not settled(s)
    s["robots"]["r1"]["outside_shard"] = 3
    assert not settled(s)                                        # one still unaccounted for
    s["robots"]["r0"]["outside_shard"] = 1
    assert settled(s, mapped=7, received=14)
