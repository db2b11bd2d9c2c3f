"""A cluster holding two views of one keyframe in many keyframes is two objects (``perception.cannot_link``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from perception.cannot_link import SHARED_LEAST, shared_keyframes, split_by_keyframes
from perception.clustering import ClusterConfig, Clusterer
from perception.features import FeatureVector, merge_features


def _views(
    xs: list[float], keyframes: int, seed: int, var: float = 0.01, along: float | None = None
) -> tuple[list[FeatureVector], list[int]]:
    """One view of each object at ``xs`` (m along a row) in each keyframe, each view its own track window and
    observation; and the keyframe of each observation. ``var``: their variance (m^2) across the row, ``along``
    along it (default ``var``)."""
    rng = np.random.default_rng(seed)
    views, keyframe_of = [], []
    for k in range(keyframes):
        for j, x in enumerate(xs):
            mean = np.array([x, 2.0, 0.45]) + rng.normal(0, 0.03, 3)
            views.append(
                FeatureVector(
                    mean,
                    np.diag([var if along is None else along, var, 0.05]),
                    50,
                    "chair",
                    100 * j + k,
                    (len(keyframe_of),),
                )
            )
            keyframe_of.append(k)
    return views, keyframe_of


def _xs(parts: list[list[FeatureVector]]) -> list[float]:
    return sorted(round(float(np.mean([f.mean[0] for f in p])), 1) for p in parts)


def test_two_chairs_in_every_keyframe_are_cut_apart_and_a_row_of_four_into_four() -> None:
    views, keyframe_of = _views([0.0, 0.5], 10, seed=1)
    assert shared_keyframes([{keyframe_of[s] for s in f.sources} for f in views]) == (10, 10)  # both in each
    # a track window pooling a view of each chair from two keyframes holds both keyframes
    bridge = FeatureVector(np.array([0.25, 2.0, 0.45]), np.diag([0.02, 0.01, 0.05]), 50, "chair", 999, (0, 3))
    parts = split_by_keyframes([*views, bridge], keyframe_of, min_size=3)
    assert _xs(parts) == [0.0, 0.5]
    assert sorted(len(p) for p in parts) == [10, 11]
    row, row_keyframes = _views([0.0, 0.5, 1.0, 1.5], 8, seed=2)
    assert _xs(split_by_keyframes(row, row_keyframes, min_size=3)) == [0.0, 0.5, 1.0, 1.5]


def test_one_object_seen_once_per_keyframe_stays_whole_however_spread_its_views() -> None:
    # a table seen in parts: views 1.2 m apart, one per keyframe
    table, keyframe_of = _views([0.0], 20, seed=3, var=0.1)
    for i, f in enumerate(table):
        f.mean[0] = -0.6 + 1.2 * i / 19
    assert split_by_keyframes(table, keyframe_of, min_size=3) == [table]
    # a detector's second box on one chair in fewer than SHARED_LEAST keyframes: not enough to cut
    chair, keyframe_of = _views([0.0], 20, seed=4)
    twins = [
        FeatureVector(
            chair[k].mean + np.array([0.3, 0, 0]), chair[k].cov, 50, "chair", 500 + k, (len(keyframe_of) + k,)
        )
        for k in range(SHARED_LEAST - 1)
    ]
    keyframe_of = keyframe_of + list(range(SHARED_LEAST - 1))
    assert split_by_keyframes(chair + twins, keyframe_of, min_size=3) == [chair + twins]


def _bridged(keyframes: int, bridges: int, seed: int, var: float = 0.01) -> tuple[list[FeatureVector], list[int]]:
    """Two chairs 0.5 m apart in every keyframe; ``bridges`` track windows each pool a view of the first chair
    and the next keyframe's view of the second (NPDA carried the track across), lying between them."""
    views, keyframe_of = _views([0.0, 0.5], keyframes, seed, var)
    pooled, windows = set(), []
    for i in range(bridges):
        a, b = 4 * i, 4 * i + 3  # chair 0 in keyframe 2i, chair 1 in keyframe 2i + 1
        pooled |= {a, b}
        cov = np.diag([var + 0.06, var, 0.05])
        windows.append(FeatureVector((views[a].mean + views[b].mean) / 2, cov, 100, "chair", 900 + i, (a, b)))
    return [f for j, f in enumerate(views) if j not in pooled] + windows, keyframe_of


def test_the_clusterer_cuts_a_cluster_that_took_two_chairs_of_one_keyframe() -> None:
    """Track windows between two chairs join them into one object (HDBSCAN, then ``perception.coincident``);
    cut where a keyframe holds two views, they are the two chairs."""
    views, keyframe_of = _bridged(16, 4, seed=5, var=0.03)
    clusterer = Clusterer(ClusterConfig(split_shared=False))
    clusterer.keyframe_of = keyframe_of
    clusterer.add(views)
    assert [o.n_observations for o in clusterer.recluster()] == [28]
    clusterer.config = ClusterConfig()
    objects = sorted(clusterer.recluster(), key=lambda o: float(o.mean[0]))
    assert len(objects) == 2
    assert abs(objects[0].mean[0] - 0.0) < 0.1 and abs(objects[1].mean[0] - 0.5) < 0.1
    assert sorted(o.n_observations for o in objects) == [13, 15]


def test_a_cut_is_not_made_into_parts_whose_objects_would_stand_in_one_place() -> None:
    """A chair whose views in a few keyframes lie high on its back (a second box on it): pooled, the two parts
    stand 0.36 m apart and are cut; placed as the mapper places objects (here: standing on the floor), they stand
    in one place, so the coincident rule would join them again, and the cut is not made."""
    seat, keyframe_of = _views([0.0], 12, seed=6)
    backs = [
        FeatureVector(
            seat[k].mean + np.array([0.0, 0.1, 0.35]), seat[k].cov, 50, "chair", 700 + k, (len(keyframe_of) + k,)
        )
        for k in range(6)
    ]
    members, keyframe_of = seat + backs, keyframe_of + list(range(6))
    assert len(split_by_keyframes(members, keyframe_of, min_size=3, stds=1.5)) == 2

    def on_floor(part: Sequence[FeatureVector]) -> tuple[np.ndarray, np.ndarray]:
        pooled = merge_features(part)
        return np.array([*pooled.mean[:2], 0.45]), pooled.cov

    assert split_by_keyframes(members, keyframe_of, min_size=3, stds=1.5, place=on_floor) == [members]
