"""Label encoder: MiniLM class-name embeddings per pixel, pooled into cells; queries."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from common.feature_space import FeatureSpace
from common.pca import PCA
from encoders import EncoderConfig, make_encoder

CLASSES = ["sky", "ground", "road", "building", "tree", "car", "fence", "chimney", "water tower",
           "radio tower", "street lamp", "bench"]


@pytest.fixture(scope="module")
def enc():
    return make_encoder(EncoderConfig(kind="label", label_stride=4), class_names=CLASSES)


@pytest.mark.parametrize("query,expected", [("vehicle", "car"), ("antenna mast", "radio tower"),
                                            ("lamp post", "street lamp"), ("automobile", "car")])
def test_open_vocabulary_queries(enc, query, expected):
    q = enc.text.encode([query])[0]
    sims = enc.table @ q
    assert CLASSES[int(sims.argmax())] == expected


def test_cells_are_mean_of_pixel_embeddings(enc):
    rng = np.random.default_rng(0)
    lab = rng.integers(0, len(CLASSES), (10, 13)).astype(np.int32)
    rgb = np.zeros((10, 13, 3), np.uint8)
    f = enc.encode(rgb, lab)
    assert f.shape == (384, 3, 4) and f.dtype == torch.float32   # ceil(10/4), ceil(13/4)
    T = enc.table.numpy()
    for i in range(3):
        for j in range(4):
            block = lab[i * 4:(i + 1) * 4, j * 4:(j + 1) * 4]
            np.testing.assert_allclose(f[:, i, j].numpy(), T[block.reshape(-1)].mean(0), rtol=1e-5, atol=1e-6)
    g = enc.encode_global(rgb, lab)
    np.testing.assert_allclose(g.numpy(), T[lab.reshape(-1)].mean(0), rtol=1e-5, atol=1e-6)


def test_majority_pooling():
    e = make_encoder(EncoderConfig(kind="label", label_stride=2, label_pooling="majority"), class_names=CLASSES)
    lab = np.array([[5, 5, 1, 2], [5, 7, 2, 2]], np.int64)
    f = e.encode(None, lab)
    torch.testing.assert_close(f[:, 0, 0], e.table[5])
    torch.testing.assert_close(f[:, 0, 1], e.table[2])
    # global: 3 x car, 3 x road -> tie goes to the lowest class id (road = 2)
    torch.testing.assert_close(e.encode_global(None, lab), e.table[2])
    lab[1, 1] = 5
    torch.testing.assert_close(e.encode_global(None, lab), e.table[5])


def test_end_to_end_query_through_feature_space(enc):
    # a 'car' region in a 'road' scene must be where "vehicle" scores highest
    lab = np.full((32, 32), CLASSES.index("road"), np.int32)
    lab[8:16, 20:28] = CLASSES.index("car")
    lab[:4] = 0
    f = enc.encode(None, lab)                                    # (384, 8, 8)
    X = f.flatten(1).T
    pca = PCA.fit(torch.cat([enc.table, X]), 8)
    fs = FeatureSpace.for_encoder(enc, pca)
    assert fs.text_model == "minilm-l6" and fs.dim == 8 and fs.id.startswith("label-minilm-l6.1-")
    y = torch.as_tensor(fs.compress(X))
    q = fs.embed_queries(["vehicle"], enc.text)
    s = fs.similarity(y, q)[0].reshape(8, 8)
    r, c = divmod(int(s.argmax()), 8)
    assert 2 <= r < 4 and 5 <= c < 7


def test_bad_labels(enc):
    with pytest.raises(ValueError, match="needs per-pixel labels"):
        enc.encode(np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match=r"\[0, 12\)"):
        enc.encode(None, np.full((4, 4), 12))
    with pytest.raises(ValueError, match="differ"):
        enc.encode(np.zeros((4, 5, 3), np.uint8), np.zeros((4, 4), np.int32))
    with pytest.raises(ValueError, match="class names"):
        make_encoder(EncoderConfig(kind="label"))


def test_image_vector_is_the_dominant_class_of_a_rendered_crop():
    """The label encoder's image side: a crop rendered from the synthetic world (bounding box
    of one instance, background and shadow pixels included) gives exactly the embedding of
    that instance's class; a sky-only image gives the sky's; an image of no class is refused.
    (Classes the renderer shades alike are confused by colour: the largest building view reads
    as ground, a street lamp as road; see the module docstring.)"""
    from encoders.label_image import class_shares, label_image_embedding
    from synthetic_world import World
    from synthetic_world.classes import CLASS_NAMES

    w = World.generate(0)
    res = (240, 320)
    K = w.camera(res, 90.0)
    table = np.random.default_rng(0).standard_normal((len(CLASS_NAMES), 8)).astype(np.float32)
    seen = {}
    for pose in w.trajectory("ground", 40):
        r = w.render(pose, K, res)
        for cls in ("water tower", "tree", "car"):
            cid = w.class_id(cls)
            for inst in np.unique(r.instance[r.labels == cid]):
                ys, xs = np.nonzero(r.instance == inst)
                if len(ys) > seen.get(cls, (0, None))[0]:                # the largest view
                    seen[cls] = (len(ys), r.rgb[ys.min():ys.max() + 1, xs.min():xs.max() + 1])
    assert set(seen) == {"water tower", "tree", "car"}
    for cls, (_, crop) in seen.items():
        p = class_shares(crop)
        assert p[w.class_id(cls)] < 1.0, (cls, p)        # not pure: background / shadow pixels too
        np.testing.assert_array_equal(label_image_embedding(crop, table), table[w.class_id(cls)])
    sky = np.broadcast_to(np.array([205, 222, 240], np.uint8), (8, 8, 3)).copy()
    np.testing.assert_array_equal(label_image_embedding(sky, table), table[0])
    with pytest.raises(ValueError, match="matches none"):
        label_image_embedding(np.full((8, 8, 3), (255, 0, 255), np.uint8), table)
