"""A bound on the clustering's feature vectors over a long run: the ended tracks of an object are retired.

The clustering keeps the feature vectors of every track and pools each track's consecutive vectors once they
exceed ``ClusterConfig.max_features`` (``merge_track_runs``). That bound holds while the tracks are fewer than
it; a robot that keeps revisiting its objects starts new tracks on each of them (a track ends when NPDA's chain
breaks), about one per four keyframes in ``objslam bench longrun``, so past a few thousand keyframes the
vectors, each object's track set and the landmarks' track map grow with the run, and the clustering's
pairwise distances with their square.

So when the tracks alone exceed half the bound, each object's ended tracks are retired into its anchor track
(its oldest): their vectors take the anchor's id, and are then pooled in runs like any track's. The object keeps
its views, its id (``_carry_ids`` follows the anchor) and its landmark; the retired tracks' landmark
measurements are settled where they are (``graph.object_landmarks.ObjectLandmarks.settle``), since no later
clustering can move a track that no vector names.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import replace
from typing import Protocol

from perception.features import FeatureVector, merge_track_runs


class _Tracked(Protocol):
    @property
    def tracks(self) -> frozenset[int]: ...


def anchors(objects: Sequence[_Tracked], live: Collection[int]) -> dict[int, int]:
    """Each object's ended tracks (not in ``live``) other than its oldest, mapped to that oldest track."""
    out: dict[int, int] = {}
    for o in objects:
        if len(o.tracks) > 1:
            anchor = min(o.tracks)
            out.update((t, anchor) for t in o.tracks if t != anchor and t not in live)
    return out


def compacted(
    features: list[FeatureVector], objects: Sequence[_Tracked], live: Collection[int], max_features: int
) -> tuple[list[FeatureVector], list[int]]:
    """``features`` within ``max_features`` where pooling allows, and the tracks retired to get there (sorted).

    Pools each track's consecutive vectors in runs until at most ``max_features`` remain; first, when the
    distinct tracks are more than half of them, retires the objects' ended tracks into their anchors."""
    retired: list[int] = []
    if len(features) > max_features and len({f.track_id for f in features}) > max_features // 2:
        to = anchors(objects, live)
        if to:
            features = [replace(f, track_id=to[f.track_id]) if f.track_id in to else f for f in features]
            retired = sorted(to)
    while len(features) > max_features:
        merged = merge_track_runs(features, -(-len(features) // max_features))
        if len(merged) == len(features):
            break
        features = merged
    return features, retired
