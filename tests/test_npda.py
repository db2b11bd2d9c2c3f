"""NPDA (SPEC 6.2): Mann-Whitney U, ties and p-value against scipy; batched U; gates; assignment; tracks."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import mannwhitneyu, norm

from perception.camera import Intrinsics
from perception.frame import Detection
from perception.npda import (
    NPDAConfig,
    assign,
    associate,
    association_matrix,
    association_score,
    box_samples,
    is_compatible,
    mann_whitney,
    out_of_view_scores,
    u_statistics,
)
from perception.tracks import Tracker
from perception.warp import moved_box_points


def _scipy(x: np.ndarray, y: np.ndarray, continuity: bool) -> tuple[float, float]:
    """scipy's U counting x < y (its statistic for (y, x)) and its asymptotic two-sided p-value."""
    r = mannwhitneyu(y, x, alternative="two-sided", method="asymptotic", use_continuity=continuity)
    return float(r.statistic), float(r.pvalue)


def test_u_and_p_value_match_scipy_without_ties() -> None:
    rng = np.random.default_rng(0)
    x, y = rng.normal(2.0, 0.1, 57), rng.normal(2.03, 0.1, 43)
    mw = mann_whitney(x, y)
    u, p = _scipy(x, y, continuity=False)
    assert mw.u == u
    assert mw.mean == 57 * 43 / 2
    assert mw.var == pytest.approx(57 * 43 * 101 / 12)
    assert association_score(mw.u, mw.mean, mw.var) == pytest.approx(p, rel=1e-12)


def test_tie_correction_and_p_value_match_scipy_with_many_ties() -> None:
    rng = np.random.default_rng(1)
    x, y = np.round(rng.normal(2.0, 0.02, 120), 2), np.round(rng.normal(2.005, 0.02, 90), 2)
    mw = mann_whitney(x, y)
    u, p = _scipy(x, y, continuity=False)
    _, counts = np.unique(np.concatenate([x, y]), return_counts=True)
    assert counts.max() > 10  # heavily tied
    tc = np.sum(counts**3.0 - counts) / (210 * (210**2 - 1))
    assert mw.u == u
    assert mw.var == pytest.approx(120 * 90 * 211 / 12 * (1 - tc))
    assert association_score(mw.u, mw.mean, mw.var) == pytest.approx(p, rel=1e-12)


def test_score_is_the_no_continuity_p_value_not_the_corrected_one() -> None:
    rng = np.random.default_rng(2)
    x, y = rng.normal(0, 1, 30), rng.normal(0.4, 1, 30)
    mw = mann_whitney(x, y)
    _, p_plain = _scipy(x, y, continuity=False)
    _, p_corrected = _scipy(x, y, continuity=True)
    score = float(association_score(mw.u, mw.mean, mw.var))
    assert score == pytest.approx(p_plain, rel=1e-12)
    assert abs(score - p_corrected) > 1e-4


def test_batched_u_statistics_equal_pairwise_mann_whitney() -> None:
    rng = np.random.default_rng(3)
    prev = [rng.integers(1000, 1100, n) for n in (40, 25, 60)]
    cur = [rng.integers(1020, 1120, n) for n in (30, 50)]
    u, mean, var = u_statistics(prev, cur)
    for p, a in enumerate(prev):
        for k, b in enumerate(cur):
            mw = mann_whitney(b, a)  # eq. 2.4: current samples below previous ones
            assert u[p, k] == pytest.approx(mw.u)
            assert mean[p, k] == pytest.approx(mw.mean)
            assert var[p, k] == pytest.approx(mw.var)


def test_compatibility_interval_agrees_with_score_below_the_mean() -> None:
    mean, var = 500.0, 2500.0  # sd 50
    for u in (480.0, 430.0, 400.0, 360.0):
        score = float(association_score(u, mean, var))
        for c in (0.80, 0.90, 0.95, 0.99):
            assert is_compatible(u, mean, var, c) == (score >= 1 - c - 1e-12)
    z90 = float(norm.ppf(0.95))  # eq. 2.13's 1.645
    assert is_compatible(mean + 1.0 + z90 * 50 - 1e-6, mean, var, 0.90)  # the upper bound carries eq. 2.13's +1
    assert not is_compatible(mean + 1.0 + z90 * 50 + 1e-3, mean, var, 0.90)
    assert not is_compatible(mean - z90 * 50 - 1e-3, mean, var, 0.90)


