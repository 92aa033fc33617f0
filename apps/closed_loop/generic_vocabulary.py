"""A generic vocabulary: common nouns of scenes and objects, written for this project, not
taken from any world or dataset list. ``rayfronts eval search --pca-fit vocabulary`` fits the
PCA basis on their text embeddings (the semantic directions of the encoder's space), with
every phrase that names a class of the world at hand left out, as a basis fitted offline on a
broad corpus would be (the real edge's ``pca.path``) — not on the robot's few first views,
whose span misses what they did not see (docs/results/closed_loop_robot.md).
"""
from __future__ import annotations

GENERIC_VOCABULARY: tuple[str, ...] = (
    # living things
    "person", "child", "dog", "cat", "horse", "cow", "bird", "sheep",
    # vehicles
    "car", "truck", "bus", "van", "bicycle", "motorcycle", "train", "boat", "airplane", "tractor", "trailer",
    # ways
    "road", "street", "sidewalk", "path", "bridge", "tunnel", "parking lot", "crosswalk", "highway", "railway",
    # buildings
    "house", "building", "skyscraper", "tower", "church", "castle", "temple", "pagoda", "barn", "shed", "garage",
    "hut", "tent", "factory", "warehouse", "stadium",
    # parts of buildings
    "wall", "fence", "gate", "door", "window", "roof", "stairs", "column", "arch", "balcony", "chimney", "dome",
    # nature
    "tree", "bush", "grass", "flower", "plant", "palm", "forest", "field", "hill", "mountain", "rock", "stone",
    "sand", "snow", "water", "river", "lake", "sea", "pond", "waterfall",
    # surfaces
    "sky", "cloud", "sun", "ground", "floor", "ceiling", "earth", "dirt", "mud",
    # structures
    "pole", "street light", "traffic light", "sign", "billboard", "antenna", "mast", "pylon", "power line",
    "wind turbine", "tank", "silo", "pipe", "crane",
    # furniture and things
    "bench", "table", "chair", "sofa", "bed", "shelf", "cabinet", "desk", "lamp", "box", "barrel", "crate", "bin",
    "bag", "bottle", "cup",
    # figures and machines
    "statue", "sculpture", "monument", "fountain", "toy", "doll", "ball", "robot", "machine", "vehicle",
    "container", "tire",
)


def vocabulary_without(classes: list[str]) -> list[str]:
    """:data:`GENERIC_VOCABULARY` less every phrase that is one of ``classes`` (case-blind)."""
    own = {c.strip().lower() for c in classes}
    return [w for w in GENERIC_VOCABULARY if w.lower() not in own]
