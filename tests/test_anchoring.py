"""A large object's depth segment anchored on its own surface, not on a smaller object in front of its middle."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from perception.anchoring import PixelCounts, anchored_on, anchored_segments
from perception.features import LARGER, FeatureConfig, depth_segment, in_box, in_front, object_pixels, overlap


def _wall(z: float = 4.0, shape: tuple[int, int] = (60, 80)) -> np.ndarray:
    return np.full(shape, z, np.float32)


def test_a_refrigerator_behind_a_plant_is_anchored_on_itself_not_on_the_plant() -> None:
    """A refrigerator's face 2.4 m away with a potted plant 2.0 m away before its middle: its box's centre shows
    the plant, so its segment alone is the plant's; anchored again off the plant's box it is its own face."""
    depth = _wall()
    depth[5:55, 20:60] = 2.4  # the refrigerator
    depth[20:45, 32:48] = 2.0  # the plant before its middle
    fridge, plant = (20.0, 5.0, 60.0, 55.0), (32.0, 20.0, 48.0, 45.0)
    cfg = FeatureConfig()
    alone = depth_segment(depth, fridge, cfg, "refrigerator")[2]
    assert alone is not None and alone.far < 2.1  # on its own, the box's segment is the plant
    (rows, cols, own), (_, _, small) = anchored_segments(
        depth, [(fridge, "refrigerator"), (plant, "potted plant")], cfg
    )
    assert own is not None and small is not None
    assert abs(own.anchor - 2.4) < 0.01 and own.near > 2.35 and np.all(depth[rows, cols] > 2.35)
    assert len(rows) > 1000  # its face around the plant
    assert abs(small.anchor - 2.0) < 0.01 and small.far < 2.05  # the plant keeps its own


def test_the_back_chair_of_a_row_is_anchored_on_its_own_sides_not_on_the_chair_in_front() -> None:
    """Two chairs seen along their row: the front one 2.0 m away covers the middle of the back one's box, whose
    own surface 3.0 m away shows either side of it. The back box's segment alone is the front chair's; anchored
    again off the front chair's box it is the back chair's."""
    depth = _wall()
    depth[10:50, 30:70] = 3.0  # the back chair
    depth[10:50, 40:60] = 2.0  # the chair in front, before its middle
    front, back = (40.0, 10.0, 60.0, 50.0), (30.0, 10.0, 70.0, 50.0)
    cfg = FeatureConfig()
    alone = depth_segment(depth, back, cfg, "chair")[2]
    assert alone is not None and alone.far < 2.1  # on its own, the back box's segment is the front chair
    (rows, cols, own), (_, _, first) = anchored_segments(depth, [(back, "chair"), (front, "chair")], cfg)
    assert own is not None and first is not None
    assert abs(own.anchor - 3.0) < 0.01 and np.all(depth[rows, cols] > 2.95)
    assert abs(first.anchor - 2.0) < 0.01 and first.far < 2.05  # the front chair keeps its own


def test_a_table_anchored_on_its_own_top_keeps_its_segment_with_a_cup_on_it() -> None:
    """A cup on the far part of a table top: the table's centre shows the table, so nothing changes; nor does a
    box that only touches the table's (not inside it)."""
    depth = _wall()
    depth[30:50, 10:70] = np.linspace(1.8, 2.6, 20)[:, None]  # the table top receding from 1.8 to 2.6 m
    depth[22:30, 50:56] = 2.5  # the cup
    table, cup = (10.0, 22.0, 70.0, 50.0), (50.0, 22.0, 56.0, 31.0)
    cfg = FeatureConfig()
    plain = [depth_segment(depth, b, cfg, label) for b, label in ((table, "dining table"), (cup, "cup"))]
    again = anchored_segments(depth, [(table, "dining table"), (cup, "cup")], cfg)
    for (r0, c0, s0), (r1, c1, s1) in zip(plain, again, strict=True):
        assert s0 == s1 and np.array_equal(r0, r1) and np.array_equal(c0, c1)
    assert plain[0][2] is not None and plain[1][2] is not None
    assert anchored_on(plain, cfg.gap_m) == [[], []]


