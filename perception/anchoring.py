"""Which object a detection's depth segment shows: its own, or another detection's in front of its centre.

A segment is anchored at the median depth of its box's centre (``features.segment_anchor``). A box whose centre
another detected object covers (a potted plant before a refrigerator or a couch, standing taller than the couch's
back) is anchored on that object, and its view puts its own object where the other stands: on the development
seeds 0-35, such views made a "couch" or a "refrigerator" on a potted plant and "chairs" on plants. A segment whose
pixels lie in another detection's box, anchored within that one's depths, shows it (``explains``); it is anchored
again on its centre's pixels outside that box (``reanchored``), which are its own object's or none. This holds
for detections of one class too: in a row of chairs seen along the row, the front chair covers the centre of
every box behind it, and the back chairs' views put them where the front one stands (development seed 15: the
views of chairs at x = 1.25, 1.73 and 2.20 m lay at 2.12, 2.56 and 2.69 m, the front chair at 2.68 m).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from perception.coco import FLOOR_CLASSES
from perception.features import (
    AROUND,
    BEYOND,
    LARGER,
    Box,
    FeatureConfig,
    Segmented,
    box_pixels,
    depth_segment,
    in_box,
    segment_at,
)
from perception.pixel_grid import grid_of

EXPLAINED = 0.8
"""A segment with this share of its pixels inside another detection's box shows that one's object
(``anchored_on``)."""


class PixelCounts:
    """How many of a segment's pixels (rows, cols) lie inside boxes, in constant time per box: a summed-area
    table over the regular grid the pixels lie on (``pixel_grid``).
    Built once per segment, so testing every pair of N detections costs N tables and N^2 lookups, not N^2 passes
    over the pixels."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray) -> None:
        self.r0, self.c0, self.step = 0, 0, 1
        self.table = np.zeros((1, 1), np.int64)
        if len(rows) == 0:
            return
        self.r0, self.c0, self.step, gr, gc = grid_of(rows, cols)
        shape = (int(gr.max()) + 1, int(gc.max()) + 1)
        grid = np.bincount(gr * shape[1] + gc, minlength=shape[0] * shape[1]).reshape(shape)
        self.table = np.zeros((shape[0] + 1, shape[1] + 1), np.int64)
        self.table[1:, 1:] = grid.cumsum(0).cumsum(1)

    def inside(self, boxes: np.ndarray) -> np.ndarray:
        """How many of the pixels ``features.in_box`` counts inside each box (rows of x1, y1, x2, y2)."""
        boxes = np.asarray(boxes, float).reshape(-1, 4)
        h, w = self.table.shape[0] - 1, self.table.shape[1] - 1
        # the grid cells whose pixel satisfies x1 <= col < x2 (and likewise rows): from ceil((x1 - c0) / step)
        # on, up to but not including ceil((x2 - c0) / step)
        cols = np.clip(np.ceil((boxes[:, [0, 2]] - self.c0) / self.step), 0, w).astype(int)
        rows = np.clip(np.ceil((boxes[:, [1, 3]] - self.r0) / self.step), 0, h).astype(int)
        cols[:, 1], rows[:, 1] = np.maximum(cols[:, 1], cols[:, 0]), np.maximum(rows[:, 1], rows[:, 0])
        (a1, a2), (b1, b2), t = cols.T, rows.T, self.table
        return t[b2, a2] - t[b1, a2] - t[b2, a1] + t[b1, a1]


def explains(found: Sequence[Segmented], margin_m: float, standing: Sequence[bool] = ()) -> np.ndarray:
    """Which detection's object each segment shows (``[i, j]``: segment ``i`` shows detection ``j``'s): anchored
    within ``j``'s segment (its depths, ``margin_m`` either side: a plant's leaves before a refrigerator's box lie
    nearer than the plant's own anchor), ``EXPLAINED`` of its pixels inside ``j``'s box, and ``j``'s box neither
    around its own (``features.AROUND``) nor far larger (``features.LARGER``): a bottle on a table shows the
    bottle, whose pixels lie in the table's box. The box tests run on all pairs at once, the pixel counts
    (``PixelCounts``) only on the pairs they leave: a pass over the pixels per pair cost 0.50-0.54 s per keyframe for
    100 overlapping detections. ``standing`` (per detection): its object stands on the floor
    (``coco.FLOOR_CLASSES``), so nothing is under it, and a box around it or far larger shows what stands before
    it when its anchor lies beyond that one's (``BEYOND``): a chair behind a couch, out of the depth sensor's
    range, whose box holds only the couch's depth, showed a chair on the couch."""
    n = len(found)
    shows = np.zeros((n, n), bool)
    picked = [(k, seg) for k, (rows, _, seg) in enumerate(found) if seg is not None and len(rows) > 0]
    valid, segs = [k for k, _ in picked], [seg for _, seg in picked]
    if len(segs) < 2:
        return shows
    box = np.array([s.box for s in segs], float)
    anchor, near, far = (np.array([getattr(s, name) for s in segs]) for name in ("anchor", "near", "far"))
    area = np.maximum((box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1]), 1e-9)
    x1, y1 = np.maximum(box[:, None, 0], box[None, :, 0]), np.maximum(box[:, None, 1], box[None, :, 1])
    x2, y2 = np.minimum(box[:, None, 2], box[None, :, 2]), np.minimum(box[:, None, 3], box[None, :, 3])
    held = np.clip(x2 - x1, 0.0, None) * np.clip(y2 - y1, 0.0, None) / area[:, None]  # as ``features.overlap``
    larger = area[None, :] / area[:, None]
    within = (near[None, :] - margin_m <= anchor[:, None]) & (anchor[:, None] <= far[None, :] + margin_m)
    stands = np.asarray(standing, bool)[valid] if len(standing) else np.zeros(len(segs), bool)
    beyond = stands[:, None] & (anchor[:, None] > anchor[None, :] + BEYOND * margin_m)
    maybe = within & (((held < AROUND) & (larger < LARGER)) | beyond)
    np.fill_diagonal(maybe, False)
    for a in np.flatnonzero(maybe.any(1)):
        rows, cols, _ = found[valid[a]]
        others = np.flatnonzero(maybe[a])
        inside = PixelCounts(rows, cols).inside(box[others])
        shows[valid[a], [valid[b] for b in others]] = inside / len(rows) >= EXPLAINED
    return shows


def anchored_on(found: Sequence[Segmented], margin_m: float, standing: Sequence[bool] = ()) -> list[list[Box]]:
    """Per detection (its ``depth_segment``), the boxes of the other detections that its segment shows rather
    than its own object (``explains``), unless its own shows theirs as well (one object detected twice, under
    two labels: each keeps its view)."""
    shows = explains(found, margin_m, standing)
    only = shows & ~shows.T  # a detection shows only detections with a segment
    boxes = {k: seg.box for k, (_, _, seg) in enumerate(found) if seg is not None}
    return [[boxes[int(j)] for j in np.flatnonzero(row)] for row in only]


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
    under = anchored_on(found, config.gap_m, [label in FLOOR_CLASSES for _, label in boxes])
    return [reanchored(depth_m, f, config, u) if u else f for f, u in zip(found, under, strict=True)]