def test_one_to_one_assignment_vs_per_column_argmax() -> None:
    scores = np.array([[0.9, 0.8], [0.0, 0.5]])
    assert sorted(assign(scores, NPDAConfig(alpha=0.1))) == [(0, 0), (1, 1)]
    assert sorted(assign(scores, NPDAConfig(alpha=0.1, one_to_one=False))) == [(0, 0), (0, 1)]


def test_one_to_one_assignment_follows_the_moved_boxes_where_depths_cannot_tell_a_row_apart() -> None:
    """Three chairs in a row at one depth: A ranks the neighbours higher by chance; the previous boxes, moved
    into the current image, overlap their own chairs' boxes most."""
    scores = np.array([[0.40, 0.90, 0.00], [0.85, 0.50, 0.95], [0.00, 0.90, 0.30]])
    overlaps = np.array([[0.70, 0.25, 0.00], [0.22, 0.75, 0.21], [0.00, 0.24, 0.65]])
    config = NPDAConfig(alpha=0.1)
    assert config.rank_by == "overlap"
    assert sorted(assign(scores, config, overlaps)) == [(0, 0), (1, 1), (2, 2)]
    by_score = sorted(assign(scores, replace(config, rank_by="score"), overlaps))
    assert by_score == [(0, 1), (1, 0), (2, 2)] or by_score == [(0, 0), (1, 2), (2, 1)]
    assert sorted(assign(scores, config)) == by_score  # no moved boxes: A alone


def test_assignment_by_overlap_keeps_alpha_and_lets_a_break_ties() -> None:
    scores = np.array([[0.05, 0.60], [0.50, 0.20]])
    overlaps = np.array([[0.90, 0.00], [0.00, 0.00]])  # row 1's box left the image: no overlap anywhere
    pairs = sorted(assign(scores, NPDAConfig(alpha=0.1), overlaps))
    assert pairs == [(0, 1), (1, 0)]  # (0, 0) overlaps most but fails alpha; row 1 goes by A


def test_assignment_drops_pairs_below_alpha() -> None:
    scores = np.array([[0.04, 0.0], [0.0, 0.3]])
    assert assign(scores, NPDAConfig(alpha=0.05)) == [(1, 1)]
    assert assign(np.zeros((0, 3)), NPDAConfig()) == []


def _two_object_depth(seed: int) -> np.ndarray:
    """60x80 depth: wall at 3 m, object A at 1.2 m (left), object B at 2.0 m (right), mm-quantised noise."""
    rng = np.random.default_rng(seed)
    d = np.full((60, 80), 3.0, np.float32)
    d[10:40, 5:30] = 1.2 + 0.05 * np.linspace(0, 1, 25)[None, :]
    d[15:45, 45:75] = 2.0 + 0.05 * np.linspace(0, 1, 30)[None, :]
    return np.round(d + rng.normal(0, 0.002, d.shape), 3).astype(np.float32)


def test_association_matrix_separates_objects_and_applies_gates() -> None:
    prev = [Detection("chair", 0.9, (5, 10, 30, 40)), Detection("chair", 0.9, (45, 15, 75, 45))]
    cur = [Detection("chair", 0.9, (46, 14, 74, 45)), Detection("cup", 0.9, (6, 11, 30, 40))]
    dp, dc = _two_object_depth(0), _two_object_depth(1)
    cfg = NPDAConfig(class_gate=False, min_iou=0.0)
    A = association_matrix(prev, dp, cur, dc, cfg)
    assert A[1, 0] > 0.05 and A[0, 1] > 0.05
    assert A[0, 0] < 1e-6 and A[1, 1] < 1e-6
    gated = association_matrix(prev, dp, cur, dc, NPDAConfig(min_iou=0.0))
    assert gated[0, 1] == 0.0  # chair vs cup
    boxes_far = np.array([[0, 0, 4, 4], [45, 15, 75, 45]], float)
    box_gated = association_matrix(prev, dp, cur, dc, NPDAConfig(class_gate=False, min_iou=0.3), boxes_far)
    assert box_gated[0, 1] == 0.0 and box_gated[1, 0] == A[1, 0]


def test_box_samples_are_bounded_and_deterministic() -> None:
    d = _two_object_depth(0)
    cfg = NPDAConfig(max_samples=40)
    a = box_samples(d, (0, 0, 80, 60), cfg)
    assert len(a) == 40 and np.array_equal(a, box_samples(d, (0, 0, 80, 60), cfg))
    assert len(box_samples(d, (np.nan, 0, 10, 10), cfg)) == 0