def test_a_bottle_standing_above_a_tables_box_keeps_its_own_segment() -> None:
    """A bottle on a table top, its top above the table's box: the table's box holds 80 % of the bottle's, not the
    90 % that makes it around it (``AROUND``), but it is far larger (``LARGER``), so the bottle's pixels in it are
    its own."""
    depth = _wall()
    depth[30:50, 10:70] = np.linspace(1.8, 2.6, 20)[:, None]  # the table top
    depth[14:34, 40:46] = 2.0  # the bottle, standing on it and reaching above its box
    table, bottle = (10.0, 18.0, 70.0, 50.0), (40.0, 14.0, 46.0, 34.0)
    cfg = FeatureConfig()
    plain = [depth_segment(depth, b, cfg, label) for b, label in ((table, "dining table"), (bottle, "bottle"))]
    assert plain[1][2] is not None and abs(plain[1][2].anchor - 2.0) < 0.01
    assert anchored_on(plain, cfg.gap_m) == [[], []]
    (_, _, own), _ = anchored_segments(depth, [(bottle, "bottle"), (table, "dining table")], cfg)
    assert own == plain[1][2]


def test_a_box_showing_only_another_detection_gives_no_segment() -> None:
    """A couch whose own surface returns no depth behind a tall plant: every pixel with depth in its box is the
    plant's, so it gives no view of its own; the plant keeps its own."""
    depth = np.full((60, 80), np.nan, np.float32)
    depth[0:60, 25:55] = 2.0  # the plant, taller than the couch's box
    couch, plant = (20.0, 10.0, 60.0, 50.0), (25.0, 0.0, 55.0, 60.0)
    cfg = FeatureConfig()
    out = anchored_segments(depth, [(couch, "couch"), (plant, "potted plant")], cfg)
    assert depth_segment(depth, couch, cfg, "couch")[2] is not None  # alone, it would be the plant's surface
    assert out[0][2] is None and len(out[0][0]) == 0
    assert out[1][2] is not None and abs(out[1][2].anchor - 2.0) < 0.01


def test_one_object_detected_under_two_labels_keeps_both_views() -> None:
    """A chair also detected as a couch, the two boxes nearly the same: each segment lies in the other's box,
    neither is taken for the other's object."""
    depth = _wall()
    depth[10:50, 20:60] = 2.0
    boxes = [((20.0, 10.0, 60.0, 50.0), "chair"), ((21.0, 11.0, 59.0, 50.0), "couch")]
    cfg = FeatureConfig()
    plain = [depth_segment(depth, b, cfg, label) for b, label in boxes]
    assert anchored_on(plain, cfg.gap_m) == [[], []]
    assert all(s is not None for _, _, s in anchored_segments(depth, boxes, cfg))


def _couch_before_a_chair() -> tuple[np.ndarray, tuple[float, ...], tuple[float, ...]]:
    """A couch's back receding from 2.0 to 3.6 m across the image, far larger than the box of a chair behind its
    far end; the chair itself lies beyond the depth sensor's range (no depth)."""
    depth = np.full((60, 80), np.nan, np.float32)
    depth[20:60, 0:80] = np.linspace(2.0, 3.6, 80)[None, :]  # the couch
    return depth, (0.0, 20.0, 80.0, 60.0), (55.0, 10.0, 75.0, 45.0)


def test_a_chair_behind_a_couch_out_of_the_sensors_range_gives_no_view() -> None:
    """Every pixel with depth in the chair's box is the couch's, which holds the box and is far larger: a chair
    stands on the floor, so the couch is not under it and its box shows the couch (no view). A teddy bear's box in
    the same place keeps its segment: it may sit on the couch."""
    depth, couch, chair = _couch_before_a_chair()
    cfg = FeatureConfig()
    alone = depth_segment(depth, chair, cfg, "chair")[2]
    couch_alone = depth_segment(depth, couch, cfg, "couch")[2]
    assert alone is not None and couch_alone is not None and alone.anchor > couch_alone.anchor + 0.1
    out = anchored_segments(depth, [(couch, "couch"), (chair, "chair")], cfg)
    assert out[1][2] is None and len(out[1][0]) == 0
    assert out[0][2] is not None and abs(out[0][2].anchor - couch_alone.anchor) < 1e-6  # the couch keeps its own
    bear = anchored_segments(depth, [(couch, "couch"), (chair, "teddy bear")], cfg)
    assert bear[1][2] == alone


