"""Same-class objects that stand in one place are one object.

Two detections in one image are two objects (``clustering.merge_overlapping`` never joins clusters that share a
keyframe), but in a row of chairs the views of neighbours can mix: two clusters then each hold views of both
chairs and both land between them, a few centimetres to a few decimetres apart, one of them a duplicate. Two
real objects of one class cannot stand inside each other: when one object's centre lies well inside the other's
extent, their clusters are joined, whatever keyframes they share.

A detector also calls one object by two names from frame to frame (a mug a "cup" here and a "bowl" there: on the
7-Scenes kitchen a "bowl" object stood 1 cm from the "cup" it was, as large). Two objects of different classes do
stand close (a cup on a book, a plant in a vase), but not with one centre deep inside the other and the same size:
such a pair (``RELABELLED``, ``SAME_SIZE``) is one object, named by its larger cluster.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def extent_radius(cov: np.ndarray, stds: float) -> float:
    """An object's typical reach: ``stds`` times its median standard deviation."""
    return stds * float(np.sqrt(np.median(np.clip(np.linalg.eigvalsh(cov), 0.0, None))))


RELABELLED = 0.5
"""Objects of two labels whose centres are closer than this share of the smaller one's reach are one object seen
under two labels, when they are the same size (``SAME_SIZE``)."""

SAME_SIZE = 1.5
"""Two objects are the same size when their reaches (``extent_radius``) differ by at most this factor."""


def coincident_groups(labels: Sequence[str], means: np.ndarray, covs: np.ndarray, stds: float) -> list[list[int]]:
    """Groups of object indices to join: same label, centres closer than the smaller of their reaches
    (``extent_radius`` of ``stds``); or different labels, centres closer than ``RELABELLED`` of that and reaches
    within ``SAME_SIZE`` of each other; transitively. Every index is in exactly one group, in order; with
    ``stds`` 0, each its own."""
    n = len(labels)
    if stds <= 0:
        return [[i] for i in range(n)]
    radius = [extent_radius(c, stds) for c in covs]
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            gap, reach = float(np.linalg.norm(means[i] - means[j])), min(radius[i], radius[j])
            if labels[i] == labels[j]:
                join = gap < reach
            else:
                join = gap < RELABELLED * reach and max(radius[i], radius[j]) <= SAME_SIZE * reach
            if join:
                parent[root(j)] = root(i)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())
