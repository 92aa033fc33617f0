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


def _target_probability(chain: EdgeChain, world, target: str, cell: str | None = None,
                        background: list[str] | tuple[str, ...] = GENERIC_BACKGROUND) -> float:
    """p(target) over target + ``background`` of the class cell of ``cell`` (default: the
    target's own) as the map scores it: the encoder's feature PCA-compressed, the query
    projected into the basis."""
    cells = chain.class_cells()
    q = chain.encoder.text.encode([target, *background]).float()
    qn, qm = chain.space.project_queries(q)
    m, v = chain.pca.torch_basis(torch.device("cpu"), torch.float32)
    y = (cells - m) @ v
    cos = (y @ qn.T + qm[None]) / (y @ v.T + m).norm(dim=1, keepdim=True)
    return float(torch.softmax(100 * cos, 1)[world.classes.index(cell or target), 0])


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


def test_the_vocabulary_background_tells_a_target_from_the_class_it_is_confused_with(world):
    """Against the seven generic phrases a radio tower reads as a water tower (and a teddy bear
    as the teddy bear statue); against the generic vocabulary less the world's class names
    (``--background vocabulary``: the confusing class's own name is not among them) the nearest
    common noun ("tower", "toy") takes the confused class's share and the target keeps its own."""
    from apps.closed_loop.episode import LoopSettings
    from synthetic_world.pybullet_world import PybulletWorld

    start = np.array([16.1, -17.8, 1.5])
    cfg = SensorConfig(encoder="sim", sensor="realistic", pca_fit="vocabulary")
    town = EdgeChain(world, cfg, fit_at=start)
    site_world = PybulletWorld.generate(0)
    site = EdgeChain(site_world, cfg)
    cases = [(town, world, "water tower", "radio tower"), (site, site_world, "teddy bear statue", "teddy bear")]
    for chain, w, target, confused in cases:
        vocab = LoopSettings(background="vocabulary").background_phrases(w)
        assert not set(vocab) & set(w.classes) and len(vocab) >= 100
        assert _target_probability(chain, w, target, confused) > 0.5, (target, confused)      # the confusion
        assert _target_probability(chain, w, target, confused, vocab) < 0.5, (target, confused)
        assert _target_probability(chain, w, target, None, vocab) > 0.5, target
