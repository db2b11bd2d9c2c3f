"""Depth warping for large motion (Sec. 2.4.3): predict the newer keyframe's depth from the older one.

Conventions: depth images are float metres with NaN where invalid; ``K`` is the camera's ``Intrinsics``;
``T_new_old`` maps points from the older camera frame into the newer one (``inverse(T_wc_new) @ T_wc_old``).
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from graph.geometry import motion_magnitude
from perception.camera import Intrinsics, backproject_xy, points_to_pixels, project_uv
from perception.features import Box, box_pixels, depth_points, dominant_depth_mask, stride_subsample, transform

log = logging.getLogger(__name__)

MIN_Z_M = 1e-3


def needs_warp(T_rel: np.ndarray, tau: float, phi: float) -> bool:
    """True when the relative motion exceeds translation ``tau`` (m) or rotation ``phi`` (rad), eq. 2.16."""
    t, angle = motion_magnitude(T_rel)
    return t > tau or angle > phi


def project(points: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) as (u, v) and depths (N,) of camera-frame points (``fx * x / z + cx``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = points_to_pixels(points, K, scale_first=True)
    return np.stack([u, v], axis=1), points[:, 2]


def warp_depth(depth_m: np.ndarray, K: Intrinsics, T_new_old: np.ndarray, splat: int = 1, step: int = 1) -> np.ndarray:
    """The older depth seen from the newer camera: back-project, transform, re-project with a z-buffer (Sec. 2.4.3).

    Each point lands on its nearest pixel (``splat=2``: on the 2x2 pixels around it, which closes the
    one-pixel cracks of magnified surfaces); where several land on one pixel the nearest wins
    (``np.minimum.at``, then a 2x2 minimum filter for the splat). Pixels nothing lands on are NaN. ``step=2``
    warps every second pixel of every second row and splats each onto 2x2 pixels: four times fewer points,
    for consumers that sample boxes.
    """
    h, w = depth_m.shape
    if step > 1:
        sub = depth_m[::step, ::step]
        rows, cols = np.nonzero(np.isfinite(sub) & (sub > 0))
        rows, cols, splat = rows * step, cols * step, 2
    else:
        rows, cols = np.nonzero(np.isfinite(depth_m) & (depth_m > 0))
    z0 = depth_m[rows, cols].astype(np.float32)
    x0, y0 = backproject_xy(cols, rows, z0, K, depth_first=True, dtype=np.float32)
    R, t = T_new_old[:3, :3].astype(np.float32), T_new_old[:3, 3].astype(np.float32)
    x = R[0, 0] * x0 + R[0, 1] * y0 + R[0, 2] * z0 + t[0]
    y = R[1, 0] * x0 + R[1, 1] * y0 + R[1, 2] * z0 + t[1]
    z = R[2, 0] * x0 + R[2, 1] * y0 + R[2, 2] * z0 + t[2]
    front = z > MIN_Z_M
    x, y, z = x[front], y[front], z[front]
    u, v = project_uv(x, y, z, K, scale_first=True, dtype=np.float32)
    # z-buffer on the image padded by one pixel on each side: a point whose splat reaches the image is kept
    # once, and positions in the padding are cropped. A 2x2 splat is the one-pixel z-buffer at the floor of
    # each point followed by a 2x2 minimum filter (each pixel takes the nearest of the points whose 2x2 splat
    # covers it), four times fewer scattered writes than writing the four positions.
    pw = w + 2
    if splat == 2:
        ui, vi = np.floor(u), np.floor(v)
        near = (ui >= -1) & (ui < w) & (vi >= -1) & (vi < h)
    else:
        ui, vi = np.rint(u), np.rint(v)
        near = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    index = (vi[near].astype(np.int64) + 1) * pw + ui[near].astype(np.int64) + 1
    out = np.full((h + 2) * pw, np.inf, dtype=np.float32)
    np.minimum.at(out, index, z[near])
    out = out.reshape(h + 2, pw)
    if splat == 2:  # pixel (r, c) of the padded image takes the minimum over (r-1..r, c-1..c)
        out = cv2.erode(
            out, np.ones((2, 2), np.uint8), anchor=(1, 1), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf
        )
    out = out[1 : h + 1, 1 : w + 1]
    out[np.isinf(out)] = np.nan
    return out


def moved_box_points(
    box: Box,
    depth_m: np.ndarray,
    K: Intrinsics,
    T_new_old: np.ndarray,
    gap_m: float = 0.05,
    anchor_fraction: float = 0.5,
    max_points: int = 4000,
) -> np.ndarray:
    """A box's object points in the newer camera's frame (N, 3): its dominant-depth pixels, back-projected.

    Only the pixels of the box's dominant depth segment are used (background inside the box moves with a
    different parallax); at most ``max_points`` pixels (by stride). Empty when the box has no depth.
    """
    if not np.all(np.isfinite(box)):
        return np.zeros((0, 3))
    rows, cols = box_pixels(depth_m, box)
    idx = stride_subsample(len(rows), max_points)
    rows, cols = rows[idx], cols[idx]
    if len(rows) == 0:
        return np.zeros((0, 3))
    cr, cc = box_pixels(depth_m, box, anchor_fraction)
    anchor = float(np.median(depth_m[cr, cc] if len(cr) else depth_m[rows, cols]))
    keep = dominant_depth_mask(depth_m[rows, cols], anchor, gap_m)
    return transform(T_new_old, depth_points(depth_m, K, rows[keep], cols[keep]))


def in_view(points: np.ndarray, K: Intrinsics, width: int, height: int) -> np.ndarray:
    """Mask of the camera-frame points in front of the camera that project inside a width x height image."""
    uv, z = project(points, K)
    with np.errstate(invalid="ignore"):
        return (z > MIN_Z_M) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)


def image_box(points: np.ndarray, K: Intrinsics, width: int, height: int) -> Box | None:
    """Bounding box of camera-frame points projected into a width x height image, clipped to it; None when
    nothing projects inside."""
    uv, z = project(points, K)
    uv = uv[z > MIN_Z_M]
    if len(uv) == 0:
        return None
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    bx1, by1 = max(lo[0], 0.0), max(lo[1], 0.0)
    bx2, by2 = min(hi[0] + 1.0, float(width)), min(hi[1] + 1.0, float(height))
    if bx2 <= bx1 or by2 <= by1:
        return None
    return (float(bx1), float(by1), float(bx2), float(by2))


def warp_box(
    box: Box,
    depth_m: np.ndarray,
    K: Intrinsics,
    T_new_old: np.ndarray,
    gap_m: float = 0.05,
    anchor_fraction: float = 0.5,
    max_points: int = 4000,
) -> Box | None:
    """A box moved into the newer image: ``image_box`` of its object points (``moved_box_points``)."""
    h, w = depth_m.shape
    return image_box(moved_box_points(box, depth_m, K, T_new_old, gap_m, anchor_fraction, max_points), K, w, h)


def image_boxes(points: list[np.ndarray], K: Intrinsics, width: int, height: int) -> np.ndarray:
    """``image_box`` of each point set as rows (L, 4); rows of NaN for sets that leave the image."""
    out = np.full((len(points), 4), np.nan)
    for i, p in enumerate(points):
        box = image_box(p, K, width, height)
        if box is not None:
            out[i] = box
    return out
