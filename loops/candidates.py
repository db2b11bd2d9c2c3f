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
    """Old keyframes whose estimate (in ``poses``) lies near the new one's (geometric candidates): the archived
    ones at least ``min_gap_s`` older, nearest first. Only those within ``proximity_m`` are looked at one by
    one, so the cost per keyframe stays a vector operation as the map grows."""
    c = settings
    if entry.index >= len(poses):
        return []
    here = poses[entry.index]
    dist = np.linalg.norm(poses[:, :3, 3] - here[:3, 3], axis=1)
    within = np.flatnonzero(dist <= c.proximity_m)
    near: list[int] = []
    for k in within[np.argsort(dist[within], kind="stable")].tolist():
        if len(near) >= c.proximity_k:
            break
        t = keyframes.timestamp(k)
        if t is None or t > entry.timestamp - c.min_gap_s:
            continue
        _, angle = motion_magnitude(relative(poses[k], here))
        if math.degrees(angle) <= c.proximity_deg:
            near.append(k)
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
