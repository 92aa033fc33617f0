"""Leases and caps of standing queries and searches (``mapper.leases``): the unit, the
message fields, and a real mapper process whose standing requests end when their client is
gone, are capped per client and in total with one-line errors, and are snapshotted only while
live. Also the one-line error of a text search the mapper cannot embed."""
from __future__ import annotations

import base64
import json
import time
from pathlib import Path

import pytest

from common.messages import MessageError, QueryRequest, decode_query_request, encode_query_request
from common.search_messages import SearchRequest, decode_search_reply, decode_search_request, encode_search_request
from mapper.leases import Leases


class _Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_leases_expire_renew_and_cap():
    clock = _Clock()
    ls = Leases("standing search", "search", default_s=10.0, max_total=3, max_per_client=2, clock=clock)
    ls.admit("a", "alice", 0.0, held=0)             # 0 = the default lease (10 s)
    ls.admit("b", "alice", 4.0, held=1)
    ls.admit("a", "alice", 0.0, held=2)             # registering again is not one more
    with pytest.raises(MessageError, match=r"for client 'alice' \(2, limit search.max_standing_per_client=2\)") as e:
        ls.admit("c", "alice", 0.0, held=2)
    assert "\n" not in str(e.value)
    ls.admit("c", "bob", 0.0, held=2)
    with pytest.raises(MessageError, match=r"on this mapper \(3, limit search.max_standing=3\)"):
        ls.admit("d", "carol", 0.0, held=3)
    assert ls.describe() == {"a": 10.0, "b": 4.0, "c": 10.0}
    clock.t += 4.0                                  # b's 4 s are over, a's 10 s are not
    assert not ls.live("b") and ls.live("a")
    assert ls.expired() == ["b"] and ls.expired() == []
    clock.t += 3.0
    assert ls.renew("a", known=True) == 10.0
    clock.t += 7.0                                  # c (registered 14 s ago) ends, a (renewed 7 s ago) lives
    assert ls.expired() == ["c"] and ls.describe() == {"a": 3.0}
    with pytest.raises(MessageError, match=r"no standing search 'c' to renew .*register it again") as e:
        ls.renew("c", known=False)
    assert "\n" not in str(e.value)
    assert ls.live("never-leased")                  # the mapper's own requests have no lease
    ls.restore("r", "alice", 2.0)
    clock.t += 2.0
    assert ls.expired() == ["r"]


def test_lease_fields_round_trip_and_bad_values():
    q = QueryRequest(text="car", standing=True, id="q1", lease_s=12.5, client="c1")
    assert decode_query_request(encode_query_request(q)) == q
    s = SearchRequest(targets=["car"], standing=True, id="s1", lease_s=3.0, client="c1")
    assert decode_search_request(encode_search_request(s)) == s
    assert decode_search_request(encode_search_request(SearchRequest(renew=True, id="s1"))).renew
    for bad, match in ((dict(lease_s=-1.0), "lease_s must be seconds"), (dict(lease_s=1e9), "lease_s must be"),
                       (dict(client="a b"), "client id"), (dict(renew=True), "renew request needs")):
        with pytest.raises(MessageError, match=match) as e:
            SearchRequest(targets=["car"], **bad).validate()
        assert "\n" not in str(e.value)
        with pytest.raises(MessageError, match=match.replace("search", "query")):
            QueryRequest(text="car", **bad).validate()


def test_text_search_without_text_model_is_one_line():
    """A map whose feature space needs SigLIP (a NARADIO robot) and no text model on the
    mapper: a one-line error naming what to set, not "internal error: ModelFileError(...)"."""
    from mapper.query_answer import text_encoder

    with pytest.raises(MessageError) as e:
        text_encoder("siglip", "cpu", "")
    msg = str(e.value)
    assert "\n" not in msg and "set text_model_dir=DIR" in msg and "siglip" in msg
    with pytest.raises(MessageError, match="/nonexistent-text-model is not a directory.*set text_model_dir"):
        text_encoder("siglip", "cpu", "/nonexistent-text-model")
    # through the search's embedding and the queryable's reply: the asker reads that line
    from types import SimpleNamespace

    from mapper.replies import REQUEST_ERRORS, reply_to
    from mapper.search_answer import embed_phrases

    naradio = SimpleNamespace(id="naradio-space", text_model="siglip", head_config={"kind": "siglip"}, lang_dim=1152,
                              embed_queries=lambda *a, **k: pytest.fail("embedded without a text model"))
    req = SearchRequest(targets=["car"]).validate()

    class Query:
        key_expr = "rayfronts/mapper/search"
        payload = SimpleNamespace(to_bytes=lambda: encode_search_request(req))
        out = b""

        def reply(self, key, payload, attachment=None):
            Query.out = payload

    before = REQUEST_ERRORS["search"]
    reply_to(Query(), "search", lambda data: embed_phrases(naradio, decode_search_request(data), ["road"], "cpu", "",
                                                           "auto"))
    with pytest.raises(MessageError) as e:
        decode_search_reply(Query.out)
    assert str(e.value).startswith("remote error: cannot embed text") and "internal error" not in str(e.value)
    assert "set text_model_dir=DIR" in str(e.value) and "\n" not in str(e.value)
    assert REQUEST_ERRORS["search"] == before + 1


