"""The key space (common.keys): docs/key_space.md keys, prefix handling, id validation, parsers."""
from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.keys import InvalidKey, KeySpace, check_id, is_valid_id

ID_ALPHABET = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-"


def test_design_table_keys_default_prefix():
    k = KeySpace()
    assert k.prefix == "rayfronts"
    assert k.frames("r1") == "rayfronts/robots/r1/frames"
    assert k.frames_all == "rayfronts/robots/*/frames"
    assert k.alive("r1") == "rayfronts/robots/r1/alive"
    assert k.alive_all == "rayfronts/robots/*/alive"
    assert k.feature_space("r1") == "rayfronts/robots/r1/feature_space"
    assert k.mapper_alive == "rayfronts/mapper/alive"
    assert k.mapper_query == "rayfronts/mapper/query"
    assert k.mapper_queries("q7") == "rayfronts/mapper/queries/q7"
    assert k.mapper_queries_all == "rayfronts/mapper/queries/*"
    assert k.layers("voxels") == "rayfronts/mapper/layers/voxels"
    assert k.layers_all == "rayfronts/mapper/layers/*"
    assert k.stats == "rayfronts/mapper/stats"
    assert k.snapshot == "rayfronts/mapper/snapshot"


def test_custom_prefix_multi_chunk():
    k = KeySpace("site-a/exp.2")
    assert k.frames("jackal_1") == "site-a/exp.2/robots/jackal_1/frames"
    assert k.mapper_alive == "site-a/exp.2/mapper/alive"
    assert k.robot_from_key("site-a/exp.2/robots/jackal_1/alive") == "jackal_1"
    # another prefix's keys are not ours
    assert k.robot_from_key("rayfronts/robots/jackal_1/alive") is None
    assert KeySpace("a") == KeySpace("a") and KeySpace("a") != KeySpace("b")


@pytest.mark.parametrize("prefix", ["", "/rayfronts", "rayfronts/", "a//b", "a/*", "a/**", "a b", "a?x", "a#b", "a$b",
                                    3])
def test_bad_prefix_rejected(prefix):
    with pytest.raises(InvalidKey):
        KeySpace(prefix)


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "r 1", "r$1", "r?1", "r#1", "x" * 65, "é", None, 5])
def test_bad_ids_rejected_everywhere(bad):
    k = KeySpace()
    assert not is_valid_id(bad)
    for fn in (k.frames, k.alive, k.feature_space, k.mapper_queries, k.layers, check_id):
        with pytest.raises(InvalidKey):
            fn(bad)


def test_robot_from_key():
    k = KeySpace()
    assert k.robot_from_key("rayfronts/robots/r1/frames") == "r1"
    assert k.robot_from_key("rayfronts/robots/r-1_B/feature_space") == "r-1_B"
    for key in ["rayfronts/robots/r1", "rayfronts/robots//frames", "rayfronts/robots/*/frames",
                "rayfronts/robots/r1/frames/extra", "rayfronts/mapper/alive", "other/robots/r1/frames",
                "rayfronts/robots/" + "x" * 65 + "/frames", "xrayfronts/robots/r1/frames", ""]:
        assert k.robot_from_key(key) is None, key


def test_qid_and_layer_parsers():
    k = KeySpace()
    assert k.qid_from_key(k.mapper_queries("abc")) == "abc"
    assert k.layer_from_key(k.layers("frontiers")) == "frontiers"
    assert k.qid_from_key("rayfronts/mapper/queries/a/b") is None
    assert k.layer_from_key("rayfronts/mapper/queries/x") is None


@given(st.text(alphabet=ID_ALPHABET, min_size=1, max_size=64))
def test_roundtrip_any_valid_robot(robot):
    k = KeySpace()
    for key in (k.frames(robot), k.alive(robot), k.feature_space(robot)):
        assert k.robot_from_key(key) == robot
        # an independent check of the key shape
        parts = key.split("/")
        assert parts[:2] == ["rayfronts", "robots"] and parts[2] == robot and len(parts) == 4


def test_keys_are_valid_zenoh_key_exprs():
    import zenoh
    k = KeySpace("rayfronts")
    keys = [k.frames("r1"), k.frames_all, k.alive("r1"), k.alive_all, k.feature_space("r1"), k.mapper_alive,
            k.mapper_query, k.mapper_queries("q1"), k.mapper_queries_all, k.layers("voxels"), k.layers_all,
            k.stats, k.snapshot, k.everything]
    for key in keys:
        assert str(zenoh.KeyExpr(key)) == key
    assert zenoh.KeyExpr(k.frames_all).intersects(zenoh.KeyExpr(k.frames("r2")))
    assert not zenoh.KeyExpr(k.frames_all).intersects(zenoh.KeyExpr(k.alive("r2")))