def test_tracks_follow_association_chains_and_keep_ids() -> None:
    tracker = Tracker()
    first = tracker.update(0, ["cup", "chair"], [])
    second = tracker.update(1, ["chair", "cup", "tv"], [(1, 0), (0, 1)])
    third = tracker.update(2, ["tv", "book"], [(2, 0)])
    assert second[:2] == [first[1], first[0]]
    assert third[0] == second[2] and len(set(first + third)) == 4
    assert tracker.associated(third[0]) and tracker.associated(first[0])
    assert not tracker.associated(third[1])


def _side_by_side_views(seed: int = 0) -> tuple[Intrinsics, np.ndarray, np.ndarray, np.ndarray]:
    """One 2 m deep object seen from two cameras 1.2 m apart along x: the previous camera sees the part at
    x in [1.0, 1.8] m (current camera frame), which lies right of the current image; the current one sees the
    part at x in [0.3, 0.9] m. Returns K, T_cur_prev, previous depth, current depth."""
    K = Intrinsics(500.0, 500.0, 320.0, 240.0)
    rng = np.random.default_rng(seed)
    prev, cur = np.full((480, 640), np.nan), np.full((480, 640), np.nan)
    prev[200:300, 270:470] = 2.0 + 0.005 * rng.standard_normal((100, 200))  # x_prev in [-0.2, 0.6]
    cur[200:300, 395:545] = 2.0 + 0.005 * rng.standard_normal((100, 150))  # x_cur in [0.3, 0.9]
    T = np.eye(4)
    T[0, 3] = 1.2  # p_cur = p_prev + (1.2, 0, 0)
    return K, T, prev, cur


def test_an_object_whose_seen_part_leaves_the_image_is_associated_by_its_moved_depths() -> None:
    K, T, prev, cur = _side_by_side_views()
    chair = [Detection("chair", 0.9, (270.0, 200.0, 470.0, 300.0))]
    current = [
        Detection("chair", 0.9, (395.0, 200.0, 545.0, 300.0)),
        Detection("tv", 0.9, (395.0, 200.0, 545.0, 300.0)),
    ]
    config = NPDAConfig()
    result = associate(chair, prev, current, cur, K, T, config)
    assert result.warped and result.pairs == [(0, 0)] and result.scores[0, 1] == 0.0  # class gate holds
    assert associate(chair, prev, current, cur, K, T, replace(config, out_of_view_gap_m=None)).pairs == []
    far = np.eye(4)
    far[0, 3] = 2.2  # the seen part now lies 1.1 m right of the current one: beyond the 0.5 m gap
    assert associate(chair, prev, current, cur, K, far, config).pairs == []
    rows = out_of_view_scores(["chair"], [moved_box_points(chair[0].box, prev, K, T)], current, cur, K, config)
    assert list(rows) == [0] and rows[0][0] >= config.alpha


def test_the_out_of_view_test_also_compares_heights_when_the_two_seen_parts_lie_at_different_depths() -> None:
    """The current view sees a part of the object 0.4 m deeper than the part the previous view saw, over the
    same heights (rows scaled by depth): the depth test rejects the pair, the height test accepts it."""
    K, T, prev, _ = _side_by_side_views()
    rng = np.random.default_rng(1)
    cur = np.full((480, 640), np.nan)
    cur[173:290, 395:545] = 2.4 + 0.005 * rng.standard_normal((117, 150))  # y in [-0.16, 0.24] m, as before
    chair = [Detection("chair", 0.9, (270.0, 200.0, 470.0, 300.0))]
    current = [Detection("chair", 0.9, (395.0, 173.0, 545.0, 290.0))]
    config = NPDAConfig()
    assert config.out_of_view_height
    assert associate(chair, prev, current, cur, K, T, config).pairs == [(0, 0)]
    depth_only = associate(chair, prev, current, cur, K, T, replace(config, out_of_view_height=False))
    assert depth_only.pairs == [] and depth_only.scores[0, 0] < config.alpha
    lower = np.full((480, 640), np.nan)  # the same deeper part, but 0.3 m lower: nothing matches
    lower[235:352, 395:545] = cur[173:290, 395:545]
    moved_down = [Detection("chair", 0.9, (395.0, 235.0, 545.0, 352.0))]
    assert associate(chair, prev, moved_down, lower, K, T, config).pairs == []
