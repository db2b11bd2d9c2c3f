"""Same-class objects that stand in one place are one object.

Two detections in one image are two objects (``clustering.merge_overlapping`` never joins clusters that share a
keyframe), but in a row of chairs the views of neighbours can mix: two clusters then each hold views of both
chairs and both land between them, a few centimetres to a few decimetres apart, one of them a duplicate. Two
real objects of one class cannot stand inside each other: when one object's centre lies well inside the other's
extent, their clusters are joined, whatever keyframes they share.

A detector also calls one object by two names from frame to frame (a mug a "cup" here and a "bowl" there: on the
7-Scenes kitchen a "bowl" object stood 1-2.4 cm from the "cup" it was, as large). Two objects of different classes
do stand close (a cup on a book, a plant in a vase), but not the same size with each centre inside the other's
reach: side by side, two objects as large as each other stand their width apart, over twice that reach. Such a
pair (``SAME_SIZE``) is one object, named by its larger cluster.

A large object seen in parts (``footprint.LARGE_CLASSES``: a table whose views each show the part of its top in
view) can leave its parts in clusters of their own, side by side. One object is detected once in an image, so
its parts are never in one keyframe, while two tables that stand close are seen together. Two such objects whose
extents touch along the line between their centres, and which no keyframe saw together, are one
(``touching``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from perception.floor import view_ends
from perception.footprint import LARGE_CLASSES


def extent_radius(cov: np.ndarray, stds: float) -> float:
    """An object's typical reach: ``stds`` times its median standard deviation."""
    return stds * float(np.sqrt(np.median(np.clip(np.linalg.eigvalsh(cov), 0.0, None))))


SAME_SIZE = 1.5
"""Two objects are the same size when their reaches (``extent_radius``) differ by at most this factor."""


def touching(mean_a: np.ndarray, cov_a: np.ndarray, mean_b: np.ndarray, cov_b: np.ndarray) -> bool:
    """Whether two objects' uniform extents (``sqrt(3)`` standard deviations from their centres) touch along the
    line between their centres."""
    gap = mean_b - mean_a
    dist = float(np.linalg.norm(gap))
    if dist == 0.0:
        return True
    d = gap / dist
    far_a = view_ends(mean_a[None], cov_a[None], d)[0][0]
    near_b = view_ends(mean_b[None], cov_b[None], d)[1][0]
    return bool(near_b <= far_a)


def coincident_groups(
    labels: Sequence[str],
    means: np.ndarray,
    covs: np.ndarray,
    stds: float,
    keyframes: Sequence[set[int]] | None = None,
) -> list[list[int]]:
    """Groups of object indices to join: centres closer than the smaller of their reaches (``extent_radius`` of
    ``stds``), of one label, or of two labels with reaches within ``SAME_SIZE`` of each other (one object seen
    under two labels); transitively. With the ``keyframes`` that saw each object, also two of
    one large class (``LARGE_CLASSES``) that ``touching`` and that no keyframe saw in one group. Every index is in
    exactly one group, in order; with ``stds`` 0, each its own."""
    n = len(labels)
    if stds <= 0:
        return [[i] for i in range(n)]
    radius = [extent_radius(c, stds) for c in covs]
    parent = list(range(n))
    seen = [set(k) for k in keyframes] if keyframes is not None else None  # by root: the keyframes of its group

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            gap, reach = float(np.linalg.norm(means[i] - means[j])), min(radius[i], radius[j])
            ri, rj = root(i), root(j)
            same = labels[i] == labels[j]
            join = gap < reach and (same or max(radius[i], radius[j]) <= SAME_SIZE * reach)
            if not join and same and seen is not None and labels[i] in LARGE_CLASSES and ri != rj:
                join = not seen[ri] & seen[rj] and touching(means[i], covs[i], means[j], covs[j])
            if join and ri != rj:
                parent[rj] = ri
                if seen is not None:
                    seen[ri] |= seen[rj]
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())
