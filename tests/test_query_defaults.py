"""Query defaults follow the paper: prompt templates for language encoders, softmax over the
active queries (configurable), and the evaluation's explicit template / background choices."""
from types import SimpleNamespace

import pytest
import torch

from common.config import ConfigError, merge
from common.feature_space import FeatureSpace
from common.messages import QueryRequest
from encoders.label import LabelEncoder
from mapper.query_answer import SOFTMAX_NEGATIVES, query_templates, scores_for, softmax_set
from mapper.service_config import QuerySection

NAMES = ["sky", "car", "tree", "building"]


@pytest.fixture(scope="module")
def space():
    enc = LabelEncoder(NAMES)
    return enc, FeatureSpace.for_encoder(enc)


def _cos(a, b):
    return torch.nn.functional.normalize(a, dim=-1) @ torch.nn.functional.normalize(b, dim=-1).T


def test_templates_auto_per_encoder(space):
    _, fs = space
    assert query_templates(fs) == "none"                                   # label: raw name embeddings
    assert query_templates(SimpleNamespace(head_config=None, text_model="siglip")) == "imagenet80"
    assert query_templates(SimpleNamespace(head_config=object(), text_model="x")) == "imagenet80"
    assert query_templates(fs, "single") == "single"
    from encoders.text.templates import IMAGENET_TEMPLATES
    assert len(IMAGENET_TEMPLATES) == 80 and len(set(IMAGENET_TEMPLATES)) == 80


def test_softmax_over_standing_queries_by_default(space):
    enc, fs = space
    te = enc.text
    feats = te.encode(["car", "tree"])                                     # a car voxel, a tree voxel
    q = te.encode(["vehicle"])
    req = QueryRequest(text="vehicle", softmax=True, id="a")
    others = [QueryRequest(text="tree", standing=True, id="b"), QueryRequest(text="building", standing=True, id="c"),
              req]                                                          # itself is not counted twice
    qcfg = QuerySection()
    assert qcfg.softmax_set == "queries" and qcfg.templates == "auto"
    neg = softmax_set(fs, req, qcfg, others)
    assert neg.shape == (2, 384)
    got = scores_for(fs, feats, q, True, neg)
    allq = torch.cat([q, te.encode(["tree", "building"])])
    want = torch.softmax(100 * _cos(allq, feats), dim=0)[0]
    torch.testing.assert_close(torch.as_tensor(got), want, atol=1e-5, rtol=1e-5)
    assert got[0] > got[1]
    # a lone softmax query: the paper's constant 1
    assert softmax_set(fs, req, qcfg, [req]) is None
    assert torch.equal(torch.as_tensor(scores_for(fs, feats, q, True, None)), torch.ones(2))


def test_softmax_negatives_mode(space):
    enc, fs = space
    te = enc.text
    feats = te.encode(["car", "tree"])
    q = te.encode(["car"])
    qcfg = merge(QuerySection(), {"softmax_set": "negatives"})
    req = QueryRequest(text="car", softmax=True)
    neg = softmax_set(fs, req, qcfg, [QueryRequest(text="tree", standing=True, id="b")])
    torch.testing.assert_close(neg, te.encode(list(SOFTMAX_NEGATIVES)))
    qcfg2 = merge(QuerySection(), {"softmax_set": "negatives", "softmax_negatives": ["tree"]})
    got = scores_for(fs, feats, q, True, softmax_set(fs, req, qcfg2))
    want = torch.softmax(100 * _cos(torch.cat([q, te.encode(["tree"])]), feats), dim=0)[0]
    torch.testing.assert_close(torch.as_tensor(got), want, atol=1e-5, rtol=1e-5)
    with pytest.raises(ConfigError, match="softmax_set"):
        merge(QuerySection(), {"softmax_set": "everything"})


def test_eval_templates_and_background_explicit():
    from apps.evaluation.language import use_templates
    from apps.evaluation.semseg import BACKGROUND_REFERENCE, BACKGROUND_SYNTHETIC, SemsegConfig
    from apps.evaluation.srchvol import SrchvolConfig
    assert SrchvolConfig().templates == "auto" and SemsegConfig().templates == "auto"
    assert use_templates("auto", SimpleNamespace(language_head=object(), text_model="siglip")) is True
    assert use_templates("auto", SimpleNamespace(language_head=None, text_model="minilm-l6")) is False
    assert use_templates(True, SimpleNamespace(language_head=None)) is True
    assert SemsegConfig().background == BACKGROUND_REFERENCE + BACKGROUND_SYNTHETIC
    assert BACKGROUND_REFERENCE[:6] == ["wall", "floor", "ceiling", "door", "window", "background"]
