"""The regular grid a box's pixels lie on.

``features.box_pixels`` takes a box's pixels at one stride, so a detection's pixels (and any subset of them, such
as its depth segment) sit on a grid: an origin, a step, and each pixel's row and column on it. Filters and
summed-area tables over that grid work on the pixels as an image.
"""

from __future__ import annotations

import numpy as np


def grid_of(rows: np.ndarray, cols: np.ndarray) -> tuple[int, int, int, np.ndarray, np.ndarray]:
    """The grid pixels (rows, cols) lie on: its origin row and column (the smallest), its step (the greatest
    common divisor of their offsets from it; 1 for a single pixel) and each pixel's grid row and column."""
    r0, c0 = int(rows.min()), int(cols.min())
    step = int(np.gcd.reduce(np.r_[rows - r0, cols - c0])) or 1
    return r0, c0, step, (rows - r0) // step, (cols - c0) // step
