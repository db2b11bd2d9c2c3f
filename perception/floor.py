"""The floor under the map, and objects that stand on it.

A camera looking down at a room (a robot's, a person's) sees the floor in the lower part of most images. Each
keyframe contributes the dominant level plane of its lower half (``level_plane``: camera frame); moved into the
world by the keyframe's pose, the lowest height that many keyframes agree on is the floor and the median
normal of those planes is "up" (``Floor.estimate``). Furniture that stands on the floor (``coco.FLOOR_CLASSES``) then
reaches down to it (``on_floor``): a chair near a downward-looking camera has its legs cut off by the image's
lower edge in every view, and its visible part alone puts its centre 5-10 cm too high. Other objects reach from
the bottom to the top that their views see whole (``vertical_span``); a screen whose top no view sees is as tall
as a screen of its width says (``screen_span``).

Pure computation, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perception.camera import Intrinsics, pixels_to_points


def level_hypotheses(points: np.ndarray, max_tilt_deg: float, hypotheses: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC plane hypotheses through triplets of camera-frame ``points`` (fixed seed: deterministic) whose
    normal lies within ``max_tilt_deg`` of the camera's vertical axis: unit normals (M, 3) turned towards the
    camera's up (-y) and offsets (M,), n . p + d = 0."""
    triplets = points[np.random.default_rng(0).integers(0, len(points), (hypotheses, 3))]
    normals = np.cross(triplets[:, 1] - triplets[:, 0], triplets[:, 2] - triplets[:, 0])
    length = np.linalg.norm(normals, axis=1)
    ok = length > 1e-9
    normals = normals[ok] / length[ok, None]
    normals *= np.where(normals[:, 1] > 0, -1.0, 1.0)[:, None]
    offsets = -np.einsum("ij,ij->i", normals, triplets[ok, 0])
    level = -normals[:, 1] >= np.cos(np.radians(max_tilt_deg))
    return normals[level], offsets[level]


@dataclass(frozen=True)
class FloorConfig:
    """How the floor is found in keyframes and when furniture is stretched down to it."""

    max_tilt_deg: float = 45.0
    """A level plane's normal lies within this angle of the camera's up axis (-y)."""
    min_below_m: float = 0.4
    """A floor lies at least this far below the camera centre."""
    inlier_m: float = 0.02
    """RANSAC inlier distance."""
    min_share: float = 0.25
    """The dominant level plane holds at least this share of the lower half's valid pixels."""
    samples: int = 1200
    """Pixels of the lower half tried (a regular grid)."""
    hypotheses: int = 64
    """RANSAC hypotheses (fixed seed: deterministic)."""
    min_keyframes: int = 5
    """Keyframes that must agree on the floor before objects are stretched to it."""
    min_support: float = 0.1
    """A height is a candidate for the floor when at least this share of the best-supported height's keyframes
    agree on it (a few planes below the floor are noise). 0.2 until 2026-12-04: in the 7-Scenes kitchen the
    floor is seen by the first 14 of 107 keyframes with a level plane and the table top by 77, so the table top
    was taken for the floor and the chairs, stretched to it, lay 0.2-0.28 m high; the synthetic family's
    development scenes map the same with 0.1."""
    agree_m: float = 0.05
    """Planes within this height of the lowest common one are the floor."""
    lower_share: float = 0.05
    """A level surface below the dominant one (``level_plane``) holding at least this share of the lower half's
    pixels, and spanning ``lower_span_m``, is the keyframe's floor instead."""
    lower_span_m: float = 1.0
    """How wide (across the camera's view, 5th to 95th percentile) such a lower surface must be: a floor, not a
    chair's seat."""
    max_gap_m: float = 1.5
    """A floor-standing object is stretched only when its visible bottom lies at most this far above the floor
    (and no more than ``agree_m`` below it): farther, the object or the floor estimate is something else."""


