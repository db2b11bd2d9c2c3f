"""Dense photometric RGB-D alignment (direct odometry in the manner of Steinbruecker et al. 2011 and Kerl et
al. 2013): the keyframe's pixels, lifted by their depth, moved into the current frame so that brightness
agrees, by Gauss-Newton with Huber weights from coarse to fine.

It needs texture but no feature to survive a detector and a descriptor match, so it tracks blurred or
repetitive images that ORB cannot; it needs a start within a few pixels of motion at the coarsest level (a
motion prior). Everything is in the colour camera; depth is registered to it first.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from perception.camera import Intrinsics, pixels_to_points

LEVELS: tuple[tuple[int, int], ...] = ((16, 15), (8, 12), (4, 10), (2, 6))
"""(resolution divisor, Gauss-Newton iterations) from coarse to fine."""


@dataclass(frozen=True)
class DenseResult:
    """``T_cur_ref`` (colour camera), the robust RMS brightness residual (grey levels), the pixels used, and
    the smallest over largest eigenvalue of the normal equations (near 0: a direction the image cannot see)."""

    T: np.ndarray
    residual: float
    pixels: int
    conditioning: float


def _level(
    gray: np.ndarray, depth: np.ndarray, K: Intrinsics, factor: int
) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """A pyramid level: the grey image area-averaged, depth subsampled (holes stay NaN), the intrinsics."""
    h, w = gray.shape
    small = cv2.resize(gray.astype(np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 1.0)  # a wider basin: gradients reach a pixel or two farther
    d = depth[factor // 2 :: factor, factor // 2 :: factor][: small.shape[0], : small.shape[1]]
    K_small = Intrinsics(K.fx / factor, K.fy / factor, (K.cx + 0.5) / factor - 0.5, (K.cy + 0.5) / factor - 0.5)
    return small, d, K_small


def align(
    ref_gray: np.ndarray,
    ref_depth: np.ndarray,
    cur_gray: np.ndarray,
    K: Intrinsics,
    T_init: np.ndarray,
    levels: tuple[tuple[int, int], ...] = LEVELS,
    huber: float = 10.0,
    min_pixels: int = 300,
) -> DenseResult | None:
    """``T_cur_ref`` (colour camera) that makes ``cur_gray`` at the keyframe's moved points match
    ``ref_gray``; ``ref_depth`` is the keyframe's metric depth registered to its colour image. None when too
    few pixels stay in view."""
    T = np.array(T_init, float)
    result = None
    for factor, iterations in levels:
        ref, depth, Kl = _level(ref_gray, ref_depth, K, factor)
        cur, _, _ = _level(cur_gray, ref_depth, K, factor)
        gx = cv2.Sobel(cur, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(cur, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        gref = np.hypot(cv2.Sobel(ref, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(ref, cv2.CV_32F, 0, 1, ksize=3))
        v, u = np.nonzero(np.isfinite(depth) & (depth > 0) & (gref > 8.0))  # pixels with depth and gradient
        if len(u) < min_pixels:
            return None
        X = pixels_to_points(u.astype(np.float64), v.astype(np.float64), depth[v, u].astype(np.float64), Kl)
        intensity = ref[v, u].astype(np.float64)
        h, w = cur.shape
        for _ in range(iterations):
            P = X @ T[:3, :3].T + T[:3, 3]
            z = P[:, 2]
            front = z > 0.05
            with np.errstate(divide="ignore", invalid="ignore"):
                pu = Kl.fx * P[:, 0] / z + Kl.cx
                pv = Kl.fy * P[:, 1] / z + Kl.cy
            ok = front & (pu >= 1) & (pu < w - 2) & (pv >= 1) & (pv < h - 2)
            if ok.sum() < min_pixels:
                return None
            P, pu, pv = P[ok], pu[ok], pv[ok]
            sample, dx, dy = (_bilinear(image, pu, pv) for image in (cur, gx, gy))
            r = sample - intensity[ok]
            x, y, zz = P[:, 0], P[:, 1], P[:, 2]
            # d(pixel)/d(point) times the point's derivative in the left-multiplied twist (rotation, translation)
            ju = np.stack([-Kl.fx * x * y / zz**2, Kl.fx * (1 + x**2 / zz**2), -Kl.fx * y / zz,
                           Kl.fx / zz, np.zeros_like(zz), -Kl.fx * x / zz**2], axis=1)  # fmt: skip
            jv = np.stack([-Kl.fy * (1 + y**2 / zz**2), Kl.fy * x * y / zz**2, Kl.fy * x / zz,
                           np.zeros_like(zz), Kl.fy / zz, -Kl.fy * y / zz**2], axis=1)  # fmt: skip
            J = dx[:, None] * ju + dy[:, None] * jv
            weight = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-9))
            H = (J * weight[:, None]).T @ J
            g = (J * weight[:, None]).T @ r
            xi = np.linalg.solve(H + 1e-6 * np.eye(6), -g)
            T = _twist(xi) @ T
            eig = np.linalg.eigvalsh(H)
            result = DenseResult(
                T.copy(),
                float(np.sqrt(np.sum(weight * r**2) / np.sum(weight))),
                len(r),
                float(max(eig[0], 0.0) / max(eig[-1], 1e-12)),
            )
            if np.linalg.norm(xi) < 1e-6:
                break
    return result


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``image`` at sub-pixel positions (u, v) inside it, bilinearly interpolated."""
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    a, b = u - u0, v - v0
    top = image[v0, u0] * (1 - a) + image[v0, u0 + 1] * a
    bottom = image[v0 + 1, u0] * (1 - a) + image[v0 + 1, u0 + 1] * a
    return (top * (1 - b) + bottom * b).astype(np.float64)


def _twist(xi: np.ndarray) -> np.ndarray:
    """The rigid motion of a small twist: rotation vector ``xi[:3]``, translation ``xi[3:]``."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(xi[:3].reshape(3, 1))[0]
    T[:3, 3] = xi[3:]
    return T
