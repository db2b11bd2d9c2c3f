"""The clustering's bound over a long run (``perception.track_retirement``): an object's ended tracks are
retired into its anchor track, so the vectors, the objects' track sets and the landmarks' track map stay
bounded while a robot revisits its objects with new tracks."""

from __future__ import annotations

import numpy as np

from perception.clustering import ClusterConfig, Clusterer
from perception.features import FeatureVector
from perception.track_retirement import anchors, compacted

CENTRES = {"chair": np.array([0.0, 0.0, 0.5]), "cup": np.array([2.0, 1.0, 0.8])}


def _views(rng: np.random.Generator, label: str, track: int, n: int, start: int) -> list[FeatureVector]:
    cov = np.diag([0.04, 0.04, 0.09]) if label == "chair" else np.diag([0.002, 0.002, 0.003])
    return [
        FeatureVector(CENTRES[label] + rng.normal(0, 0.01, 3), cov, 200, label, track, (start + i,)) for i in range(n)
    ]


def _revisits(clusterer: Clusterer, laps: int, first_track: int = 0) -> int:
    """Each lap sees both objects with new tracks of two views each; returns the next track id."""
    rng, track = np.random.default_rng(first_track), first_track
    for _ in range(laps):
        for label in CENTRES:
            clusterer.add(_views(rng, label, track, 2, 2 * track))
            track += 1
    return track


def test_a_long_run_of_revisits_keeps_the_vectors_and_track_sets_bounded_and_the_objects_as_they_were():
    config = ClusterConfig(max_features=40)
    clusterer = Clusterer(config)
    track = _revisits(clusterer, 5)
    first = {o.label: o for o in clusterer.recluster()}
    assert set(first) == {"chair", "cup"}
    for _ in range(8):  # 80 more tracks: twice the bound in tracks alone
        track = _revisits(clusterer, 5, track)
        live = {track - 2, track - 1}  # the last lap's tracks are still open
        objects = {o.label: o for o in clusterer.recluster(live)}
        assert len(clusterer.features) <= config.max_features
        assert {k: o.id for k, o in objects.items()} == {k: o.id for k, o in first.items()}  # ids carried
        for label, o in objects.items():
            assert np.linalg.norm(o.mean - CENTRES[label]) < 0.02
            assert min(first[label].tracks) in o.tracks  # the anchor stays
    retired = clusterer.retired
    assert retired and not set(retired) & live and len(set(retired)) == len(retired)
    assert max(len(o.tracks) for o in objects.values()) <= config.max_features // 2
    assert not {f.track_id for f in clusterer.features} & set(retired)
    sources = sorted(s for f in clusterer.features for s in f.sources)
    assert sources == list(range(2 * track))  # no view lost: each observation pooled into one vector


def test_tracks_are_retired_only_past_the_bound_and_never_while_open():
    features = [FeatureVector(np.zeros(3), np.eye(3), 10, "cup", t, (t,)) for t in range(10)]

    class Obj:
        tracks = frozenset(range(10))

    assert anchors([Obj()], live={3, 9}) == {t: 0 for t in range(10) if t not in {0, 3, 9}}
    same, retired = compacted(features, [Obj()], live=(), max_features=10)
    assert same is features and retired == []  # within the bound: left as it is
    out, retired = compacted(features, [Obj()], live={3}, max_features=8)
    assert retired == [1, 2, 4, 5, 6, 7, 8, 9] and len(out) <= 8
    assert {f.track_id for f in out} == {0, 3}
