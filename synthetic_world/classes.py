"""Class names and colours of the synthetic world.

Index = class id; id 0 is ``"sky"`` (nothing there). Names are plain English on purpose: the
label encoder embeds them with a text model, so "vehicle" must land near "car" and
"antenna mast" near "radio tower".
"""
from __future__ import annotations

#: (name, RGB colour) by class id.
DEFAULT_CLASSES: list[tuple[str, tuple[int, int, int]]] = [
    ("sky", (135, 185, 235)),
    ("ground", (128, 140, 80)),
    ("road", (72, 72, 78)),
    ("building", (196, 170, 140)),
    ("tree", (46, 112, 46)),
    ("car", (190, 40, 40)),
    ("fence", (150, 110, 70)),
    ("chimney", (150, 60, 45)),
    ("street lamp", (90, 95, 105)),
    ("bench", (120, 80, 40)),
    ("rock", (125, 120, 115)),
    ("water tower", (210, 210, 215)),
    ("radio tower", (220, 60, 50)),
]

CLASS_NAMES: list[str] = [n for n, _ in DEFAULT_CLASSES]
CLASS_COLORS: list[tuple[int, int, int]] = [c for _, c in DEFAULT_CLASSES]

#: classes whose instances sit near the trajectories (inside a 20 m sensor's range).
IN_RANGE_CLASSES = ["road", "building", "tree", "car", "fence", "chimney", "street lamp", "bench", "rock"]
#: classes that exist only as far landmarks (100–300 m from every trajectory pose).
FAR_CLASSES = ["water tower", "radio tower"]
