"""A table's view from its top (issue 24): the part of the table a view shows is the part of its top it shows.

A camera above a table's top sees that top to its far edge, except where things on it hide it, and the top is
the object's extent across the floor. The view's other points are not: a table's box holds the chairs around it,
its legs and its front face, and a depth completion as deep as the points are wide stretches a top seen along
its length to as deep as it is wide. On development seeds 0-15 tables came out 0.2-0.3 m too wide and too long
(their views' ends 0.13-0.18 m past the true ends in the median, on each side), so their ground-plane IoU was
that of a box a third too large.

``top_view`` finds the top as the highest level band of the view's points that holds about as many of them as
the fullest band, and describes it by its points weighted by the area each pixel covers there: a top seen at a
grazing angle from a few metres holds many more pixels per square metre near the camera than far from it. The
moments of a uniformly sampled rectangle give its ends exactly along its own axes (``sqrt(3)`` standard
deviations from its centre), and those are the axes ``footprint.union_footprint`` measures along.

Pure computation, no I/O.
"""

from __future__ import annotations

import numpy as np

TOP_CLASSES: frozenset[str] = frozenset({"dining table"})
"""Classes whose views are measured by their top surface."""

BAND_M = 0.02
"""Half height of a level band (the top's points within this of its height)."""

FULL_SHARE = 0.5
"""A band is the top when it holds this share of the fullest band's points and none higher does."""

MIN_SHARE = 0.03
"""The top must hold this share of the view's points, else the view is completed as any other. A top seen from
a few metres at a camera's height of 1.3-1.5 m is a sliver of the image beside the table's front face (on the
development seeds, 4-5 % of a table view's points)."""

MIN_STD_M = 0.05
"""The top's points must spread this much across the floor in every direction (a uniform extent of 0.17 m): a
surface, not the upper edge of a face seen from below the top (where the highest full band is a line)."""


def top_height(heights: np.ndarray, band: float = BAND_M, full: float = FULL_SHARE) -> float:
    """The height of the highest level band that holds ``full`` of the fullest band's points (bands of
    ``2 * band`` centred on 1 cm steps)."""
    steps = np.arange(float(heights.min()), float(heights.max()) + 0.01, 0.01)
    ordered = np.sort(heights)
    counts = np.searchsorted(ordered, steps + band, "right") - np.searchsorted(ordered, steps - band, "left")
    return float(steps[np.flatnonzero(counts >= full * counts.max())[-1]])


def top_view(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The area-weighted mean and horizontal covariance (camera frame) of the top surface among a view's
    ``points`` (N, 3), ``up`` the world's up in the camera frame; None when too few of them lie on it."""
    heights = points @ up
    top = points[np.abs(heights - top_height(heights)) <= BAND_M]
    if len(top) < max(20, MIN_SHARE * len(points)):
        return None
    dist = np.linalg.norm(top, axis=1)
    w = dist**3 / np.maximum(np.abs(top @ up), 0.05 * dist)  # pixel area on a level surface: z^2 / cos(incidence)
    w /= w.sum()
    mean = w @ top
    P = np.eye(3) - np.outer(up, up)
    d = (top - mean) @ P
    cov = np.einsum("n,ni,nj->ij", w, d, d)
    return (mean, cov) if np.linalg.eigvalsh(cov)[1] >= MIN_STD_M**2 else None  # [0]: along up, zero
