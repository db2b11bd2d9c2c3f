"""Two detections of one image are two objects: a cluster that holds both is split (issue 24).

HDBSCAN groups feature vectors by their distance alone. In a row of chairs 0.5 m apart, NPDA carries tracks from
one chair to its neighbour, their track windows bridge the gap, and one cluster can take the row: on development
seed 15 one "chair" held the views of four chairs, two or more of them in 68-70 of its 89 keyframes. A cluster of
one object holds one view per keyframe (the detector's non-maximum suppression keeps one box per object and
class); on the same seeds the clusters of one object held two views of a keyframe in at most 1 of 91.
``merge_overlapping`` already keeps such clusters from being joined; here a cluster that holds two views of a
keyframe in enough of its keyframes (``SHARED_LEAST``, ``SHARED_SHARE``) is cut by a k-means of its feature
vectors' centres, started from the two vectors of one keyframe that lie farthest apart, and the cut is
kept when its parts are clusters (``min_size`` vectors each) and it parts the views of at least ``RESOLVED`` of
those keyframes. A row of four is cut in four: as many parts as views a few of its keyframes hold, started from
that pair and each time the vector farthest from those chosen (so a track window that pooled a view of each of
two chairs, between them, joins one of them rather than starting a part). Parts that would stand in one place
(``perception.coincident``) are not made: two clusters of one chair that each hold views of its neighbour are
joined there and stay joined.

The cut needs views that lie at their own chairs: with the back chairs of a row anchored on the front one, the
views of all lay at the front chair and no cut parted them (development seeds 0-35, the cut alone: pairs at
0.5 m unchanged at 107 of 114, false objects 15 -> 20). With every detection's segment anchored off the
detections it shows, same class included (``perception.anchoring``): mapped 96.8 / 90.5 -> 100.0 / 91.6 %,
pairs at 0.5 m 107 -> 110 of 114, false objects 15 -> 22 (worst decile 5.9 -> 7.0 %), IoU 0.674 and centroid
error 0.039 m unchanged.

The coincident rule joins objects where the mapper places them (``Clusterer.locate``: a chair stands on the floor),
so a group it joined is cut again only into parts that stand apart there too (``place``). Cut by their pooled
views, two clusters of one chair were joined and cut back into the same two on every re-clustering: on development
seed 11 (box chairs) a chair of 32 views and one of 6 whose views lay on its back, 0.36 m apart pooled, 0.18 m
where the mapper placed them. Development seeds 0-35 with chairs rendered as chairs: false objects 20 -> 19, the
rest unchanged; with box chairs it was 15 -> 14 with 3 objects fewer found (seeds 0 and 15, rows of chairs whose
clusters mixed neighbours).

Pure computation, no I/O.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np

from perception.coincident import coincident_groups
from perception.features import FeatureVector, merge_features

SHARED_LEAST = 3
"""A cluster is split only when it holds two views of at least this many keyframes."""

SHARED_SHARE = 0.1
"""... and of at least this share of its keyframes."""

Place = Callable[[Sequence[FeatureVector]], "tuple[np.ndarray, np.ndarray] | None"]
"""Where the object of a cluster stands (``clustering.Locate``): its centre and covariance, or None to take the
pooled Gaussian's."""

RESOLVED = 0.5
"""A cut is kept when it leaves at most this share of those keyframes with two views in one part."""


def keyframe_sets(members: Sequence[FeatureVector], keyframe_of: Sequence[int]) -> list[set[int]]:
    """The keyframes of each feature vector's observations (``keyframe_of[s]`` for each of its ``sources``)."""
    return [{keyframe_of[s] for s in f.sources if s < len(keyframe_of)} for f in members]


def shared_keyframes(frames: Sequence[set[int]]) -> tuple[int, int]:
    """(keyframes seen by two or more of the feature vectors whose keyframe sets are ``frames``, keyframes seen)."""
    counts = Counter(k for fs in frames for k in fs)
    return sum(c > 1 for c in counts.values()), len(counts)


