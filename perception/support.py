"""The surface an object stands on, and the object's pixels without it (SPEC 6.5).

A detection's box holds the floor or table around the object's foot, joined to its depth segment where they
touch: ``support_plane`` finds that level plane around the box, ``split_support`` takes it off the object's pixels.

Pure computation, no I/O.
"""

from __future__ import annotations

import numpy as np

from perception.camera import Intrinsics
from perception.features import (
    Box,
    FeatureConfig,
    depth_points,
    dominant_depth_mask,
    object_pixels,
    ring_windows,
    segment_anchor,
    stride_subsample,
    transform,
)
from perception.floor import level_hypotheses


def ring_pixels(
    shape: tuple[int, ...], box: Box, ring: float = 0.15, most: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of a ring around a box, ``ring`` of the box size wide (clipped to the image); with
    ``most``, on a regular grid coarse enough to give about that many."""
    windows = ring_windows(shape, box, ring)
    if windows is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    (y1, y2, x1, x2), inner = windows
    area = (y2 - y1) * (x2 - x1) - (inner[1] - inner[0]) * (inner[3] - inner[2])
    step = max(1, int(np.sqrt(area / most))) if most else 1
    rows, cols = np.meshgrid(np.arange(y1, y2, step), np.arange(x1, x2, step), indexing="ij")
    outside = (rows < inner[0]) | (rows >= inner[1]) | (cols < inner[2]) | (cols >= inner[3])
    return rows[outside], cols[outside]


def support_plane(
    depth_m: np.ndarray,
    K: Intrinsics,
    box: Box,
    max_tilt_deg: float,
    inlier_m: float = 0.01,
    min_share: float = 0.3,
    samples: int = 1000,
    hypotheses: int = 64,
) -> np.ndarray | None:
    """The plane ``(n, d)`` (n . p + d = 0, camera frame) an object in ``box`` stands on, or None.

    RANSAC (fixed seed: deterministic) over the ring of pixels around the box, among the planes whose normal
    lies within ``max_tilt_deg`` of the camera's vertical axis (so a wall behind the object is never taken);
    the best must hold ``min_share`` of the ring's points within ``inlier_m``.
    """
    rows, cols = ring_pixels(depth_m.shape, box, most=samples)
    valid = np.isfinite(depth_m[rows, cols])
    if valid.sum() < 50:
        return None
    points = depth_points(depth_m, K, rows[valid], cols[valid])
    normals, offsets = level_hypotheses(points, max_tilt_deg, hypotheses)
    if len(normals) == 0:
        return None
    inliers = (np.abs(points @ normals.T + offsets) < inlier_m).sum(axis=0)
    best = int(np.argmax(inliers))
    return np.r_[normals[best], offsets[best]] if inliers[best] >= min_share * len(points) else None


def split_support(
    depth_m: np.ndarray,
    K: Intrinsics,
    box: Box,
    rows: np.ndarray,
    cols: np.ndarray,
    config: FeatureConfig,
    min_left: float = 0.3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The object pixels minus those on the floor or table it stands on (``FeatureConfig.support_tilt_deg``), and
    that support plane ``(n, d)`` (camera frame), or None when none was taken off.

    A surface joined to the object's depth segment stretches its extent (a cup's box holds the table around
    its foot). Nothing is dropped when that would leave less than ``min_left`` of the pixels: an object lying
    flat on the plane, or a plane that is the object. Without the support, the pixels are segmented by depth
    again around the box's anchor (``dominant_depth_mask``): what the support alone joined to the object is no
    part of it (a bottle on a table against a wall: the table top runs on from its foot to the wall, whose
    pixels beside the bottle doubled its width and pulled its centre 3 cm back).
    """
    if config.support_tilt_deg is None or len(rows) < 20:
        return rows, cols, None
    plane = support_plane(depth_m, K, box, config.support_tilt_deg)
    if plane is None:
        return rows, cols, None
    off = np.abs(depth_points(depth_m, K, rows, cols) @ plane[:3] + plane[3]) > config.support_tolerance_m
    if off.sum() < min_left * len(rows):
        return rows, cols, None
    left = rows[off], cols[off]
    joined = dominant_depth_mask(depth_m[left], segment_anchor(depth_m, box, config, *left), config.gap_m)
    return (left[0][joined], left[1][joined], plane) if joined.sum() >= min_left * len(rows) else (*left, plane)


def object_points(depth_m: np.ndarray, K: Intrinsics, box: Box, config: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """A detection's object pixels: its depth segment (``object_pixels``) without its support surface."""
    rows, cols = object_pixels(depth_m, box, config)
    rows, cols, _ = split_support(depth_m, K, box, rows, cols, config)
    return rows, cols


def backproject_detection(
    depth_m: np.ndarray, K: Intrinsics, T_wc: np.ndarray, box: Box, config: FeatureConfig
) -> np.ndarray:
    """World points (N, 3) of a detection's object pixels with the camera pose ``T_wc`` (Sec. 2.4.4)."""
    rows, cols = object_points(depth_m, K, box, config)
    idx = stride_subsample(len(rows), config.max_points)
    return transform(T_wc, depth_points(depth_m, K, rows[idx], cols[idx]))
