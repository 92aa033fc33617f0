"""The label encoder's image side: the global feature of an RGB image in its MiniLM space.

The label encoder reads ground-truth labels, which a query image does not have, so an image
is mapped into the same space by the synthetic world's class *appearance*
(:mod:`synthetic_world.classes` colours as :mod:`synthetic_world.render` shades them). Definition:

* **Pixel classes.** A surface of class ``c`` (colour ``C_c``) renders as
  ``(1 − f)·s·C_c + f·H`` — shade ``s ∈ [0.42, 1]`` (ambient + Lambert), aerial perspective
  ``f ∈ [0, 0.4]`` toward the horizon colour ``H`` (0.4 = 460 m of haze), ±3 levels of
  noise; the sky (class 0) is the horizon→zenith gradient; the generator's other paints of a
  class (:data:`EXTRA_APPEARANCE`: coloured car paints, ...) are families of that class too.
  A pixel takes the class of the nearest family (RGB distance to the family's (s, f) box, by
  least squares) and is unclassified when every family is farther than
  :data:`MAX_RGB_DISTANCE`. At most :data:`MAX_PIXELS` pixels are classified (a regular subsample).
* **Image vector.** The embedding ``e_c`` (the MiniLM embedding of class ``c``'s name, the
  label encoder's own table) of the class ``c`` with the largest share of the classified
  pixels, class 0 (sky, "nothing there") counting only when no other class is found: the
  image shows its dominant class, as a real encoder's global feature is dominated by the
  salient object. So a crop of the water tower answers exactly as the text "water tower",
  a crop of a car as "car". (The share-weighted mix ``Σ_c p_c · e_c`` that the label
  encoder's ``encode_global`` computes for a frame was the first definition: a tower's
  bounding-box crop holds ~40 % building, rock-grey shadow and ground pixels, and that mix
  answered with building rays on the README walkthrough's map.)

Classes the world shades alike (car and radio tower are both red; the grey road, rock,
street lamp and a water tower's shadowed side) are partly confused pixel by pixel; the
dominant class decides, and a query answers with the map's classes: a car crop finds car
voxels in range (radio towers exist only as far rays).
"""
from __future__ import annotations

import numpy as np

from synthetic_world.classes import CLASS_COLORS, CLASS_NAMES

#: pixels farther than this (RGB levels, Euclidean) from every class family are unclassified
MAX_RGB_DISTANCE = 40.0
#: at most this many pixels are classified per image (a regular subsample beyond)
MAX_PIXELS = 65536
# the renderer's constants (synthetic_world.render): shade range, horizon and zenith sky colours
_SHADE = (0.42, 1.0)
_HAZE_MAX = 0.4
_SKY_HORIZON = np.array([205.0, 222.0, 240.0])
_SKY_ZENITH = np.array([105.0, 155.0, 225.0])
#: colours the world generator gives some instances besides their class colour
#: (synthetic_world.generate: car paints, the factory chimney and building, far buildings).
#: White and black cars are left out: by colour they are the water tower and the road.
EXTRA_APPEARANCE: dict[str, list[tuple[int, int, int]]] = {
    "car": [(40, 70, 170), (200, 170, 40)],
    "chimney": [(170, 70, 55)],
    "building": [(170, 165, 160), (150, 160, 175)],
}


def label_vocabulary() -> list[str]:
    """The label encoder's class names, in class-id order (its embedding table's rows)."""
    return list(CLASS_NAMES)


def _families(colors=CLASS_COLORS, names=CLASS_NAMES) -> tuple[np.ndarray, np.ndarray]:
    """``(F, 3)`` base colours of the appearance families and their ``(F,)`` class ids
    (class 0, the sky, has none: it is the horizon→zenith segment)."""
    bases, ids = [], []
    for c, col in enumerate(colors):
        if c == 0:
            continue
        for b in [col, *EXTRA_APPEARANCE.get(names[c], [])]:
            bases.append(b)
            ids.append(c)
    return np.asarray(bases, np.float64), np.asarray(ids, np.int64)


_FAMILIES = _families()


def _family_dist2(x: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared RGB distance of pixels ``x`` (N, 3) to the family ``(1 − f)·s·b + f·H``
    (``s ∈ [0.42, 1]``, ``f ∈ [0, 0.4]``): least squares in ``(a, f)``, ``a = (1 − f)·s``,
    then clamped to the box (f first, then a given f, then f given a)."""
    H = _SKY_HORIZON
    bb, bh, hh = b @ b, b @ H, H @ H
    xb, xh = x @ b, x @ H
    det = bb * hh - bh * bh
    f = np.clip((bb * xh - bh * xb) / det, 0.0, _HAZE_MAX)
    a = np.clip((xb - f * bh) / bb, (1 - f) * _SHADE[0], (1 - f) * _SHADE[1])
    f = np.clip((xh - a * bh) / hh, 0.0, _HAZE_MAX)
    a = np.clip(a, (1 - f) * _SHADE[0], (1 - f) * _SHADE[1])
    r = x - a[:, None] * b[None] - f[:, None] * H[None]
    return (r * r).sum(1)


def _sky_dist2(x: np.ndarray) -> np.ndarray:
    d = _SKY_ZENITH - _SKY_HORIZON
    t = np.clip((x - _SKY_HORIZON) @ d / (d @ d), 0.0, 1.0)
    r = x - _SKY_HORIZON[None] - t[:, None] * d[None]
    return (r * r).sum(1)


def classify_pixels(rgb: np.ndarray, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """``(N,)`` class id per classified (subsampled) pixel of ``rgb`` ``(H, W, 3)`` uint8; -1 =
    unclassified (farther than :data:`MAX_RGB_DISTANCE` from every class)."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"image must be (H, W, 3) uint8 RGB, got {a.shape} {a.dtype}")
    px = a.reshape(-1, 3)
    if len(px) > max_pixels:
        px = px[np.linspace(0, len(px) - 1, max_pixels).astype(np.int64)]
    x = px.astype(np.float64)
    bases, ids = _FAMILIES
    d2 = np.stack([_sky_dist2(x)] + [_family_dist2(x, b) for b in bases], 1)
    cls = np.concatenate([[0], ids])
    j = d2.argmin(1)
    best = d2[np.arange(len(x)), j]
    return np.where(best <= MAX_RGB_DISTANCE ** 2, cls[j], -1)


def class_shares(rgb: np.ndarray, n_classes: int = len(CLASS_NAMES)) -> np.ndarray:
    """``(K,)`` share of each class among the classified pixels (sky only if nothing else;
    all zero when no pixel is classified)."""
    lab = classify_pixels(rgb)
    lab = lab[lab >= 0]
    hist = np.bincount(lab, minlength=n_classes)[:n_classes].astype(np.float64)
    if hist[1:].sum() > 0:
        hist[0] = 0.0
    tot = hist.sum()
    return hist / tot if tot > 0 else hist


def label_image_embedding(rgb: np.ndarray, class_embeddings: np.ndarray) -> np.ndarray:
    """The image vector (module docstring: the dominant class's embedding) for class embeddings ``(K, D)``
    (row ``c`` = the text embedding of ``CLASS_NAMES[c]``); ``ValueError`` when no pixel
    looks like any class of the world."""
    e = np.asarray(class_embeddings, np.float32)
    p = class_shares(rgb, e.shape[0])
    if p.sum() <= 0:
        raise ValueError("the image matches none of the synthetic world's class appearances "
                         f"(no pixel within {MAX_RGB_DISTANCE:.0f} RGB levels of a class colour)")
    return e[int(np.argmax(p))].copy()
