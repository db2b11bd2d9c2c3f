"""Non-parametric data association, NPDA (Sec. 2.3, 2.4.2, Algorithm 1, SPEC 6.2).

Detections of the previous keyframe (rows l) and the current one (columns k) are compared by the
Mann-Whitney U test on their boxes' depth samples. The association score A(l, k) is the two-sided
p-value of U under the normal approximation with tie correction (eqs. 2.11-2.13): the pair is compatible
at confidence c when U lies in [E(U) - z_c sqrt(Var U), 1 + E(U) + z_c sqrt(Var U)], so A = 1 - the
smallest such c. Pairs with A >= alpha are candidates; the assignment is one-to-one or, as in Algorithm 1
line 16, the per-column argmax. One-to-one, it maximises how much each previous box, moved into the current
image, overlaps its current box (``NPDAConfig.rank_by``), A breaking ties: same-class objects side by side (a
row of chairs) have depths alike, so A ranks them by chance. Hungarian on -A, as the thesis does, joined
neighbouring chairs in one track in 12 % of the chairs' associations on development seeds 7, 15 and 23 (true
poses; 187 of 1604); ranked by overlap, in 1 % (21 of 1610).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal, cast

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment
from scipy.special import erfc, ndtri
from scipy.stats import rankdata

from perception.camera import Intrinsics
from perception.features import Box, box_window, stride_subsample
from perception.frame import Detection
from perception.warp import MIN_Z_M, image_boxes, in_view, moved_box_points, needs_warp, warp_depth

log = logging.getLogger(__name__)


RankBy = Literal["overlap", "score"]
"""What NPDA's one-to-one assignment maximises (``NPDAConfig.rank_by``)."""


@dataclass(frozen=True)
class NPDAConfig:
    """NPDA choices; defaults from `objslam bench association` (docs/benchmarks.md, ablation table)."""

    alpha: float = 0.01
    """Minimum association score (two-sided p-value of U) of a candidate pair, SPEC range [0.01, 0.20]."""
    max_samples: int = 50
    """Depth samples per box (regular pixel lattice, then stride; deterministic): bounds the test's power and cost."""
    min_samples: int = 10
    """Boxes with fewer valid depth samples take part in no association."""
    box_fraction: float = 1.0
    """Central fraction (per side) of each box whose depth is sampled; 1.0 = the whole box."""
    quantum_m: float = 0.001
    """Depths are compared at this resolution (the sensor's millimetre), which defines the ties of eq. 2.12."""
    class_gate: bool = True
    """Only detections with the same class label can be associated."""
    one_to_one: bool = True
    """Hungarian assignment; False = per-column argmax of A as in Algorithm 1 (one previous may match many)."""
    rank_by: RankBy = "overlap"
    """What the one-to-one assignment maximises over the candidates (A >= alpha): "overlap", the moved previous
    box's overlap with the current box (``overlap``), A breaking ties (module docstring); "score", A (the
    thesis's Hungarian on -A)."""
    min_iou: float = 0.2
    """Box gate: overlap of the previous box moved into the current image with the current box; 0 disables it."""
    overlap: str = "iou"
    """Box gate overlap measure: "iou", or "iomin" (intersection over the smaller box: kinder to partial views)."""
    warp_tau: float = 0.01
    """Warp the previous depth when the relative translation exceeds this (m), eq. 2.16."""
    warp_phi: float = 0.01
    """... or when the relative rotation angle exceeds this (rad), eq. 2.16."""
    warp_step: int = 2
    """Warp every ``warp_step``-th pixel (splatted 2x2): 4x cheaper; measured by `objslam bench association`."""
    covisible_only: bool = True
    """With warping, sample only pixels valid in both the warped and the current depth (the co-visible part)."""
    out_of_view_gap_m: float | None = 0.6
    """A previous box whose object points mostly leave the current image after warping (no co-visible part:
    the large motions of Table 2.2) is also tested with its points' depths in the current camera, against
    current boxes whose points come within this gap (m, between the two point sets' 5-95 % extents: two
    views of one object may show parts over half a metre apart); None = no such test. Measured in
    `objslam bench association` (grid with and without it; 0.6 and 0.75 m gave the same counts in every
    cell, 0.5 m missed a refrigerator seen at opposite image edges, its parts 0.51 m apart)."""
    out_of_view_height: bool = True
    """The out-of-view test also compares the points' heights (camera y) and keeps the larger score: when
    the two views show different parts of an object (its left end, then its right end), their depths differ
    but their heights do not."""