def _k_means(means: np.ndarray, weights: np.ndarray, seeds: list[int], iterations: int = 20) -> np.ndarray:
    """Which of ``len(seeds)`` groups each row of ``means`` falls in: weighted Lloyd iterations from rows
    ``seeds``."""
    centres = means[seeds].copy()
    side = np.zeros(len(means), int)
    for _ in range(iterations):
        side = np.argmin(np.linalg.norm(means[:, None, :] - centres[None], axis=2), axis=1)
        new = np.stack(
            [
                np.average(means[side == g], axis=0, weights=weights[side == g]) if (side == g).any() else centres[g]
                for g in range(len(seeds))
            ]
        )
        if np.allclose(new, centres):
            break
        centres = new
    return side


def _seeds(means: np.ndarray, frames: Sequence[set[int]], k: int) -> list[int]:
    """``k`` feature vectors to start from: the two of one keyframe that lie farthest apart, then each time the
    one farthest from those chosen (so the first ``j`` of them are the seeds for ``j`` parts)."""
    by_frame: dict[int, list[int]] = {}
    for i, fs in enumerate(frames):
        for f in fs:
            by_frame.setdefault(f, []).append(i)
    best, chosen = -1.0, [0, 0]
    for idx in by_frame.values():
        gaps = np.linalg.norm(means[idx][:, None, :] - means[idx][None], axis=2)
        a, b = np.unravel_index(int(np.argmax(gaps)), gaps.shape)
        if gaps[a, b] > best:
            best, chosen = float(gaps[a, b]), [idx[a], idx[b]]
    while len(chosen) < k:
        gap = np.min(np.linalg.norm(means[:, None, :] - means[chosen][None], axis=2), axis=1)
        chosen.append(int(np.argmax(gap)))
    return chosen


def _apart(parts: list[list[FeatureVector]], stds: float, place: Place | None = None) -> bool:
    """No two of ``parts`` stand in one place (``perception.coincident`` with ``stds``), each part where ``place``
    puts its object (else its pooled Gaussian): the places the objects would be joined by."""
    located = []
    for p in parts:
        where = place(p) if place is not None else None
        if where is None:
            pooled = merge_features(p)
            where = (pooled.mean, pooled.cov)
        located.append(where)
    means, covs = np.stack([m for m, _ in located]), np.stack([c for _, c in located])
    return len(coincident_groups([p[0].label for p in parts], means, covs, stds)) == len(parts)


def split_by_keyframes(
    members: list[FeatureVector],
    keyframe_of: Sequence[int],
    min_size: int,
    stds: float = 0.0,
    place: Place | None = None,
) -> list[list[FeatureVector]]:
    """The clusters ``members`` is, cut where it holds two views of one keyframe (module docstring); the
    members themselves when it holds one per keyframe, or no cut parts them. The cut is into as many parts as
    the views ``SHARED_LEAST`` of its keyframes hold, or fewer when that many are not clusters (``min_size``
    vectors each) or two of them stand in one place (``perception.coincident`` with ``stds``, each part's object
    where ``place`` puts it: the views of one chair and of its neighbour that two clusters of it each hold are not
    cut back into those)."""
    frames = keyframe_sets(members, keyframe_of)
    counts = sorted(Counter(f for fs in frames for f in fs).values(), reverse=True)
    shared = sum(c > 1 for c in counts)
    if shared < SHARED_LEAST or shared < SHARED_SHARE * len(counts) or len(members) < 2 * min_size:
        return [members]
    means, weights = np.stack([f.mean for f in members]), np.array([f.n for f in members], float)
    most = min(counts[SHARED_LEAST - 1], len(members) // min_size)
    seeds = _seeds(means, frames, most)
    for k in range(most, 1, -1):
        side = _k_means(means, weights, seeds[:k])
        parts = [[f for f, s in zip(members, side, strict=True) if s == g] for g in range(k)]
        left = sum(shared_keyframes([fs for fs, s in zip(frames, side, strict=True) if s == g])[0] for g in range(k))
        if min(len(p) for p in parts) >= min_size and left <= RESOLVED * shared and _apart(parts, stds, place):
            return parts
    return [members]


def split_all(
    clusters: list[list[FeatureVector]],
    keyframe_of: Sequence[int],
    min_size: int,
    stds: float = 0.0,
    place: Place | None = None,
) -> list[list[FeatureVector]]:
    """Every cluster of ``clusters`` split (``split_by_keyframes``), in order."""
    return [part for c in clusters for part in split_by_keyframes(c, keyframe_of, min_size, stds, place)]
