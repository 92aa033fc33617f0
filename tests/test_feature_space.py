"""FeatureSpace: id, wire body round trip and validation, exact similarity fast path."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.feature_space import FeatureSpace, FeatureSpaceError
from common.language_head import MLP2, MLP2Config
from tests.support.data import low_rank_pca


def _head(d=32, out=12, seed=0):
    torch.manual_seed(seed)
    h = MLP2(MLP2Config(d, 20, out, num_inner=1))
    return h.cfg, {k: v.detach().numpy().copy() for k, v in h.state_dict().items()}


def test_id_changes_with_basis():
    p1, _ = low_rank_pca(seed=0)
    p2, _ = low_rank_pca(seed=1)
    a = FeatureSpace("label", "minilm-l6.1", 32, pca=p1)
    b = FeatureSpace("label", "minilm-l6.1", 32, pca=p2)
    assert a.id == f"label-minilm-l6.1-{p1.content_hash}-8"
    assert a.id != b.id
    assert FeatureSpace("label", "minilm-l6.1", 32).id == "label-minilm-l6.1-raw-32"


def test_body_roundtrip_with_pca_and_head():
    p, _ = low_rank_pca()
    hc, hs = _head()
    fs = FeatureSpace("naradio", "radio_v2.5-b.abcd", 32, "siglip", p, hc, hs)
    body = fs.to_body()
    for k, v in body.items():
        assert isinstance(k, str) and isinstance(v, (str, int, float, np.ndarray)), k
    back = FeatureSpace.from_body(body)
    assert back.id == fs.id and back.dim == 8 and back.lang_dim == 12 and back.text_model == "siglip"
    np.testing.assert_array_equal(back.pca.basis, p.basis)
    y = torch.randn(10, 8)
    torch.testing.assert_close(back.to_language(y), fs.to_language(y))


def test_body_validation():
    p, _ = low_rank_pca()
    hc, hs = _head()
    body = FeatureSpace("naradio", "v1", 32, "siglip", p, hc, hs).to_body()
    bad = dict(body, **{"pca.basis": body["pca.basis"][:, :7]})
    with pytest.raises(FeatureSpaceError, match="basis"):
        FeatureSpace.from_body(bad)
    bad = {k: v for k, v in body.items() if k != "head.sd.fc1.weight"}
    with pytest.raises(FeatureSpaceError, match="fc1.weight"):
        FeatureSpace.from_body(bad)
    bad = {k: v for k, v in body.items() if k != "encoder_name"}
    with pytest.raises(FeatureSpaceError, match="encoder_name"):
        FeatureSpace.from_body(bad)
    with pytest.raises(FeatureSpaceError, match="id"):
        FeatureSpace.from_body(dict(body, id="other"))
    with pytest.raises(FeatureSpaceError, match="encoder dim"):
        FeatureSpace("x", "1", 31, pca=p)


def slow_cos(fs, y, q):
    x = torch.as_tensor(fs.decompress(y.double().numpy()))
    if fs.head_config is not None:
        x = fs.language_head()(x.float()).double()
    x = x / x.norm(dim=1, keepdim=True)
    q = q.double() / q.double().norm(dim=1, keepdim=True)
    return (q @ x.T).float()


def test_similarity_fast_path_equals_slow_path():
    p, X = low_rank_pca()
    fs = FeatureSpace("label", "minilm-l6.1", 32, pca=p)
    y = torch.from_numpy(p.compress(X[:500])).float()
    q = torch.randn(5, 32, dtype=torch.float64).float()
    fast = fs.similarity(y, q, chunk=77)
    torch.testing.assert_close(fast, slow_cos(fs, y, q), rtol=1e-4, atol=1e-4)
    # a map feature whose decompression is ~0 gives 0, not NaN
    zero = torch.from_numpy(p.compress(np.zeros((1, 32), np.float32))).float()
    zq = fs.similarity(zero, q)
    assert torch.isfinite(zq).all()


def test_similarity_with_head_and_raw():
    p, X = low_rank_pca()
    hc, hs = _head()
    fs = FeatureSpace("naradio", "v1", 32, "siglip", p, hc, hs)
    y = torch.from_numpy(p.compress(X[:300])).float()
    q = torch.randn(3, 12)
    torch.testing.assert_close(fs.similarity(y, q, chunk=64), slow_cos(fs, y, q), rtol=1e-4, atol=1e-4)
    raw = FeatureSpace("label", "1", 32)
    xs = torch.from_numpy(X[:50]).float()
    q2 = torch.randn(2, 32)
    ref = torch.nn.functional.normalize(q2, dim=1) @ torch.nn.functional.normalize(xs, dim=1).T
    torch.testing.assert_close(raw.similarity(xs, q2), ref, rtol=1e-5, atol=1e-5)
    with pytest.raises(FeatureSpaceError, match=r"\(Q, 12\)"):
        fs.similarity(y, torch.randn(3, 32))
    with pytest.raises(FeatureSpaceError, match=r"\(N, 8\)"):
        fs.similarity(torch.randn(4, 9), q)


def test_embed_queries_checks_text_model():
    class Fake:
        name = "minilm-l6"

        def encode_labels(self, labels, templates="none"):
            return torch.ones(len(labels), 32)

    fs = FeatureSpace("label", "1", 32, "minilm-l6")
    assert fs.embed_queries(["a", "b"], Fake()).shape == (2, 32)
    with pytest.raises(FeatureSpaceError, match="siglip"):
        FeatureSpace("naradio", "1", 32, "siglip").embed_queries(["a"], Fake())


def test_from_decoded_message_has_writable_arrays_and_no_torch_warning():
    import warnings

    from common.messages import decode_feature_space, encode_feature_space

    p, X = low_rank_pca()
    hc, hs = _head()
    fs = FeatureSpace("naradio", "v1", 32, "siglip", p, hc, hs)
    _, body = decode_feature_space(encode_feature_space("r1", fs.to_body()))
    assert not body["pca.basis"].flags.writeable          # the wire hands out read-only views
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = FeatureSpace.from_body(body)
        assert back.pca.basis.flags.writeable and back.pca.mean.flags.writeable
        y = torch.from_numpy(p.compress(X[:20].astype(np.float32)))
        torch.testing.assert_close(back.to_language(y), fs.to_language(y))
        torch.testing.assert_close(back.similarity(y, torch.randn(2, 12)).shape, torch.Size([2, 20]))