@dataclass(frozen=True)
class MannWhitney:
    """U statistic of eq. 2.4 (ties count 1/2) with its mean and tie-corrected variance (eqs. 2.11, 2.12)."""

    u: float
    mean: float
    var: float


@dataclass(frozen=True)
class Association:
    """NPDA result between two keyframes: matched (previous, current) index pairs and the score matrix."""

    pairs: list[tuple[int, int]]
    scores: np.ndarray
    warped: bool


def mann_whitney(x: np.ndarray, y: np.ndarray) -> MannWhitney:
    """U = #{x < y} + #{x = y} / 2 from the ranks of the pooled samples, with tie correction (eqs. 2.4, 2.11-2.12)."""
    m, n = len(x), len(y)
    pooled = np.concatenate([x, y])
    ranks = rankdata(pooled)
    u = float(ranks[m:].sum()) - n * (n + 1) / 2.0  # rank sum of y minus its minimum counts x < y
    _, t = np.unique(pooled, return_counts=True)
    big_n = m + n
    tc = float(np.sum(t.astype(float) ** 3 - t)) / (big_n * (big_n**2 - 1.0)) if big_n > 1 else 0.0
    return MannWhitney(u, m * n / 2.0, m * n * (big_n + 1) / 12.0 * (1.0 - tc))


def association_score(u: np.ndarray | float, mean: np.ndarray | float, var: np.ndarray | float) -> np.ndarray:
    """Two-sided normal-approximation p-value of U, the association score A (SPEC 6.2), vectorised."""
    u, mean, var = np.asarray(u, float), np.asarray(mean, float), np.asarray(var, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.abs(u - mean) / np.sqrt(var)
    z = np.where(var > 0, z, np.where(u == mean, 0.0, np.inf))
    return erfc(z / np.sqrt(2.0))


def is_compatible(u: float, mean: float, var: float, confidence: float) -> bool:
    """U inside [E - z_c sqrt(Var), 1 + E + z_c sqrt(Var)] at confidence c (eqs. 2.10, 2.13)."""
    z = float(ndtri(0.5 + confidence / 2.0))
    s = np.sqrt(var)
    return bool(mean - z * s <= u <= 1.0 + mean + z * s)


def box_samples(depth_m: np.ndarray, box: Sequence[float], config: NPDAConfig) -> np.ndarray:
    """Quantised depth samples (int, units of ``quantum_m``) of a box's central part, deterministic.

    The box is read on a regular pixel lattice of about 4 x ``max_samples`` points, and the valid ones
    are thinned by stride to at most ``max_samples``: cost O(max_samples), not O(box area).
    """
    win = box_window(depth_m.shape, cast(Box, tuple(box)), config.box_fraction) if np.all(np.isfinite(box)) else None
    if win is None:
        return np.zeros(0, np.int64)
    y1, y2, x1, x2 = win
    step = max(1, int(np.sqrt((y2 - y1) * (x2 - x1) / (4.0 * config.max_samples))))
    patch = depth_m[y1:y2:step, x1:x2:step]
    values = patch[np.isfinite(patch)]
    values = values[stride_subsample(len(values), config.max_samples)]
    return np.rint(values / config.quantum_m).astype(np.int64)


def u_statistics(prev: Sequence[np.ndarray], cur: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
    """U, E(U), Var(U) for every (previous l, current k) pair at once from pooled dense ranks (eqs. 2.4, 2.11-2.12).

    One sort of all samples gives each value its dense rank v; with per-box histograms P[l, v] and
    C[k, v], U[l, k] = sum_v C[k, v] (#prev_l > v + P[l, v] / 2) and the tie sum of eq. 2.12 is
    sum_v (P + C)^3 - (P + C), both expanded into matrix products.
    """
    m = np.array([len(s) for s in prev], float)
    n = np.array([len(s) for s in cur], float)
    if len(prev) == 0 or len(cur) == 0 or m.sum() == 0 or n.sum() == 0:
        z = np.zeros((len(prev), len(cur)))
        return z, z.copy(), z.copy()
    _, dense = np.unique(np.concatenate([*prev, *cur]), return_inverse=True)
    v = int(dense.max()) + 1
    owner = np.repeat(np.arange(len(prev) + len(cur)), np.concatenate([m, n]).astype(np.int64))
    hist = np.bincount(owner * v + dense, minlength=(len(prev) + len(cur)) * v).reshape(-1, v).astype(float)
    P, C = hist[: len(prev)], hist[len(prev) :]
    above = m[:, None] - np.cumsum(P, axis=1)
    u = (above + 0.5 * P) @ C.T
    ties = (
        (P**3).sum(1)[:, None]
        + (C**3).sum(1)[None, :]
        + 3.0 * (P**2) @ C.T
        + 3.0 * P @ (C**2).T
        - m[:, None]
        - n[None, :]
    )
    big_n = m[:, None] + n[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = np.where(big_n > 1, ties / (big_n * (big_n**2 - 1.0)), 0.0)
    mn = m[:, None] * n[None, :]
    return u, mn / 2.0, mn * (big_n + 1.0) / 12.0 * (1.0 - tc)


def box_iou(a: ArrayLike, b: ArrayLike, over: str = "iou") -> np.ndarray:
    """Overlap matrix (L, K) of boxes a (L, 4) and b (K, 4): IoU, or intersection over the smaller ("iomin")."""
    a, b = np.asarray(a, float).reshape(-1, 4), np.asarray(b, float).reshape(-1, 4)
    iw = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    ih = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    area_a = ((a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]))[:, None]
    area_b = ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]))[None, :]
    denom = np.minimum(area_a, area_b) if over == "iomin" else area_a + area_b - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = inter / denom
    return np.nan_to_num(ratio, nan=0.0)  # NaN boxes overlap nothing


