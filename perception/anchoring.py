"""Which object a detection's depth segment shows: its own, or another detection's in front of its centre.

A segment is anchored at the median depth of its box's centre (``features.segment_anchor``). A box whose centre
another detected object covers (a potted plant before a refrigerator or a couch, standing taller than the couch's
back) is anchored on that object, and its view puts its own object where the other stands: on the development
seeds 0-35, such views made a "couch" or a "refrigerator" on a potted plant and "chairs" on plants. A segment whose
pixels lie in another detection's box, anchored within that one's depths, shows it (``explains``); it is anchored
again on its centre's pixels outside that box (``reanchored``), which are its own object's or none.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from perception.features import (
    AROUND,
    LARGER,
    Box,
    DepthSegment,
    FeatureConfig,
    Segmented,
    box_pixels,
    depth_segment,
    in_box,
    overlap,
    segment_at,
)

EXPLAINED = 0.8
"""A segment with this share of its pixels inside another detection's box shows that one's object
(``anchored_on``)."""


def explains(mine: Segmented, other: DepthSegment, margin_m: float) -> bool:
    """Whether ``other``'s detection is what segment ``mine`` shows: anchored within the other's segment (its
    depths, ``margin_m`` either side: a plant's leaves before a refrigerator's box lie nearer than the plant's own
    anchor), ``EXPLAINED`` of its pixels inside the other's box, and the other's box neither around its own
    (``features.AROUND``) nor far larger (``features.LARGER``): a bottle on a table shows the bottle, whose
    pixels lie in the table's box."""
    rows, cols, own = mine
    if own is None or not other.near - margin_m <= own.anchor <= other.far + margin_m:
        return False
    held, larger = overlap(own.box, other.box)
    if held >= AROUND or larger >= LARGER:
        return False
    return len(rows) > 0 and in_box(rows, cols, other.box).mean() >= EXPLAINED


def anchored_on(found: Sequence[Segmented], labels: Sequence[str], margin_m: float) -> list[list[Box]]:
    """Per detection (its ``depth_segment`` and label), the boxes of the detections of other labels that its
    segment shows rather than its own object (``explains``), unless its own explains theirs as well (one object
    detected twice, under two labels: each keeps its view)."""
    segs = [f[2] for f in found]
    shows = [
        [i != j and labels[i] != labels[j] and s is not None and explains(m, s, margin_m) for j, s in enumerate(segs)]
        for i, m in enumerate(found)
    ]
    return [
        [s.box for j, s in enumerate(segs) if s is not None and shows[i][j] and not shows[j][i]]
        for i in range(len(found))
    ]


def outside(rows: np.ndarray, cols: np.ndarray, boxes: Sequence[Box]) -> np.ndarray:
    """Which pixels (rows, cols) lie in none of ``boxes``."""
    out = np.ones(len(rows), bool)
    for box in boxes:
        out &= ~in_box(rows, cols, box)
    return out


def reanchored(depth_m: np.ndarray, segmented: Segmented, config: FeatureConfig, boxes: Sequence[Box]) -> Segmented:
    """``segmented`` (a box's ``depth_segment``) anchored on its centre's pixels outside ``boxes`` (all its
    pixels outside them when its centre has none); no segment when none is left."""
    rows, cols, own = segmented
    assert own is not None
    every = box_pixels(depth_m, own.box, most=config.pixels)
    cr, cc = box_pixels(depth_m, own.box, config.anchor_fraction, most=config.pixels)
    free = outside(cr, cc, boxes)
    if not free.any():
        (cr, cc), free = every, outside(*every, boxes)
    if not free.any():
        return rows[:0], cols[:0], None
    return segment_at(depth_m, own.box, config, float(np.median(depth_m[cr[free], cc[free]])), every)


def anchored_segments(depth_m: np.ndarray, boxes: Sequence[tuple[Box, str]], config: FeatureConfig) -> list[Segmented]:
    """Each detection's (box, label) ``depth_segment``, anchored again off the detections it shows instead of its
    own object (``anchored_on``)."""
    found = [depth_segment(depth_m, box, config, label) for box, label in boxes]
    under = anchored_on(found, [label for _, label in boxes], config.gap_m)
    return [reanchored(depth_m, f, config, u) if u else f for f, u in zip(found, under, strict=True)]
