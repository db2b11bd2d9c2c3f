"""Projective point-to-plane ICP between two depth images (the KinectFusion registration step).

Used to refine feature-based relative poses at keyframes and loop closures: it works in the depth
camera's own frame, so it does not depend on the colour-to-depth calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from perception.camera import Intrinsics, pixels_to_points, points_to_pixels


@dataclass(frozen=True)
class IcpResult:
    """Refined ``T_dst_src``, point-to-plane RMS residual (m), inlier fraction and the 6x6 information."""

    T: np.ndarray
    rmse_m: float
    inlier_fraction: float
    inliers: int
    information: np.ndarray


def vertex_map(depth_m: np.ndarray, K: Intrinsics) -> np.ndarray:
    """(H, W, 3) camera-frame points, NaN where depth is invalid."""
    h, w = depth_m.shape
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    z = np.where(depth_m > 0, depth_m, np.nan).astype(np.float32)
    return pixels_to_points(u, v, z, K)


def smooth_depth(
    depth_m: np.ndarray, diameter: int = 7, sigma_depth_m: float = 0.04, sigma_px: float = 3.0
) -> np.ndarray:
    """Edge-preserving bilateral filter of a depth image (KinectFusion's first step); NaN stays invalid."""
    valid = np.isfinite(depth_m) & (depth_m > 0)
    d = np.where(valid, depth_m, 0.0).astype(np.float32)
    out = cv2.bilateralFilter(d, diameter, sigma_depth_m, sigma_px)
    return np.where(valid, out, np.nan)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` over the last axis of length 3, written out (several times faster on image-sized arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def normal_map(vertices: np.ndarray) -> np.ndarray:
    """Unit normals from central differences of the vertex map (NaN at borders and holes)."""
    dx = np.full_like(vertices, np.nan)
    dy = np.full_like(vertices, np.nan)
    dx[:, 1:-1] = vertices[:, 2:] - vertices[:, :-2]
    dy[1:-1] = vertices[2:] - vertices[:-2]
    n = cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    n[(norm[..., 0] < 1e-9)] = np.nan
    return n


def downsample(depth_m: np.ndarray, K: Intrinsics, factor: int) -> tuple[np.ndarray, Intrinsics]:
    """Every ``factor``-th pixel of a depth image and the matching intrinsics."""
    if factor == 1:
        return depth_m, K
    return depth_m[::factor, ::factor], K.subsampled(factor)


def project(points: np.ndarray, K: Intrinsics, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) onto an image of ``shape`` (h, w): the mask of points in front of the camera
    that land inside it, and their flat pixel indices (row * w + column, nearest pixel)."""
    h, w = shape
    with np.errstate(invalid="ignore", divide="ignore"):
        u, v = points_to_pixels(points, K)
        u, v = np.round(u), np.round(v)
    ok = (points[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return ok, v[ok].astype(int) * w + u[ok].astype(int)


def correspond(
    points: np.ndarray, dst_v: np.ndarray, dst_n: np.ndarray, K: Intrinsics
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective association: the points (in the target camera) that land inside the target image, and the
    target vertex and normal at their pixel (NaN where the target has none)."""
    ok, idx = project(points, K, dst_v.shape[:2])
    return points[ok], dst_v.reshape(-1, 3)[idx], dst_n.reshape(-1, 3)[idx]


@dataclass(frozen=True)
class IcpTarget:
    """The destination side of ICP at one resolution: vertex and normal maps and their intrinsics (prepared
    once per depth image: a keyframe is the target of every frame refined against it)."""

    vertices: np.ndarray
    normals: np.ndarray
    K: Intrinsics
    level: int


def icp_target(dst_depth: np.ndarray, K: Intrinsics, level: int = 2) -> IcpTarget:
    """``dst_depth`` prepared as an ICP target at 1/``level`` resolution."""
    depth, K_level = downsample(dst_depth, K, level)
    vertices = vertex_map(smooth_depth(depth, 5), K_level)
    return IcpTarget(vertices, normal_map(vertices), K_level, level)


def icp_refine(
    src_depth: np.ndarray,
    dst_depth: np.ndarray | IcpTarget,
    K: Intrinsics,
    T_init: np.ndarray,
    level: int = 2,
    step: int = 3,
    iterations: int = 10,
    max_dist: tuple[float, float] = (0.08, 0.02),
    min_inliers: int = 300,
) -> IcpResult | None:
    """Refine ``T_dst_src`` (maps src camera points into the dst camera) by point-to-plane ICP.

    Both images are used at 1/``level`` resolution, the source further subsampled by ``step``; the target may
    be given prepared (``icp_target``, at the same level). Returns None when too few correspondences survive
    (degenerate geometry or a bad initial guess).
    """
    target = dst_depth if isinstance(dst_depth, IcpTarget) else icp_target(dst_depth, K, level)
    if target.level != level:
        raise ValueError(f"an ICP target prepared at level {target.level} used at level {level}")
    src_depth, _ = downsample(src_depth, K, level)
    dst_v, dst_n, K = target.vertices, target.normals, target.K
    src = vertex_map(smooth_depth(src_depth, 5), K)[::step, ::step].reshape(-1, 3)
    src = src[np.isfinite(src[:, 2])]
    T = T_init.copy()
    A = np.zeros((0, 6))
    residual = np.zeros(0)
    for it in range(iterations):
        gate = max_dist[0] + (max_dist[1] - max_dist[0]) * it / max(1, iterations - 1)
        pp, q, n = correspond(src @ T[:3, :3].T + T[:3, 3], dst_v, dst_n, K)
        r = np.einsum("ij,ij->i", pp - q, n)
        d = pp - q
        with np.errstate(invalid="ignore"):
            good = np.isfinite(r) & (np.einsum("ij,ij->i", d, d) < gate * gate)
        if good.sum() < min_inliers:
            return None
        pp, n, residual = pp[good], n[good], r[good]
        A = np.hstack([cross(pp, n), n])
        xi = np.linalg.solve(A.T @ A + 1e-9 * np.eye(6), -A.T @ residual)
        T = _exp_se3(xi) @ T
        if np.linalg.norm(xi) < 1e-6:
            break
    rmse = float(np.sqrt(np.mean(residual**2)))
    info = A.T @ A / max(rmse, 1e-3) ** 2
    return IcpResult(T, rmse, float(len(residual) / max(1, len(src))), len(residual), info)


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """Small-motion update: rotation vector xi[:3] (Rodrigues), translation xi[3:]."""
    theta = np.linalg.norm(xi[:3])
    T = np.eye(4)
    if theta > 1e-12:
        k = xi[:3] / theta
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        T[:3, :3] = np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx
    T[:3, 3] = xi[3:]
    return T


@dataclass(frozen=True)
class Agreement:
    """How well two depth images agree under a relative pose: of the source points that land on valid target
    depth, the fraction within ``tol`` of the target surface (point-to-plane), and how many landed."""

    fraction: float
    overlap: int


def depth_agreement(
    src_depth: np.ndarray,
    dst_depth: np.ndarray,
    K: Intrinsics,
    T_dst_src: np.ndarray,
    level: int = 4,
    tol_m: float = 0.015,
    tol_ratio: float = 0.01,
) -> Agreement:
    """The evidence for a relative pose that does not depend on how it was found: ``src_depth``'s points moved
    by ``T_dst_src`` against ``dst_depth`` (at 1/``level`` resolution), within ``tol_m`` + ``tol_ratio`` x
    depth of its surface along the normal, and no more than 3 x that nearer or farther along the ray."""
    src_depth, _ = downsample(src_depth, K, level)
    dst_depth, Kd = downsample(dst_depth, K, level)
    src = vertex_map(src_depth, Kd).reshape(-1, 3)
    src = src[np.isfinite(src[:, 2])]
    dst_v = vertex_map(dst_depth, Kd)
    dst_n = normal_map(dst_v)
    pp, q, n = correspond(src @ T_dst_src[:3, :3].T + T_dst_src[:3, 3], dst_v, dst_n, Kd)
    valid = np.isfinite(q[:, 2]) & np.isfinite(n[:, 0])
    if not valid.any():
        return Agreement(0.0, 0)
    pp, q, n = pp[valid], q[valid], n[valid]
    tol = tol_m + tol_ratio * q[:, 2]
    plane = np.abs(np.einsum("ij,ij->i", pp - q, n))
    close = (plane < tol) & (np.abs(pp[:, 2] - q[:, 2]) < 3 * tol)
    return Agreement(float(close.mean()), len(pp))


COARSE_TO_FINE: tuple[tuple[int, int, int, tuple[float, float]], ...] = (
    (8, 1, 12, (0.30, 0.10)),
    (4, 2, 10, (0.10, 0.03)),
    (2, 3, 8, (0.04, 0.02)),
)
"""``icp_pyramid``'s levels: (resolution divisor, source step, iterations, correspondence gate first / last)."""


def icp_pyramid(
    src_depth: np.ndarray,
    dst_depth: np.ndarray,
    K: Intrinsics,
    T_init: np.ndarray,
    levels: tuple[tuple[int, int, int, tuple[float, float]], ...] = COARSE_TO_FINE,
    min_inliers: int = 100,
) -> IcpResult | None:
    """``icp_refine`` coarse to fine: a wide correspondence gate on small images first, so that a start tens of
    centimetres off (a motion prior, not a measurement) still converges; None when a level fails."""
    T, result = T_init, None
    for level, step, iterations, gate in levels:
        result = icp_refine(src_depth, dst_depth, K, T, level, step, iterations, gate, min_inliers)
        if result is None:
            return None
        T = result.T
    return result


def degenerate_directions(information: np.ndarray, ratio: float = 1e-3) -> int:
    """How many of the 6 motion directions the ICP information barely constrains (eigenvalue below ``ratio``
    of the largest, in units of metres and radians at 1 m): a plain wall leaves 3, a corridor 1."""
    eig = np.linalg.eigvalsh(0.5 * (information + information.T))
    return int((eig < ratio * max(float(eig.max()), 1e-12)).sum())


def icp_ambiguity(
    src_depth: np.ndarray, dst_depth: np.ndarray, K: Intrinsics, result: IcpResult, offset_m: float = 0.05
) -> float:
    """How far ICP's answer depends on where it starts: ``result`` restarted ``offset_m`` away along its
    least constrained translation direction, both ways (the finer pyramid levels); the larger distance (m)
    between where the restarts end and ``result``, inf when one fails. Millimetres when the geometry pins the
    pose; centimetres when a wall and the ceiling are all there is and the camera may slide along them."""
    _, vectors = np.linalg.eigh(0.5 * (result.information[3:, 3:] + result.information[3:, 3:].T))
    spread = 0.0
    for sign in (-1.0, 1.0):
        start = result.T.copy()
        start[:3, 3] += sign * offset_m * vectors[:, 0]
        again = icp_pyramid(src_depth, dst_depth, K, start, COARSE_TO_FINE[1:])
        if again is None:
            return float("inf")
        spread = max(spread, float(np.linalg.norm(again.T[:3, 3] - result.T[:3, 3])))
    return spread
