"""Object tracks from NPDA association chains (SPEC 6.2: "association chains give object tracks").

A detection of the current keyframe associated with one of the previous keyframe continues that
detection's track; any other detection starts a new track. Track ids never change. Each track pools
its back-projected observations over a window of keyframes into one feature vector (Sec. 2.4.4:
f summarises the object over t-n..t), which bounds the number of vectors to cluster (SPEC 6.6).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

from perception.features import FeatureVector, merge_features

log = logging.getLogger(__name__)


@dataclass
class Track:
    """One association chain: class, observation count, last keyframe, and its open feature window."""

    id: int
    label: str
    n_observations: int = 0
    last_keyframe: int = -1
    window: list[FeatureVector] = field(default_factory=list)


class Tracker:
    """Turns per-keyframe NPDA pairs into persistent track ids and windowed feature vectors.

    ``window``: observations pooled per feature vector (1 = one vector per observation, as measured
    best by `objslam bench objects`); ``min_observations``: a track must be this long (associated at
    least once) before its vectors are clustered, which keeps unassociated false positives out.
    """

    def __init__(self, window: int = 1, min_observations: int = 2) -> None:
        self.window = window
        self.min_observations = min_observations
        self.tracks: dict[int, Track] = {}
        self._prev_ids: list[int] = []
        self._next_id = 1

    def state(self) -> dict:
        """Plain state: live tracks, the previous keyframe's track ids, the next id."""
        return {"tracks": self.tracks, "prev_ids": self._prev_ids, "next_id": self._next_id}

    def restore(self, state: dict) -> None:
        self.tracks, self._prev_ids, self._next_id = state["tracks"], state["prev_ids"], state["next_id"]

    def update(self, keyframe: int, labels: Sequence[str], pairs: Sequence[tuple[int, int]]) -> list[int]:
        """Track id of each current detection: inherited through a (previous, current) pair, else new."""
        ids = [-1] * len(labels)
        for prev, cur in pairs:
            if 0 <= prev < len(self._prev_ids):
                ids[cur] = self._prev_ids[prev]
        for k, label in enumerate(labels):
            if ids[k] < 0:
                ids[k], self._next_id = self._next_id, self._next_id + 1
                self.tracks[ids[k]] = Track(ids[k], label)
            track = self.tracks[ids[k]]
            track.n_observations += 1
            track.last_keyframe = keyframe
        self._prev_ids = ids
        return ids

    def associated(self, track_id: int) -> bool:
        """True when the track has been associated at least once (it is in NPDA's set M)."""
        return self.tracks[track_id].n_observations >= 2

    def observe(self, track_id: int, feature: FeatureVector | None) -> FeatureVector | None:
        """Add an observation to the track's window; return the window's pooled vector when it is full."""
        track = self.tracks[track_id]
        if feature is not None:
            track.window.append(feature)
        if len(track.window) >= self.window and track.n_observations >= self.min_observations:
            return self._emit(track)
        return None

    def close_stale(self, keyframe: int) -> list[FeatureVector]:
        """End the tracks not seen at ``keyframe`` (their chain broke): pooled vectors of their open windows.

        Ended tracks are dropped from ``tracks`` (ids are never reused), so memory follows the live tracks.
        """
        out = []
        for tid in [t for t, track in self.tracks.items() if track.last_keyframe < keyframe]:
            track = self.tracks.pop(tid)
            if track.window and track.n_observations >= self.min_observations:
                out.append(self._emit(track))
        return out

    def flush(self) -> list[FeatureVector]:
        """Pooled vectors of every open window of a long-enough track (end of sequence)."""
        return self.close_stale(keyframe=1 << 62)

    def _emit(self, track: Track) -> FeatureVector:
        """Pool and clear the track's window."""
        pooled = merge_features(track.window)
        track.window = []
        return FeatureVector(pooled.mean, pooled.cov, pooled.n, track.label, track.id, pooled.sources)