def test_a_chair_behind_a_couch_keeps_only_its_own_pixels() -> None:
    """The chair's backrest 3.53 m away joins the couch's far end in one depth segment: the couch's pixels in its
    box leave (``in_front``, standing), its own stay; for an object that is not floor-standing they stay."""
    depth, couch, chair = _couch_before_a_chair()
    depth[10:20, 55:75] = 3.53  # the chair's backrest above the couch's back
    cfg = FeatureConfig()
    own = depth_segment(depth, couch, cfg, "couch")[2]
    rows, cols, mine = depth_segment(depth, chair, cfg, "chair")
    assert own is not None and mine is not None and depth[rows, cols].min() < 3.4  # joined to the couch
    z = depth[rows, cols]
    out = in_front(z, rows, cols, mine, [own], cfg.gap_m, standing=True)
    assert np.all(z[~out] >= 3.53 - 1e-6) and np.all(z[out] < 3.53) and (~out).sum() == 200
    assert not in_front(z, rows, cols, mine, [own], cfg.gap_m).any()
    kept = object_pixels(depth, chair, cfg, [own], label="chair")
    assert len(kept[0]) == 200 and np.all(depth[kept] == np.float32(3.53))
    assert len(object_pixels(depth, chair, cfg, [own], label="teddy bear")[0]) == len(rows)


@settings(max_examples=300, deadline=None)
@given(
    origin=st.tuples(st.integers(0, 40), st.integers(0, 40)),
    step=st.integers(1, 5),
    shape=st.tuples(st.integers(1, 12), st.integers(1, 12)),
    seed=st.integers(0, 2**32 - 1),
    box=st.tuples(*[st.one_of(st.integers(-10, 110).map(float), st.floats(-10.0, 110.0, allow_nan=False))] * 4),
)
def test_pixel_counts_in_a_box_equal_the_pixels_in_box_finds(origin, step, shape, seed, box) -> None:
    """The summed-area count of a segment's pixels inside a box is ``in_box``'s, for pixels on a strided grid
    (any subset of it, repeats included) and boxes anywhere, fractional, empty or inverted."""
    rng = np.random.default_rng(seed)
    gr, gc = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    pick = rng.integers(0, gr.size, size=rng.integers(1, gr.size + 3))
    rows, cols = origin[0] + step * gr.ravel()[pick], origin[1] + step * gc.ravel()[pick]
    assert PixelCounts(rows, cols).inside(np.array([box]))[0] == int(in_box(rows, cols, box).sum())


def test_a_plant_behind_a_tables_corner_keeps_only_its_own_pixels() -> None:
    """A table top receding from 1.8 to 3.1 m, its box far larger than that of a potted plant 3.12-3.3 m away
    behind its far corner; the corner lies in the plant's box and joins its depth segment. The plant is anchored beyond
    the far end of the table's segment, where nothing standing on the table is: the corner's pixels leave. Not
    being floor-standing does not keep them (``in_front``)."""
    depth = np.full((60, 80), 4.0, np.float32)
    depth[25:60, 0:70] = np.linspace(1.8, 3.1, 70)[None, :]  # the table top, receding to its right
    depth[5:40, 70:78] = np.linspace(3.12, 3.3, 8)[None, :]  # the plant behind the corner, seen at a slant
    table, plant = (0.0, 25.0, 70.0, 60.0), (64.0, 5.0, 78.0, 40.0)
    cfg = FeatureConfig()
    own = depth_segment(depth, table, cfg, "dining table")[2]
    rows, cols, mine = depth_segment(depth, plant, cfg, "potted plant")
    assert own is not None and mine is not None
    z = depth[rows, cols]
    assert overlap(plant, table)[1] > LARGER  # the table's box is far larger
    assert z.min() < 3.05 and mine.anchor > own.far + cfg.gap_m  # the corner joined; the plant beyond the table
    out = in_front(z, rows, cols, mine, [own], cfg.gap_m)
    assert np.all(cols[out] < 70) and np.all(cols[~out] >= 70) and out.any()
