"""``--pca-fit vocabulary``: a PCA basis from a generic vocabulary's text embeddings, with
the world's class names left out and no view of the world rendered; and what it is for —
a far landmark the robot's first views never showed stays recognisable in the compressed
features (a first-views basis drops it: docs/results/closed_loop_robot.md).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from apps.closed_loop.episode import GENERIC_BACKGROUND
from apps.closed_loop.generic_vocabulary import GENERIC_VOCABULARY, vocabulary_without
from apps.closed_loop.sensing import EdgeChain, SensorConfig
from synthetic_world import World


@pytest.fixture(scope="module")
def world() -> World:
    return World.generate(seed=0)


def _target_probability(chain: EdgeChain, world: World, target: str) -> float:
    """p(target) over target + the generic background of the class cell of ``target`` as the
    map scores it: the encoder's feature PCA-compressed, the query projected into the basis."""
    cells = chain.class_cells()
    q = chain.encoder.text.encode([target, *GENERIC_BACKGROUND]).float()
    qn, qm = chain.space.project_queries(q)
    m, v = chain.pca.torch_basis(torch.device("cpu"), torch.float32)
    y = (cells - m) @ v
    cos = (y @ qn.T + qm[None]) / (y @ v.T + m).norm(dim=1, keepdim=True)
    return float(torch.softmax(100 * cos, 1)[world.classes.index(target), 0])


def test_vocabulary_leaves_out_the_world_classes_and_renders_nothing(world, monkeypatch):
    assert len(GENERIC_VOCABULARY) == len(set(GENERIC_VOCABULARY)) >= 100
    left = vocabulary_without(list(world.classes))
    assert set(left) == set(GENERIC_VOCABULARY) - {c.lower() for c in world.classes}
    assert len(left) < len(GENERIC_VOCABULARY)           # the town's classes (tree, building, ...) were in it
    seen: list[list[str]] = []

    def no_render(self, *args, **kwargs):
        raise AssertionError("a vocabulary basis renders no view")

    from encoders.text.minilm import MiniLMText

    real = MiniLMText.encode
    monkeypatch.setattr(World, "render", no_render)
    monkeypatch.setattr(MiniLMText, "encode", lambda self, texts: seen.append(list(texts)) or real(self, texts))
    chain = EdgeChain(world, SensorConfig(encoder="sim", sensor="realistic", pca_fit="vocabulary"))
    assert chain.pca is not None
    assert left in seen, "the basis was not fitted on the vocabulary"


def test_a_far_landmark_survives_a_vocabulary_basis_not_a_first_views_one(world):
    start = np.array([16.1, -17.8, 1.5])          # a street start in world 0, towers ~200 m away
    cfg = SensorConfig(encoder="sim", sensor="realistic")
    first = EdgeChain(world, SensorConfig(**{**cfg.__dict__, "pca_fit": "first_views"}), fit_at=start)
    vocab = EdgeChain(world, SensorConfig(**{**cfg.__dict__, "pca_fit": "vocabulary"}), fit_at=start)
    for target in ("water tower", "radio tower"):
        assert _target_probability(first, world, target) < 0.5, target
        assert _target_probability(vocab, world, target) > 0.5, target
