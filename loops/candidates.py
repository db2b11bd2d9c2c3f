"""Loop-closure candidates of a keyframe: proposed ones (the RL policy), appearance, and proximity."""

from __future__ import annotations

import math

import numpy as np

from graph.geometry import motion_magnitude, relative
from loops.archive import KeyframeArchive
from loops.place_recognition import PlaceIndex
from loops.records import Candidate, KeyframeEntry, Source
from loops.settings import LoopSettings


def nearby(entry: KeyframeEntry, keyframes: KeyframeArchive, poses: np.ndarray, settings: LoopSettings) -> list[int]:
    """Old keyframes whose estimate (in ``poses``) lies near the new one's (geometric candidates)."""
    c = settings
    old = [k for k, t in keyframes.timestamps() if t <= entry.timestamp - c.min_gap_s]
    if not old or entry.index >= len(poses):
        return []
    here = poses[entry.index]
    dist = np.linalg.norm(poses[old, :3, 3] - here[:3, 3], axis=1)
    near: list[int] = []
    for i in np.argsort(dist):
        if dist[i] > c.proximity_m or len(near) >= c.proximity_k:
            break
        _, angle = motion_magnitude(relative(poses[old[i]], here))
        if math.degrees(angle) <= c.proximity_deg:
            near.append(old[i])
    return near


def candidates(
    entry: KeyframeEntry,
    descriptor: np.ndarray,
    proposed: list[Candidate],
    keyframes: KeyframeArchive,
    places: PlaceIndex,
    poses: np.ndarray | None,
    settings: LoopSettings,
) -> list[Candidate]:
    """The candidates to verify, in order: ``proposed`` ones first, then (when ``source`` is appearance or
    both) the most similar places and the keyframes near the current estimate (``poses``; None: none).
    A keyframe is listed once, under the first source that found it."""
    found = [c for c in proposed if c.keyframe in keyframes]
    if not settings.classical:
        return found
    tried = {c.keyframe for c in found}
    c = settings
    for place in places.query(descriptor, entry.timestamp, c.min_gap_s, c.top_k, c.min_similarity):
        if place.index not in tried:
            found.append(Candidate(place.index, Source.APPEARANCE, place.similarity))
    if c.proximity and poses is not None:
        tried = {c.keyframe for c in found}
        found += [Candidate(i, Source.PROXIMITY) for i in nearby(entry, keyframes, poses, settings) if i not in tried]
    return found
