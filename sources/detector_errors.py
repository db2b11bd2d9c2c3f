"""The simulated detector's errors beyond misses and false positives: loose boxes, confused labels, part boxes.

A trained detector on real frames differs from the synthetic scenes' default detector in three ways that matter
to the object path (``objslam bench box-stability`` measures them: on 7-Scenes CenterNet's boxes wobble less from
frame to frame than the default's, but it switches labels and boxes parts of objects, which the default never
does). Each has a knob of the synthetic spec (``synthetic:family?...&box_noise=..``):

- ``box_noise``: each box side is off by a normal share of the box's size with this standard deviation
  (clipped at 2.5 of them); 0.025 by default, 0.06-0.1 for a detector whose boxes wobble from frame to frame;
- ``confusion``: the share of detections given a label the detector often mistakes the object's for
  (``CONFUSED_WITH``: a cup seen as a bowl, a couch as a chair, an orange as an apple);
- ``part_boxes``: the share of boxes that hold only part of their object, as a detector's box on a chair's
  backrest alone or on the half of a couch it recognises: 45-80 % of the box from one of its sides, kept.

Both ``confusion`` and ``part_boxes`` draw from their own random stream, so with them at 0 a scene's
detections are exactly those of a spec without them.
"""

from __future__ import annotations

import numpy as np

CONFUSED_WITH: dict[str, tuple[str, ...]] = {
    "cup": ("bowl", "vase", "wine glass"),
    "bowl": ("cup",),
    "vase": ("bottle", "cup"),
    "bottle": ("vase", "wine glass"),
    "wine glass": ("cup", "bottle"),
    "chair": ("couch",),
    "couch": ("chair", "bed"),
    "bed": ("couch",),
    "apple": ("orange",),
    "orange": ("apple",),
    "laptop": ("tv", "keyboard"),
    "tv": ("laptop",),
    "keyboard": ("laptop",),
    "desk": ("dining table",),
    "dining table": ("desk",),
}
"""Labels a COCO detector often gives instead of an object's own (each object keeps its own when absent)."""

PART_KEPT = (0.45, 0.8)
"""A part box keeps this share (uniform) of the whole box's height or width, from one of its sides."""


def confused(label: str, rng: np.random.Generator, rate: float) -> str:
    """``label``, or with probability ``rate`` one of ``CONFUSED_WITH[label]`` (uniform)."""
    if rate <= 0.0 or rng.random() >= rate or label not in CONFUSED_WITH:
        return label
    options = CONFUSED_WITH[label]
    return options[int(rng.integers(len(options)))]


def part_box(box: np.ndarray, rng: np.random.Generator, rate: float) -> np.ndarray:
    """``box`` (x1, y1, x2, y2), or with probability ``rate`` the part of it next to one random side (top,
    bottom, left or right) that keeps a uniform ``PART_KEPT`` share of its height or width."""
    if rate <= 0.0 or rng.random() >= rate:
        return box
    side = int(rng.integers(4))
    keep = rng.uniform(*PART_KEPT)
    x1, y1, x2, y2 = (float(v) for v in box)
    if side == 0:  # top part: a chair's backrest, a person's head and shoulders
        y2 = y1 + keep * (y2 - y1)
    elif side == 1:
        y1 = y2 - keep * (y2 - y1)
    elif side == 2:
        x2 = x1 + keep * (x2 - x1)
    else:
        x1 = x2 - keep * (x2 - x1)
    return np.array([x1, y1, x2, y2])