def level_plane(depth_m: np.ndarray, K: Intrinsics, config: FloorConfig) -> np.ndarray | None:
    """The dominant level plane ``(n, d)`` (n . p + d = 0, camera frame, n towards the camera's up) of the lower
    half of a depth image lying ``min_below_m`` below the camera, or None."""
    h, w = depth_m.shape[:2]
    step = max(1, int(np.sqrt((h // 2) * w / config.samples)))
    rows, cols = np.meshgrid(np.arange(h // 2, h, step), np.arange(0, w, step), indexing="ij")
    z = depth_m[rows, cols]
    valid = np.isfinite(z) & (z > 0)
    if valid.sum() < 100:
        return None
    points = pixels_to_points(cols[valid].astype(np.float64), rows[valid].astype(np.float64), z[valid], K)
    points = np.asarray(points, np.float64)
    normals, offsets = level_hypotheses(points, config.max_tilt_deg, config.hypotheses)
    keep = offsets >= config.min_below_m
    if not keep.any():
        return None
    normals, offsets = normals[keep], offsets[keep]
    inliers = np.abs(points @ normals.T + offsets) < config.inlier_m
    count = inliers.sum(axis=0)
    best = int(np.argmax(count))
    if count[best] < config.min_share * len(points):
        return None
    centre, normal = _level_fit(lowest_surface(points, points[inliers[:, best]], config))
    return np.r_[normal, -normal @ centre]


def _level_fit(on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares plane of points: their centre and unit normal, turned towards the camera's up (-y)."""
    centre = on.mean(axis=0)
    normal = np.linalg.svd(on - centre, full_matrices=False)[2][-1]
    return centre, normal * (-1.0 if normal[1] > 0 else 1.0)


def lowest_surface(points: np.ndarray, dominant: np.ndarray, config: FloorConfig) -> np.ndarray:
    """The inliers of the lowest broad level surface among ``points``: those of the ``dominant`` level plane, or
    of one below it parallel to it (``lower_share`` of the points within ``inlier_m`` of one height, spread
    ``lower_span_m`` across). A camera at a person's height looking over tables sees their tops more than the
    floor between them: in the development scenes with handheld sweeps the floor never held a quarter of the
    lower half, the table tops were taken for it, and the chairs, stretched down to them, lay 0.1-0.25 m
    high."""
    centre, normal = _level_fit(dominant)
    height = (points - centre) @ normal  # above the dominant plane, towards the camera's up
    below = np.sort(height[height < -2.0 * config.inlier_m])
    if len(below) < config.lower_share * len(points):
        return dominant
    # for each height below, how many lie within 2 x inlier_m above it; the lowest with enough starts a surface
    counts = np.searchsorted(below, below + 2.0 * config.inlier_m, side="right") - np.arange(len(below))
    starts, tried = np.flatnonzero(counts >= config.lower_share * len(points)), -np.inf
    for start in starts:
        if below[start] <= tried:  # within the band of one tried before: the same surface
            continue
        tried = below[start] + 2.0 * config.inlier_m
        on = points[(height >= below[start]) & (height <= tried)]
        across = on - np.outer(on @ normal, normal)
        spread = np.percentile(across, 95, axis=0) - np.percentile(across, 5, axis=0)
        if np.linalg.norm(spread) >= config.lower_span_m:
            return on
    return dominant


@dataclass(frozen=True)
class Floor:
    """The floor in the world frame: unit ``up`` and the ``height`` of the floor along it (floor points p:
    up . p == height); ``support``: keyframes that agree."""

    up: np.ndarray
    height: float
    support: int

    @staticmethod
    def estimate(normals: np.ndarray, feet: np.ndarray, config: FloorConfig) -> Floor | None:
        """The floor from the level planes of many keyframes, each given by its world-frame unit normal (N, 3)
        and the point of it under the camera that saw it (N, 3): the lowest height (along the planes' mean
        normal) that at least ``min_keyframes`` of them, and ``min_support`` of the most any height has, share
        within ``agree_m`` (tables and seats lie higher), None before that. Heights are those of points, not
        planes' offsets, so the estimate turns and moves with the world."""
        if len(normals) < config.min_keyframes:
            return None
        up = normals.mean(axis=0)
        heights = feet @ (up / np.linalg.norm(up))
        order = np.argsort(heights, kind="stable")
        ranked = heights[order]
        # for each plane, how many lie within agree_m above it: the lowest with enough is the floor
        counts = np.searchsorted(ranked, ranked + config.agree_m, side="right") - np.arange(len(ranked))
        lowest = np.flatnonzero(counts >= max(config.min_keyframes, config.min_support * counts.max()))
        if len(lowest) == 0:
            return None
        on = (heights >= ranked[lowest[0]]) & (heights <= ranked[lowest[0]] + config.agree_m)
        up = normals[on].mean(axis=0)
        up /= np.linalg.norm(up)
        return Floor(up, float(np.median(feet[on] @ up)), int(on.sum()))


def world_floor_view(plane: np.ndarray, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera-frame level plane ``(n, d)`` (unit n) as the world-frame normal and the plane's point under the
    camera of the camera-to-world pose ``T_wc``."""
    return T_wc[:3, :3] @ plane[:3], T_wc[:3, :3] @ (-plane[3] * plane[:3]) + T_wc[:3, 3]


def on_floor(
    mean: np.ndarray,
    cov: np.ndarray,
    views: tuple[np.ndarray, np.ndarray, np.ndarray],
    floor: Floor,
    config: FloorConfig,
    top_cut: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A floor-standing object's Gaussian ``mean``, ``cov`` (world frame) stretched down to the floor: its bottom
    moves to the floor, its top is the weighted median of its ``views``' tops (their (N, 3) means, (N, 3, 3)
    covariances and (N,) weights; a view's top lies ``sqrt(3)`` standard deviations above its mean along
    ``up``, as for a uniform extent); across ``up`` the Gaussian stays. None when its visible bottom is not within
    ``max_gap_m`` above the floor (nor ``agree_m`` below it).

    ``top_cut`` (N,): whether the image's top edge cut each view's box. The top is then that of the views it did
    not cut, as in ``vertical_span`` (the 90th percentile of all tops when fewer than three see it): a
    refrigerator 1.8 m tall seen from near has its top above the image, and the tops of those views are the
    image's edge (development seeds 0-35: refrigerators 0.10-0.36 m low, their centres 0.2 m off)."""
    u = floor.up
    means, covs, weights = views
    w = np.asarray(weights, float)
    bottom = float(u @ mean) - np.sqrt(3.0 * max(float(u @ cov @ u), 0.0)) - floor.height
    tops = view_ends(means, covs, u)[0]
    top = (weighted_quantile(tops, w, 0.5) if top_cut is None else seen_end(tops, w, top_cut, 0.9)) - floor.height
    if not -config.agree_m <= bottom <= config.max_gap_m or top <= 0.0:
        return None
    return with_span(mean, cov, u, floor.height, floor.height + top)


def with_span(
    mean: np.ndarray, cov: np.ndarray, up: np.ndarray, bottom: float, top: float
) -> tuple[np.ndarray, np.ndarray]:
    """A Gaussian whose extent along ``up`` is the uniform one from height ``bottom`` to ``top``; across ``up`` it
    stays (cross terms with ``up`` dropped)."""
    P = np.eye(3) - np.outer(up, up)
    new_mean = mean + ((bottom + top) / 2.0 - float(up @ mean)) * up
    return new_mean, P @ cov @ P + (top - bottom) ** 2 / 12.0 * np.outer(up, up)


def weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The value below which the share ``q`` of the ``weights`` lies."""
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order] / weights.sum())
    return float(values[order][min(int(np.searchsorted(cumulative, q)), len(values) - 1)])


def view_ends(means: np.ndarray, covs: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The heights along ``up`` of the tops and bottoms (N,) of views with (N, 3) means and (N, 3, 3)
    covariances: ``sqrt(3)`` standard deviations from their means, as for a uniform extent."""
    half = np.sqrt(3.0 * np.clip(np.einsum("i,nij,j->n", up, covs, up), 0.0, None))
    return means @ up + half, means @ up - half


def vertical_span(
    means: np.ndarray, covs: np.ndarray, weights: np.ndarray, up: np.ndarray, cut: np.ndarray, min_views: int = 3
) -> tuple[float, float] | None:
    """An object's bottom and top heights along ``up`` from its views (N, 3) means, (N, 3, 3) covariances, (N,)
    weights and (N, 2) flags: the image's top / bottom edge cut the view's box. A view's top and bottom lie
    ``sqrt(3)`` standard deviations from its mean; the object's top is the weighted median of the tops of the
    views whose box the top edge does not cut (a cut view's top is the edge's, below the object's), else, with
    fewer than ``min_views`` of them, the 90th percentile of all tops; the bottom likewise. None when they cross."""
    w, cut = np.asarray(weights, float), np.asarray(cut, bool)
    top, bottom = (
        seen_end(heights, w, cut[:, k], fallback, min_views)
        for k, (heights, fallback) in enumerate(zip(view_ends(means, covs, up), (0.9, 0.1), strict=True))
    )
    return (bottom, top) if top > bottom else None


def seen_end(heights: np.ndarray, weights: np.ndarray, cut: np.ndarray, fallback: float, min_views: int = 3) -> float:
    """One end (top or bottom) of an object from its views' ends ``heights`` (N,), ``weights`` (N,) and (N,) flags
    that the image's edge cut the view there: the weighted median of the ends of the views it did not cut, else,
    with fewer than ``min_views`` of them, the ``fallback`` quantile of all."""
    seen = ~np.asarray(cut, bool)
    if seen.sum() >= min_views:
        return weighted_quantile(heights[seen], weights[seen], 0.5)
    return weighted_quantile(heights, weights, fallback)


def ends_seen(cut: np.ndarray, min_views: int = 3) -> tuple[bool, bool]:
    """Whether at least ``min_views`` views see an object's top, and its bottom (``vertical_span``): of (N, 2)
    flags that the image's top / bottom edge cut each view's box."""
    seen = (~np.asarray(cut, bool)).sum(axis=0) >= min_views
    return bool(seen[0]), bool(seen[1])


SCREEN_ASPECT: dict[str, float] = {"tv": 9.0 / 16.0}
"""Height over width of a class's screens (a size prior: televisions and computer monitors are 16:9)."""


def screen_span(span: tuple[float, float], seen: tuple[bool, bool], height: float) -> tuple[float, float]:
    """A screen's bottom and top (``span``) at least ``height`` apart (its width times ``SCREEN_ASPECT``) from the
    end its views see (``seen``: top, bottom) when they do not see the other: a screen on a wall above a camera
    at a person's height has its top above the image in most views, and the tops of those views are the image's
    edge (development seeds: tvs 0.08-0.30 m low, their heights 0.18-0.45 m for 0.6-0.8 m)."""
    bottom, top = span
    if top - bottom >= height or seen[0] == seen[1]:
        return span
    return (bottom, bottom + height) if seen[1] else (top - height, top)
