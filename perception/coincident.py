"""Same-class objects that stand in one place are one object.

Two detections in one image are two objects (``clustering.merge_overlapping`` never joins clusters that share a
keyframe), but in a row of chairs the views of neighbours can mix: two clusters then each hold views of both
chairs and both land between them, a few centimetres to a few decimetres apart, one of them a duplicate. Two
real objects of one class cannot stand inside each other: when one object's centre lies well inside the other's
extent, their clusters are joined, whatever keyframes they share.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def extent_radius(cov: np.ndarray, stds: float) -> float:
    """An object's typical reach: ``stds`` times its median standard deviation."""
    return stds * float(np.sqrt(np.median(np.clip(np.linalg.eigvalsh(cov), 0.0, None))))


def coincident_groups(labels: Sequence[str], means: np.ndarray, covs: np.ndarray, stds: float) -> list[list[int]]:
    """Groups of object indices to join: same label, centres closer than the smaller of their reaches
    (``extent_radius`` of ``stds``); transitively. Every index is in exactly one group, in order."""
    n = len(labels)
    radius = [extent_radius(c, stds) for c in covs]
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            near = float(np.linalg.norm(means[i] - means[j])) < min(radius[i], radius[j])
            if labels[i] == labels[j] and near:
                parent[root(j)] = root(i)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())
