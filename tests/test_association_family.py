"""The family association bench's outcome counts (``bench.association_family.pair_outcome``)."""

from __future__ import annotations

from dataclasses import replace

from bench.association_family import RULES, pair_outcome, scene_counts
from perception.frame import Detection
from perception.npda import NPDAConfig


def _chair(x: float) -> Detection:
    return Detection("chair", 0.9, (x, 100.0, x + 60.0, 220.0))


def test_a_swap_joins_two_instances_of_one_class_and_rows_count_the_crowded_keyframes() -> None:
    prev = ([_chair(100.0), _chair(170.0), Detection("cup", 0.8, (400.0, 300.0, 420.0, 330.0))], [5, 6, 9])
    cur = ([_chair(110.0), _chair(180.0), Detection("cup", 0.8, (405.0, 300.0, 425.0, 330.0))], [5, 6, 0])
    right = pair_outcome(prev, cur, [(0, 0), (1, 1)])
    assert (right.tp, right.fp, right.fn, right.swaps, right.rows_tp, right.rows_swaps) == (2, 0, 0, 0, 2, 0)
    swapped = pair_outcome(prev, cur, [(0, 1), (1, 0), (2, 2)])
    # two chairs swapped; the cup joined to a false-positive detection (id 0) is an error but not a swap
    assert (swapped.tp, swapped.fp, swapped.fn, swapped.swaps, swapped.rows_swaps) == (0, 3, 2, 2, 2)
    total = pair_outcome(prev, cur, [])
    total.add(right)
    total.add(swapped)
    assert (total.tp, total.fp, total.fn, total.swaps) == (2, 3, 4, 2)


def test_on_a_row_of_chairs_the_overlap_ranking_keeps_neighbours_apart() -> None:
    """Development seed 15 (a row of chairs 0.48 m apart, seen along it), its first 300 frames' keyframes with the
    true poses: ranked by A alone, NPDA joined neighbours in about one association in seven of the keyframes holding
    two or more of a class; ranked by the moved boxes' overlap, in about one in a hundred."""
    rules = {name: replace(NPDAConfig(), rank_by=name) for name in RULES}
    counts, pairs = scene_counts(15, 300, rules)
    overlap, score = counts["overlap"], counts["score"]
    assert pairs > 50 and overlap.rows_tp > 300
    assert overlap.rows_swaps <= 0.02 * (overlap.rows_tp + overlap.rows_swaps)
    assert score.rows_swaps >= 0.05 * (score.rows_tp + score.rows_swaps)
    assert overlap.tp > score.tp and overlap.swaps < score.swaps
