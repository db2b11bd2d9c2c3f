"""Where an object lies from its views: robust to the few that are another object's (``robust_gaussian``), and
for a large object seen in parts, the union of its views' extents across the floor (issue 24).

A dining table, a couch, a bed or a screen is wider than most views show: the image border cuts it, chairs and
clutter hide parts, and a walk past it sees one end for many keyframes and the other for a few. Pooled, its
views' Gaussians centre it on the part seen most and stretch it along the line of sight, not along the object
(development scenes 0-15: tables lay 0.21 m off in the median, along their long side). Here the extent along
each of the object's horizontal axes (those of its views together: their Gaussians' mixture, whose spread runs
along the object) is where its views' extents end, ``sqrt(3)`` standard deviations from their centres as for a
uniform extent, with an outer share of the weight at either end left out as views of something else
(``union_footprint``): ``UNION_SHARES``, a small one along the wider axis, which views see in parts, a larger one
across it, which most views see whole, so that their ends scatter about it. Only the classes that are larger
than a view (``LARGE_CLASSES``, a size prior) are measured so: chairs and plants in a row have views that caught
their neighbour, and the union of those is the row (development scenes: chair IoU 0.69 -> 0.60 when every class
was measured so).

Pure computation, no I/O.
"""

from __future__ import annotations

import numpy as np

from perception.features import PANEL_DEPTH_M, mixture
from perception.floor import view_ends, weighted_quantile

PARTS_STD_M = 0.35
"""Views whose own extent exceeds this standard deviation (a uniform extent of 1.2 m: tables, couches, beds) are
parts of a large object rather than noisy copies of a whole one (``robust_gaussian``)."""


def robust_gaussian(
    means: np.ndarray,
    covs: np.ndarray,
    weights: np.ndarray,
    huber_m: float = 0.1,
    iterations: int = 20,
    parts_std_m: float = PARTS_STD_M,
) -> tuple[np.ndarray, np.ndarray]:
    """An object's centre and covariance from its views' Gaussians (N, 3) / (N, 3, 3) with ``weights`` (N,):
    the weighted geometric median of their means (Weiszfeld), and their mean covariance with the views farther
    than ``huber_m`` from it down-weighted (Huber). A few views of another object (a segment that caught the
    neighbouring chair, a track NPDA carried over to it) then pull the object little, where they pull the
    pooled mean (``merge_features``) in proportion to their number. The spread of a whole object's view centres
    about its centre is their error, not its extent, and is left out (development seeds 0-15: small objects
    came out 1.3-1.6 x their size with it; median IoU 0.617 -> 0.623, worst decile 0.476 -> 0.510). A large
    object (the views' mean covariance wider than ``parts_std_m``) is seen in parts, each view a different one:
    its views are pooled as they are, spread included, since the median of parts is the part seen most. (Views
    cut small by the image border escape this test: the 7-Scenes kitchen table, seen in such parts, lies 0.70 m
    off, 0.48 m with pooled views.)"""
    n = np.asarray(weights, float)
    w = n / n.sum()
    centre = w @ means
    if float(np.linalg.eigvalsh(np.einsum("n,nij->ij", w, covs))[-1]) > parts_std_m**2:  # parts of a large object
        return mixture(means, covs, n)
    for _ in range(iterations):
        centre = np.average(means, axis=0, weights=n / np.maximum(np.linalg.norm(means - centre, axis=1), 1e-3))
    w = n * np.minimum(1.0, huber_m / np.maximum(np.linalg.norm(means - centre, axis=1), 1e-9))
    return centre, np.einsum("n,nij->ij", w / w.sum(), covs)


LARGE_CLASSES: frozenset[str] = frozenset({"dining table", "couch", "bed", "tv"})
"""COCO classes whose instances are usually wider than a metre and seen in parts."""

UNION_SHARES: tuple[float, float] = (0.05, 0.2)
"""Share of the views' weight left out at each end of the wider and of the narrower horizontal axis. Development
scenes 0-15, large objects' median IoU / centroid error: pooled 0.524 / 0.217 m; (0.1, 0.1) 0.560 / 0.156 m
with the axes of the pooled Gaussian; with the mixture's axes (0.1, 0.3) 0.605 / 0.143 m, (0.05-0.1, 0.3-0.4)
within 0.01 of it, (0.15, ...) and (..., 0.2) lower. Since a table's view is the part of its top it shows
(``perception.table_top``), which ends where the top does or short of it (things on it hide the top behind
them) rather than past it, less is left out: on development scenes 0-35, recomputed from the final clusters'
views, (0.1, 0.3) -> (0.05, 0.2) moved tables' median IoU / centroid error 0.648 / 0.097 -> 0.681 / 0.100 m,
couches' 0.616 / 0.167 -> 0.638 / 0.144 m, beds' 0.652 / 0.245 -> 0.662 / 0.217 m ((0.05, 0.1): tables 0.699,
couches 0.619)."""

PANEL_SHARES: tuple[float, float] = (0.1, 0.3)
"""``UNION_SHARES`` of a panel (a screen, ``features.PANEL_DEPTH_M``): its views show its face whole, so their ends
scatter about its ends, across its face and through its few centimetres of depth, and more of them are left out
(development scenes 0-35: tvs' median IoU / centroid error 0.700 / 0.026 m with these, 0.658 / 0.031 m with
``UNION_SHARES``)."""


def shares_of(label: str) -> tuple[float, float]:
    """The shares of its views ``union_footprint`` leaves out at the ends of an object of class ``label``."""
    return PANEL_SHARES if label in PANEL_DEPTH_M else UNION_SHARES


def level_basis(up: np.ndarray) -> np.ndarray:
    """Two orthonormal axes (3, 2) across the unit vector ``up``."""
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)], axis=1)


def horizontal_axes(cov: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The principal axes (2, 3) of ``cov`` across the unit vector ``up``, the wider first."""
    basis = level_basis(up)
    _, vecs = np.linalg.eigh(basis.T @ cov @ basis)
    return (basis @ vecs[:, ::-1]).T


def union_footprint(
    mean: np.ndarray,
    cov: np.ndarray,
    views: tuple[np.ndarray, np.ndarray, np.ndarray],
    up: np.ndarray,
    shares: tuple[float, float] = UNION_SHARES,
) -> tuple[np.ndarray, np.ndarray]:
    """An object's Gaussian ``mean``, ``cov`` (world frame) with its extent across ``up`` replaced by the union
    of its ``views``' extents ((N, 3) means, (N, 3, 3) covariances, (N,) weights) along the horizontal axes of
    their mixture: from the weighted ``share`` quantile of the views' near ends to the ``1 - share`` quantile of
    their far ends, uniform in between, with the wider axis's and the narrower's ``shares``. Along ``up`` the
    Gaussian stays (cross terms with ``up`` dropped)."""
    means, covs, weights = views
    w = np.asarray(weights, float)
    U = np.outer(up, up)
    new_mean, new_cov = np.asarray(mean, float).copy(), U @ cov @ U
    for axis, share in zip(horizontal_axes(mixture(means, covs, w)[1], up), shares, strict=True):
        far, near = view_ends(means, covs, axis)
        lo, hi = weighted_quantile(near, w, share), weighted_quantile(far, w, 1.0 - share)
        new_mean += ((lo + hi) / 2.0 - float(axis @ new_mean)) * axis
        new_cov += (hi - lo) ** 2 / 12.0 * np.outer(axis, axis)
    return new_mean, new_cov