def _raw_get(session, key: str, payload: bytes) -> bytes:
    replies = [r.ok.payload.to_bytes() for r in session.get(key, payload=payload, timeout=10.0) if r.ok is not None]
    assert len(replies) == 1, replies
    return replies[0]


@pytest.mark.timeout(120)
def test_standing_requests_end_with_their_client(tmp_path, procs, pca_file):
    import zenoh

    from common.keys import KeySpace
    from tests.support.ports import free_port
    from tests.support.processes import Proc, wait_for
    from tests.support.roles import client, edge_args, mapped, mapper_args, zenoh_client_config

    K = KeySpace()
    ep = f"tcp/127.0.0.1:{free_port()}"
    snaps = tmp_path / "snaps"
    procs.append(Proc("mapper", mapper_args(ep, ["queues.idle_flush_s=0.3", f"snapshots.dir={snaps}",
                                                 "search.lease_s=1", "query.lease_s=1", "search.max_standing=4",
                                                 "search.max_standing_per_client=2"]), tmp_path))
    procs.append(Proc("edge", edge_args(ep, pca_file, frames=3, rate=4.0), tmp_path))
    ghost = None
    try:
        with client(ep) as c:
            c.lease_s = 1.5                              # renewed every 0.5 s
            wait_for(lambda: mapped(c) >= 2, 60, what="2 frames mapped")
            ghost = zenoh.open(zenoh_client_config(ep))  # a client that registers, then is gone
            dead = SearchRequest(targets=["car"], standing=True, id="ghost1", lease_s=1.0, client="ghost")
            decode_search_reply(_raw_get(ghost, K.mapper_search, encode_search_request(dead)))
            got: list = []
            h = c.watch_search(["car"], got.append)
            qh = c.watch("car", lambda r: None)
            st = c.stats()
            assert st["search"]["standing"] == 2 and set(st["search"]["leases_s"]) == {"ghost1", h.id}
            assert st["standing_queries"] == [qh.id]
            time.sleep(3.0)                              # ghost1's lease (1 s) ran out; h, qh renewed
            st = c.stats()
            assert set(st["search"]["leases_s"]) == {h.id} and st["search"]["standing"] == 1
            assert st["standing_queries"] == [qh.id] and h.renewed >= 3 and qh.renewed >= 3
            assert h.reregistered == 0
            # snapshots keep only the live ones (read back from the files)
            c.snapshot(save=True)
            meta = json.loads((Path(c.snapshot()["path"]) / "meta.json").read_text())
            saved = [decode_search_request(base64.b64decode(x["request"])).id for x in meta["standing_searches"]]
            assert saved == [h.id]
            assert [decode_query_request(base64.b64decode(x["request"])).id for x in meta["standing"]] == [qh.id]

            # bad input, one line each, counted; the mapper keeps serving
            def refused(req: SearchRequest, match: str) -> None:
                with pytest.raises(MessageError, match=match) as e:
                    decode_search_reply(_raw_get(ghost, K.mapper_search, encode_search_request(req)))
                assert "\n" not in str(e.value)

            refused(SearchRequest(renew=True, id="nope"), r"no standing search 'nope' to renew .*register it again")
            for sid in ("g2a", "g2b", "g2a"):            # per client: 2 (g2a again is not a third)
                decode_search_reply(_raw_get(ghost, K.mapper_search, encode_search_request(
                    SearchRequest(targets=["car"], standing=True, id=sid, lease_s=30.0, client="ghost2"))))
            refused(SearchRequest(targets=["car"], standing=True, id="g2c", client="ghost2"),
                    r"for client 'ghost2' \(2, limit search.max_standing_per_client=2\)")
            decode_search_reply(_raw_get(ghost, K.mapper_search, encode_search_request(
                SearchRequest(targets=["car"], standing=True, id="g3", client="ghost3"))))
            refused(SearchRequest(targets=["car"], standing=True, id="g4", client="ghost4"),
                    r"too many standing searches on this mapper \(4, limit search.max_standing=4\)")
            with pytest.raises(MessageError, match="no standing query 'nope' to renew"):
                from common.messages import decode_query_result
                decode_query_result(_raw_get(ghost, K.mapper_query, encode_query_request(QueryRequest(renew=True,
                                                                                                     id="nope"))))
            # a robot-scoped key with a wildcard for the robot, and a robot touching the operators' search
            with pytest.raises(MessageError, match="with one robot id") as e:
                decode_search_reply(_raw_get(ghost, "rayfronts/mapper/robots/*/search",
                                             encode_search_request(SearchRequest(targets=["car"]))))
            assert "\n" not in str(e.value)
            with pytest.raises(MessageError, match="'g2a' belongs to the operators, not to robot r1"):
                decode_search_reply(_raw_get(ghost, K.robot_search("r1"),
                                             encode_search_request(SearchRequest(cancel=True, id="g2a"))))
            assert c.stats()["request_errors"]["search"] == 5
            assert c.search("car").frames_mapped >= 2
            h.cancel()
            qh.cancel()
            st = c.stats()
            assert set(st["search"]["leases_s"]) == {"g2a", "g2b", "g3"} and st["standing_queries"] == []
    finally:
        if ghost is not None:
            ghost.close()