def association_matrix(
    prev_dets: Sequence[Detection],
    prev_depth: np.ndarray,
    cur_dets: Sequence[Detection],
    cur_depth: np.ndarray,
    config: NPDAConfig,
    prev_boxes_in_cur: np.ndarray | None = None,
) -> np.ndarray:
    """Association matrix A (L, K) of eq. 2.1: p-values of U with class and box gates applied (zero = gated)."""
    ps = [box_samples(prev_depth, d.box, config) for d in prev_dets]
    cs = [box_samples(cur_depth, d.box, config) for d in cur_dets]
    ps = [s if len(s) >= config.min_samples else s[:0] for s in ps]
    cs = [s if len(s) >= config.min_samples else s[:0] for s in cs]
    u, mean, var = u_statistics(ps, cs)
    score = association_score(u, mean, var)
    valid = np.array([len(s) > 0 for s in ps], bool)[:, None] & np.array([len(s) > 0 for s in cs], bool)[None, :]
    if config.class_gate:
        prev_labels = np.array([d.label for d in prev_dets], object)
        valid &= prev_labels[:, None] == np.array([d.label for d in cur_dets], object)[None, :]
    if config.min_iou > 0 and prev_boxes_in_cur is not None:
        valid &= box_iou(prev_boxes_in_cur, [d.box for d in cur_dets], config.overlap) >= config.min_iou
    return np.where(valid, score, 0.0).reshape(len(prev_dets), len(cur_dets))


TIE_WEIGHT = 1e-3
"""A's weight beside the boxes' overlap (at most 1) in the assignment ranked by overlap: a tie-break."""


def assign(scores: np.ndarray, config: NPDAConfig, overlaps: np.ndarray | None = None) -> list[tuple[int, int]]:
    """Matched (previous, current) pairs with A >= alpha: one-to-one (Hungarian) maximising the moved previous
    boxes' ``overlaps`` with the current ones (L, K) when given and ``config.rank_by`` is "overlap", else A; or
    per-column argmax of A (Algorithm 1)."""
    if scores.size == 0:
        return []
    if config.one_to_one:
        if overlaps is not None and config.rank_by == "overlap":
            candidate = (scores >= config.alpha) & (scores > 0)
            rows, cols = linear_sum_assignment(-np.where(candidate, overlaps + TIE_WEIGHT * scores, 0.0))
        else:
            rows, cols = linear_sum_assignment(-scores)
    else:
        cols = np.arange(scores.shape[1])
        rows = np.argmax(scores, axis=0)
    return [
        (int(r), int(c)) for r, c in zip(rows, cols, strict=True) if scores[r, c] >= config.alpha and scores[r, c] > 0
    ]


