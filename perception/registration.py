"""Depth reprojection between cameras: registering depth to colour, and warping depth between poses."""

from __future__ import annotations

import cv2
import numpy as np

from perception.camera import Intrinsics, pixel_rays, pixels_to_points, points_to_pixels
from perception.frame import CameraModel, Frame


def backproject(depth_m: np.ndarray, K: Intrinsics, step: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame 3D points (N, 3) of the valid depth pixels, with their pixel rows and columns."""
    d = depth_m[::step, ::step]
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    z = d[v, u]
    u = u * step
    v = v * step
    return pixels_to_points(u, v, z, K), v, u


def project_zbuffer(points: np.ndarray, K: Intrinsics, width: int, height: int) -> np.ndarray:
    """Depth image (metres, NaN = empty) of camera-frame points, nearest point per pixel wins."""
    z = points[:, 2].astype(np.float32)
    front = z > 1e-6
    pts, z = points[front], z[front]
    u, v = points_to_pixels(pts, K)
    u, v = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    out = np.full(height * width, np.inf, dtype=np.float32)
    np.minimum.at(out, v[inside] * width + u[inside], z[inside])  # z-buffer: the nearest point of a pixel wins
    out[np.isinf(out)] = np.nan
    return out.reshape(height, width)


def reproject_depth(
    depth_m: np.ndarray, K_src: Intrinsics, K_dst: Intrinsics, T_dst_src: np.ndarray, width: int, height: int
) -> np.ndarray:
    """Depth seen from another camera: back-project with K_src, move by T_dst_src, z-buffer with K_dst."""
    pts, _, _ = backproject(depth_m, K_src)
    moved = pts @ np.ascontiguousarray(T_dst_src[:3, :3].T) + T_dst_src[:3, 3]
    return project_zbuffer(moved, K_dst, width, height)


def depth_in_color(depth_m: np.ndarray, camera: CameraModel, scale: int = 1) -> np.ndarray:
    """Depth registered to the colour image (unchanged when the sensor is already registered).

    ``scale`` > 1 registers every ``scale``-th depth pixel into a 1/``scale`` colour grid and enlarges the
    result (nearest neighbour): about scale^2 times cheaper, for consumers that sample depth in boxes.
    """
    if camera.registered:
        return depth_m
    T = camera.depth_to_color if camera.depth_to_color is not None else np.eye(4)
    if scale == 1:
        return reproject_depth(depth_m, camera.depth, camera.color, T, camera.width, camera.height)
    d, c = camera.depth, camera.color
    small_src, small_dst = d.subsampled(scale), c.subsampled(scale)
    w, h = -(-camera.width // scale), -(-camera.height // scale)
    small = reproject_depth(depth_m[::scale, ::scale], small_src, small_dst, T, w, h)
    return cv2.resize(small, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)[: camera.height, : camera.width]


def smooth_depth_mask(depth_m: np.ndarray, max_ratio: float = 0.02, radius: int = 2) -> np.ndarray:
    """Pixels whose (2r+1)^2 neighbourhood is fully valid and spans less than ``max_ratio`` of the depth.

    Feature points on depth discontinuities get mixed foreground/background depth; this excludes them.
    """
    d = np.nan_to_num(depth_m, nan=0.0).astype(np.float32)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    hi, lo = cv2.dilate(d, kernel), cv2.erode(d, kernel)
    return (lo > 0) & (hi - lo < max_ratio * d)


def smooth_depth_at(
    depth_m: np.ndarray, rows: np.ndarray, cols: np.ndarray, max_ratio: float = 0.02, radius: int = 2
) -> np.ndarray:
    """``smooth_depth_mask`` at the given pixels only: O(pixels * (2r+1)^2) instead of a pass over the image."""
    h, w = depth_m.shape
    offsets = np.arange(-radius, radius + 1)
    rr = np.clip(rows[:, None, None] + offsets[None, :, None], 0, h - 1)  # clipping repeats in-window pixels
    cc = np.clip(cols[:, None, None] + offsets[None, None, :], 0, w - 1)
    window = np.nan_to_num(depth_m[rr, cc], nan=0.0).astype(np.float32).reshape(len(rows), -1)
    d = np.nan_to_num(depth_m[rows, cols], nan=0.0).astype(np.float32)
    hi, lo = window.max(axis=1), window.min(axis=1)
    return (lo > 0) & (hi - lo < max_ratio * d)


def depth_at_color_pixels(
    pixels: np.ndarray,
    depth_m: np.ndarray,
    camera: CameraModel,
    iterations: int = 3,
    max_edge_ratio: float | None = None,
) -> np.ndarray:
    """Colour-camera depth (z, metres; NaN where unknown) at colour pixels (N, 2).

    For an unregistered sensor each pixel's ray is intersected with the depth image by fixed-point
    iteration: guess z, map the colour ray point into the depth image, read the depth there, repeat.
    With a few-centimetre baseline this converges in two or three steps and costs O(N), not a full
    registration of the depth image.
    """
    h, w = depth_m.shape
    if camera.registered:
        u = np.clip(np.round(pixels[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.round(pixels[:, 1]).astype(int), 0, h - 1)
        z = depth_m[v, u].astype(float)
        if max_edge_ratio is not None:
            z[~smooth_depth_at(depth_m, v, u, max_edge_ratio)] = np.nan
        return z
    if max_edge_ratio is not None:
        depth_m = np.where(smooth_depth_mask(depth_m, max_edge_ratio), depth_m, np.nan)
    c, d = camera.color, camera.depth
    E = camera.depth_to_color if camera.depth_to_color is not None else np.eye(4)
    E_inv = np.linalg.inv(E)
    rays = np.stack([*pixel_rays(pixels[:, 0], pixels[:, 1], c), np.ones(len(pixels))], axis=1)
    z = np.full(len(pixels), float(np.nanmedian(depth_m)) if np.isfinite(depth_m).any() else 1.0)
    for _ in range(iterations):
        X_d = (rays * z[:, None]) @ E_inv[:3, :3].T + E_inv[:3, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            u, v = points_to_pixels(X_d, d)
            u, v = np.round(u), np.round(v)
        inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z_d = np.full(len(pixels), np.nan)
        z_d[inside] = depth_m[v[inside].astype(int), u[inside].astype(int)]
        X_dn = pixels_to_points(u, v, z_d, d)
        z_new = (X_dn @ E[:3, :3].T + E[:3, 3])[:, 2]
        z = np.where(np.isfinite(z_new), z_new, z)
        last = z_new
    return last


def map_points(frame: Frame, step: int = 32, max_depth_m: float = 4.0) -> np.ndarray:
    """A sparse grid of the frame's depth points (camera frame, float32) for the map's occupancy."""
    pts, _, _ = backproject(frame.depth_m(), frame.camera.depth, step)
    return pts[pts[:, 2] <= max_depth_m].astype(np.float32)
