"""common.messages: round trips and validation of the non-frame schemas."""
import numpy as np
import pytest

from common.messages import (
    MessageError,
    QueryRequest,
    QueryResult,
    decode_feature_space,
    decode_layer,
    decode_query_request,
    decode_query_result,
    decode_snapshot_request,
    decode_stats,
    encode_error,
    encode_feature_space,
    encode_layer,
    encode_query_request,
    encode_query_result,
    encode_snapshot_request,
    encode_stats,
)
from common.wire import encode_message


def test_query_request_roundtrip():
    for req in (QueryRequest(text="water tower", top_k=3),
                QueryRequest(image=b"\xff\xd8jpeg", standing=True, id="q1"),
                QueryRequest(embedding=np.arange(4, dtype=np.float32), softmax=True)):
        got = decode_query_request(encode_query_request(req))
        assert got.text == req.text and got.image == req.image and got.top_k == req.top_k
        assert got.standing == req.standing and got.id == req.id and got.softmax == req.softmax
        if req.embedding is not None:
            np.testing.assert_array_equal(got.embedding, req.embedding)


@pytest.mark.parametrize("req, msg", [
    (QueryRequest(), "exactly one"),
    (QueryRequest(text="a", image=b"x"), "exactly one"),
    (QueryRequest(text="  "), "non-empty"),
    (QueryRequest(text="a", top_k=0), "top_k"),
    (QueryRequest(text="a", standing=True), "needs an id"),
    (QueryRequest(text="a", id="bad/id"), "must match"),
    (QueryRequest(embedding=np.array([np.nan], np.float32)), "finite"),
    (QueryRequest(cancel=True), "cancel"),
])
def test_query_request_invalid(req, msg):
    with pytest.raises(MessageError, match=msg):
        encode_query_request(req)


def test_decoders_reject_wrong_schema_and_garbage():
    with pytest.raises(MessageError, match="expected schema"):
        decode_query_request(encode_stats({"a": 1}))
    with pytest.raises(MessageError):
        decode_query_result(b"\x00\x01garbage")
    with pytest.raises(MessageError, match="unknown fields"):
        decode_query_request(encode_message("rayfronts.query_request", 1, {"text": "a", "evil": 1}))
    with pytest.raises(MessageError, match="version"):
        decode_stats(encode_message("rayfronts.stats", 99, {}))
    with pytest.raises(MessageError, match="remote error: boom"):
        decode_query_result(encode_error("boom"))


def test_query_result_roundtrip_and_shape_checks():
    r = QueryResult(id="q", query="tree", cluster_xyz=np.ones((2, 3)), cluster_size=np.array([3, 1]),
                    cluster_extent=np.ones((2, 3)), cluster_score=np.array([0.9, 0.5]),
                    voxel_xyz=np.zeros((1, 3)), voxel_score=np.array([0.9]),
                    ray_origin=np.zeros((1, 3)), ray_direction=np.array([[1.0, 0, 0]]), ray_score=np.array([0.4]),
                    search_volume_m3=12.5, frames_mapped=7, timings={"total": 3.0})
    g = decode_query_result(encode_query_result(r))
    assert g.query == "tree" and g.frames_mapped == 7 and g.search_volume_m3 == 12.5
    np.testing.assert_allclose(g.cluster_score, [0.9, 0.5], rtol=1e-6)
    assert g.cluster_size.dtype == np.int32 and g.ray_direction.shape == (1, 3)
    bad = QueryResult(voxel_xyz=np.zeros((2, 3)), voxel_score=np.zeros(1))
    with pytest.raises(MessageError, match="different lengths"):
        encode_query_result(bad)
    body = {k: np.zeros((0, 3) if k.endswith(("xyz", "extent", "origin", "direction")) else (0,), np.float32)
            for k in QueryResult._ARRAYS}
    body["voxel_xyz"] = np.zeros((2, 4), np.float32)
    with pytest.raises(MessageError, match="voxel_xyz"):
        decode_query_result(encode_message("rayfronts.query_result", 1, body))


def test_query_result_mapper_only_fields_stay_off_the_wire():
    r = QueryResult(id="q", query="tree", voxel_xyz=np.zeros((1, 3)), voxel_score=np.array([0.7]))
    plain = encode_query_result(r)
    r.half_angle_deg, r.score_min = 12.5, -0.25
    wire = encode_query_result(r)
    assert wire == plain                                     # the same bytes with or without them
    d = r.to_dict()
    assert list(d)[-2:] == ["half_angle_deg", "score_min"] and d["score_min"] == -0.25
    g = decode_query_result(wire)
    assert g.half_angle_deg is None and g.score_min is None
    assert "half_angle_deg" not in g.to_dict() and "score_min" not in g.to_dict()
    assert set(r.to_dict()) - set(g.to_dict()) == {"half_angle_deg", "score_min"}
    assert "score_min" not in repr(r)


def test_layers_feature_space_snapshot():
    layer, arrays, meta = decode_layer(encode_layer("voxels", {"xyz": np.ones((4, 3)), "rgb": np.full((4, 3), 7)},
                                                    {"total": 10}))
    assert layer == "voxels" and arrays["rgb"].dtype == np.uint8 and meta["total"] == 10
    with pytest.raises(MessageError, match="unknown layer"):
        encode_layer("nope", {})
    with pytest.raises(MessageError, match="different lengths"):
        decode_layer(encode_message("rayfronts.layer", 1, {"layer": "rays", "origin": np.zeros((2, 3), np.float32),
                                                           "direction": np.zeros((3, 3), np.float32), "meta": {}}))
    robot, body = decode_feature_space(encode_feature_space("r1", {"id": "x", "pca.mean": np.zeros(3)}))
    assert robot == "r1" and body["id"] == "x"
    assert decode_snapshot_request(encode_snapshot_request("save")) == "save"
    with pytest.raises(MessageError):
        encode_snapshot_request("delete")