def associate(
    prev_dets: Sequence[Detection],
    prev_depth: np.ndarray,
    cur_dets: Sequence[Detection],
    cur_depth: np.ndarray,
    K: Intrinsics,
    T_cur_prev: np.ndarray | None,
    config: NPDAConfig,
) -> Association:
    """Algorithm 2 lines 4-7: warp the previous depth when motion is large (eq. 2.16), then NPDA and assignment.

    ``T_cur_prev`` maps previous-camera points into the current camera; None = unknown motion (no warp,
    the box gate then compares the raw boxes).
    """
    warped = T_cur_prev is not None and needs_warp(T_cur_prev, config.warp_tau, config.warp_phi)
    labels, measured_cur_depth = [d.label for d in prev_dets], cur_depth  # for the out-of-view test
    moved, moved_points = None, []
    if T_cur_prev is not None and (warped or config.min_iou > 0):
        moved_points = [moved_box_points(d.box, prev_depth, K, T_cur_prev) for d in prev_dets]
        moved = image_boxes(moved_points, K, prev_depth.shape[1], prev_depth.shape[0])
    elif config.min_iou > 0:
        moved = np.array([d.box for d in prev_dets], float).reshape(-1, 4)
    if warped:
        assert T_cur_prev is not None and moved is not None  # warped: the motion is known and the boxes moved
        prev_depth = warp_depth(prev_depth, K, T_cur_prev, step=config.warp_step)
        prev_dets = [replace(d, box=tuple(b)) for d, b in zip(prev_dets, moved, strict=True)]
        if config.covisible_only:
            both = np.isfinite(prev_depth) & np.isfinite(cur_depth)
            prev_depth, cur_depth = np.where(both, prev_depth, np.nan), np.where(both, cur_depth, np.nan)
    scores = association_matrix(prev_dets, prev_depth, cur_dets, cur_depth, config, moved)
    if warped and config.out_of_view_gap_m is not None:
        for row, values in out_of_view_scores(labels, moved_points, cur_dets, measured_cur_depth, K, config).items():
            scores[row] = np.maximum(scores[row], values)  # the warped test where it could run
    overlaps = None if moved is None else box_iou(moved, [d.box for d in cur_dets], config.overlap)
    return Association(assign(scores, config, overlaps), scores, warped)


def _extent(points: np.ndarray) -> np.ndarray:
    """(2, 3) robust axis-aligned extent (5th and 95th percentile per axis) of a point set."""
    return np.percentile(points, [5.0, 95.0], axis=0)


def _quantised(values_m: np.ndarray, config: NPDAConfig) -> np.ndarray:
    return np.rint(values_m / config.quantum_m).astype(np.int64)


def out_of_view_scores(
    prev_labels: Sequence[str],
    prev_points: Sequence[np.ndarray],
    cur_dets: Sequence[Detection],
    cur_depth: np.ndarray,
    K: Intrinsics,
    config: NPDAConfig,
) -> dict[int, np.ndarray]:
    """Rows of A for the previous boxes whose object points (``prev_points``: moved into the current camera,
    ``moved_box_points``) mostly leave the current image.

    Warping cannot test them: what the previous keyframe saw of the object is outside the current view. The
    U test then compares the depths of those points in the current camera with each current box's depth
    samples, gated by class and by 3D proximity: the gap between the two point sets' robust extents must
    not exceed ``out_of_view_gap_m``.
    """
    h, w = cur_depth.shape
    rows: dict[int, np.ndarray] = {}
    gap_m = config.out_of_view_gap_m
    if gap_m is None:  # no out-of-view test
        return rows
    current = None
    for row, (label, points) in enumerate(zip(prev_labels, prev_points, strict=True)):
        points = points[points[:, 2] > MIN_Z_M]
        if len(points) < config.min_samples or in_view(points, K, w, h).mean() >= 0.5:
            continue
        if current is None:
            current = []
            for d in cur_dets:
                pts = moved_box_points(d.box, cur_depth, K, np.eye(4))
                s = box_samples(cur_depth, d.box, config)
                enough = len(pts) >= config.min_samples and len(s) >= config.min_samples
                current.append(
                    (
                        _extent(pts) if enough else None,
                        s if enough else s[:0],
                        _quantised(pts[stride_subsample(len(pts), config.max_samples), 1], config),
                    )
                )
        z = points[stride_subsample(len(points), config.max_samples)]
        u, mean, var = u_statistics([_quantised(z[:, 2], config)], [c[1] for c in current])
        score = association_score(u, mean, var)[0]
        if config.out_of_view_height:
            u, mean, var = u_statistics([_quantised(z[:, 1], config)], [c[2] for c in current])
            score = np.maximum(score, association_score(u, mean, var)[0])
        lo, hi = _extent(points)
        valid = np.zeros(len(cur_dets), bool)
        for k, (extent, s, _) in enumerate(current):
            if extent is None or len(s) == 0 or (config.class_gate and cur_dets[k].label != label):
                continue
            gap = np.maximum(0.0, np.maximum(lo - extent[1], extent[0] - hi))
            valid[k] = float(np.linalg.norm(gap)) <= gap_m
        rows[row] = np.where(valid, score, 0.0)
    return rows
