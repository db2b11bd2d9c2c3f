"""The pinhole camera: intrinsics, projection of camera-frame points to pixels and back-projection of pixels.

Camera axes are OpenCV's (x right, y down, z forward); pixel ``(u, v)`` is column ``u``, row ``v``.
Every projection and back-projection of objslam is written here, once.

The results are those of the formulas as written, in numpy's arithmetic: the dtype of the result is the
promotion of the inputs' dtypes with the intrinsics' (an ``Intrinsics`` of Python floats keeps float32
arrays float32). Two call sites need another order of the same operations, which rounds differently, and
keep it by a keyword: the depth warping (``perception.warp``) projects as ``fx * x / z + cx``
(``scale_first``) and back-projects as ``(u - cx) * (z / fx)`` (``depth_first``), in float32 (``dtype``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

Scalar = Any  # a float, or a numpy scalar of ``dtype``


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        """The 3x3 matrix K (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def subsampled(self, step: int | float) -> Intrinsics:
        """The intrinsics of every ``step``-th pixel of every ``step``-th row: pixel u there is pixel step * u
        here, so the principal point scales with the focal lengths."""
        return Intrinsics(self.fx / step, self.fy / step, self.cx / step, self.cy / step)


def _values(K: Intrinsics, dtype: type[np.floating] | None) -> tuple[Scalar, Scalar, Scalar, Scalar]:
    """fx, fy, cx, cy as they are, or cast to ``dtype``."""
    if dtype is None:
        return K.fx, K.fy, K.cx, K.cy
    return dtype(K.fx), dtype(K.fy), dtype(K.cx), dtype(K.cy)


def pixel_rays(u: Any, v: Any, K: Intrinsics) -> tuple[Any, Any]:
    """Normalised image coordinates ``((u - cx) / fx, (v - cy) / fy)``: the ray of pixel (u, v) meets depth 1
    at ``(a, b, 1)``. ``u``, ``v``: arrays (broadcast together) or scalars."""
    return (u - K.cx) / K.fx, (v - K.cy) / K.fy


def backproject_xy(
    u: Any,
    v: Any,
    z: Any,
    K: Intrinsics,
    *,
    depth_first: bool = False,
    dtype: type[np.floating] | None = None,
) -> tuple[Any, Any]:
    """Camera-frame x and y of pixels (u, v) at depth z: ``(u - cx) / fx * z``, ``(v - cy) / fy * z``.

    ``depth_first``: ``(u - cx) * (z / fx)`` instead. ``dtype``: u, v and the intrinsics cast to it first.
    """
    fx, fy, cx, cy = _values(K, dtype)
    if dtype is not None:
        u, v = np.asarray(u, dtype), np.asarray(v, dtype)
    if depth_first:
        return (u - cx) * (z / fx), (v - cy) * (z / fy)
    return (u - cx) / fx * z, (v - cy) / fy * z


def pixels_to_points(
    u: Any,
    v: Any,
    z: Any,
    K: Intrinsics,
    *,
    depth_first: bool = False,
    dtype: type[np.floating] | None = None,
) -> np.ndarray:
    """Camera-frame points ``(..., 3)`` of pixels (u, v) at depth z (``backproject_xy``, then z).

    u, v and z broadcast together: (N,) each for N pixels, or a row of columns, a column of rows and an
    image of depths for a vertex map.
    """
    x, y = backproject_xy(u, v, z, K, depth_first=depth_first, dtype=dtype)
    return np.stack([x, y, z], axis=-1)


def project_uv(
    x: Any,
    y: Any,
    z: Any,
    K: Intrinsics,
    *,
    scale_first: bool = False,
    dtype: type[np.floating] | None = None,
) -> tuple[Any, Any]:
    """Pixel coordinates (u, v) of camera-frame points: ``u = x / z * fx + cx``, ``v = y / z * fy + cy``
    (not rounded; z <= 0 is the caller's to exclude or ignore).

    ``scale_first``: ``fx * x / z + cx`` instead. ``dtype``: the intrinsics cast to it first.
    """
    fx, fy, cx, cy = _values(K, dtype)
    if scale_first:
        return fx * x / z + cx, fy * y / z + cy
    return x / z * fx + cx, y / z * fy + cy


def points_to_pixels(points: np.ndarray, K: Intrinsics, *, scale_first: bool = False) -> tuple[Any, Any]:
    """``project_uv`` of points ``(..., 3)``."""
    return project_uv(points[..., 0], points[..., 1], points[..., 2], K, scale_first=scale_first)


def ray_matrix(K: Intrinsics, x0: float = 0.0, y0: float = 0.0) -> np.ndarray:
    """The 3x3 matrix (float64) taking pixel ``(i, j, 1)`` of a window whose first pixel is (x0, y0) to its
    ray ``(a, b, 1)`` (``pixel_rays`` of (x0 + i, y0 + j)): K^-1 for a window at the origin."""
    a0, b0 = pixel_rays(x0, y0, K)
    return np.array([[1.0 / K.fx, 0.0, a0], [0.0, 1.0 / K.fy, b0], [0.0, 0.0, 1.0]])
