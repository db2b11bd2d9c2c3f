"""Clustering (Sec. 2.4.5-2.4.6): Bhattacharyya distance, HDBSCAN with the class penalty, ellipsoids, eq. 2.15."""

from __future__ import annotations

import numpy as np
import pytest

from perception.clustering import (
    ClusterConfig,
    Clusterer,
    bhattacharyya,
    bhattacharyya_matrix,
    cluster_labels,
    ellipsoid,
    merge_overlapping,
)
from perception.features import FeatureVector, merge_features, merge_track_runs, repooled
from perception.footprint import robust_gaussian


def _feature(mean, var, label: str = "chair", track: int = 0, n: int = 100) -> FeatureVector:
    return FeatureVector(np.asarray(mean, float), np.diag(np.asarray(var, float)), n, label, track)


def _group(centre, label: str, count: int, seed: int, first_track: int = 0) -> list[FeatureVector]:
    rng = np.random.default_rng(seed)
    return [
        _feature(np.asarray(centre) + rng.normal(0, 0.02, 3), rng.uniform(0.004, 0.006, 3), label, first_track + q // 3)
        for q in range(count)
    ]


def test_bhattacharyya_matches_a_hand_computed_value() -> None:
    # x axis: 1/4 ln(1/4 (1/2 + 2 + 2)) + 1/4 (1^2 / 3) = 0.25 ln 1.125 + 1/12; y and z axes: identical Gaussians
    expected = 0.25 * np.log(1.125) + 1.0 / 12.0
    d = bhattacharyya(np.zeros(3), np.ones(3), np.array([1.0, 0.0, 0.0]), np.array([2.0, 1.0, 1.0]))
    assert d == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.112779, abs=1e-6)


def test_distance_matrix_is_the_pairwise_sum_plus_class_penalty() -> None:
    rng = np.random.default_rng(0)
    means, var = rng.normal(0, 1, (6, 3)), rng.uniform(0.01, 0.5, (6, 3))
    labels = ["cup", "cup", "tv", "cup", "tv", "book"]
    D = bhattacharyya_matrix(means, var, labels, penalty=100.0, var_floor=1e-6)
    for a in range(6):
        for b in range(6):
            expected = (
                0.0 if a == b else bhattacharyya(means[a], var[a], means[b], var[b]) + 100.0 * (labels[a] != labels[b])
            )
            assert D[a, b] == pytest.approx(expected, rel=1e-4, abs=1e-4)
    np.testing.assert_allclose(D, D.T, rtol=1e-5)


def test_hdbscan_separates_places_and_the_class_penalty_splits_one_place() -> None:
    chairs_here = _group((0.0, 0.0, 0.5), "chair", 12, 1)
    chairs_there = _group((3.0, 1.0, 0.5), "chair", 12, 2, first_track=10)
    cups_here = _group((0.0, 0.0, 0.5), "cup", 12, 3, first_track=20)  # same place, other class
    feats = chairs_here + chairs_there + cups_here
    for per_class in (False, True):
        labels = cluster_labels(feats, ClusterConfig(per_class=per_class))
        groups = [labels[:12], labels[12:24], labels[24:]]
        assert all(len(set(g)) == 1 and g[0] >= 0 for g in groups)
        assert len({g[0] for g in groups}) == 3


def test_ellipsoid_axes_are_principal_directions_times_scaled_std() -> None:
    yaw = 0.4
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    cov = R @ np.diag([0.16, 0.04, 0.01]) @ R.T
    obj = ellipsoid([FeatureVector(np.array([1.0, 2.0, 0.5]), cov, 50, "couch", 7)], object_id=3, axis_scale=1.5)
    lengths = np.sort(np.linalg.norm(obj.axes, axis=1))
    np.testing.assert_allclose(lengths, 1.5 * np.array([0.1, 0.2, 0.4]), rtol=1e-9)
    longest = obj.axes[np.argmax(np.linalg.norm(obj.axes, axis=1))]
    assert abs(longest @ R[:, 0]) == pytest.approx(0.6, rel=1e-9)  # along the yawed x axis
    assert obj.id == 3 and obj.label == "couch" and obj.tracks == frozenset({7})


def test_pooled_moments_of_merged_track_runs_equal_merge_features() -> None:
    feats = _group((1.0, 1.0, 1.0), "cup", 9, 4)  # tracks 0, 1, 2 with 3 vectors each
    merged = merge_track_runs(feats, run=3)
    assert len(merged) == 3
    for track in range(3):
        ref = merge_features([f for f in feats if f.track_id == track])
        got = next(f for f in merged if f.track_id == track)
        np.testing.assert_allclose(got.mean, ref.mean)
        np.testing.assert_allclose(got.cov, ref.cov, atol=1e-12)
        assert got.n == ref.n


def test_features_repooled_from_moved_sources_equal_merge_features_of_them() -> None:
    """A re-placement pools every vector again from its sources in one pass (``repooled``): the same Gaussian
    as ``merge_features`` of the sources, a single source as it is, a vector without sources left alone."""
    rng = np.random.default_rng(4)
    m = 30
    means = rng.normal(0, 3, (m, 3))
    covs = np.stack([a @ a.T * 1e-3 for a in rng.normal(size=(m, 3, 3))])
    n = rng.integers(20, 400, m)
    srcs = [tuple(int(i) for i in rng.choice(m, k, replace=False)) for k in (1, 2, 5, 9)]
    feats = [FeatureVector(np.zeros(3), np.eye(3), 1, "cup", t, s) for t, s in enumerate(srcs)]
    legacy = FeatureVector(np.ones(3), np.eye(3), 7, "cup", 9, ())
    got = repooled([*feats, legacy], means, covs, n)
    assert got[-1] is legacy
    for f, g in zip(feats, got, strict=False):
        ref = merge_features([FeatureVector(means[i], covs[i], int(n[i]), "cup", f.track_id, (i,)) for i in f.sources])
        np.testing.assert_allclose(g.mean, ref.mean, atol=1e-12)
        np.testing.assert_allclose(g.cov, ref.cov, atol=1e-12)
        assert (g.n, g.sources, g.track_id, g.label) == (ref.n, f.sources, f.track_id, "cup")
    np.testing.assert_array_equal(got[0].mean, means[srcs[0][0]])  # one source: exactly its own


def test_reclustering_follows_eq_2_15_and_the_outlier_count() -> None:
    cfg = ClusterConfig(outlier_threshold=5)
    cl = Clusterer(cfg)
    cl.add(_group((0.0, 0.0, 0.5), "chair", 12, 1))
    assert cl.step([], []) and len(cl.objects) == 1  # no objects yet: cluster (Algorithm 2 line 10)
    fits = _feature((0.0, 0.0, 0.5), (0.005, 0.005, 0.005))
    outlier = _feature((3.0, 3.0, 0.5), (0.005, 0.005, 0.005), track=50)
    cl.add([outlier])
    assert not cl.step([fits, fits, outlier], [True, True, True])  # |M n T| = 2 >= |M n O| = 1
    assert not cl.step([outlier], [False])  # not associated: not in M
    assert cl.step([outlier, outlier], [True, True])  # now |M n T| = 2 < |M n O| = 3
    assert cl.reclusterings == 2
    cl.add([outlier])
    for _ in range(4):  # eq. 2.15 never holds (many fits), but 5 outliers accumulate
        assert not cl.step([fits, fits, fits, outlier], [True] * 4)
    assert cl.step([fits, fits, fits, outlier], [True] * 4)


def test_object_ids_persist_across_reclustering() -> None:
    cl = Clusterer()
    cl.add(_group((0.0, 0.0, 0.5), "chair", 12, 1) + _group((3.0, 0.0, 0.5), "tv", 12, 2, first_track=10))
    first = {o.label: o.id for o in cl.recluster()}
    cl.add(_group((0.0, 0.0, 0.5), "chair", 6, 5, first_track=0) + _group((0.0, 3.0, 0.5), "cup", 9, 6, 30))
    second = {o.label: o.id for o in cl.recluster()}
    assert second["chair"] == first["chair"] and second["tv"] == first["tv"]
    assert second["cup"] not in first.values()


def _chair(x: float, source: int) -> FeatureVector:
    """A view of a chair at x, observation ``source`` of the store (its track: the same number)."""
    return FeatureVector(np.array([x, 0.0, 0.45]), np.diag([0.04, 0.04, 0.04]), 50, "chair", source, (source,))


def test_partial_views_merge_but_same_class_objects_seen_side_by_side_stay_apart() -> None:
    config = ClusterConfig()
    left, right = [_chair(0.0, 0), _chair(0.02, 1)], [_chair(0.65, 2), _chair(0.67, 3)]  # a row: 0.65 m apart
    a, b = merge_features(left), merge_features(right)
    assert bhattacharyya(a.mean, a.var, b.mean, b.var) <= config.merge_distance  # close enough to look like one
    assert len(merge_overlapping([left, right], config, [10, 11, 12, 13])) == 1  # never seen in one keyframe
    assert len(merge_overlapping([left, right], config, [10, 11, 11, 13])) == 2  # 1 and 2: one keyframe's
    third = [_chair(0.3, 4)]  # a view between them may join one of them, never both
    groups = merge_overlapping([left, right, third], config, [10, 11, 11, 13, 14])
    assert len(groups) == 2 and all({f.track_id for f in g} != {0, 1, 2, 3, 4} for g in groups)


def test_the_mapper_gives_the_clusterer_the_keyframe_of_every_observation() -> None:
    from perception.camera import Intrinsics
    from perception.frame import Detection
    from perception.object_map import ObjectMapper

    K, depth = Intrinsics(100.0, 100.0, 39.5, 29.5), np.full((60, 80), 2.0, np.float32)
    chairs = [Detection("chair", 0.9, (5.0, 10.0, 30.0, 50.0)), Detection("chair", 0.9, (45.0, 10.0, 70.0, 50.0))]

    def stored(m: ObjectMapper) -> list[int]:
        return [m.observation(s)[0] for s in range(m.observations)]

    mapper = ObjectMapper()
    for k in (0, 3):
        mapper.add_keyframe(k, chairs, depth, K, np.eye(4))
    assert stored(mapper) == [0, 0, 3, 3] and list(mapper.clusterer.keyframe_of) == stored(mapper)
    restored = ObjectMapper()
    restored.restore(mapper.state())
    restored.add_keyframe(6, chairs, depth, K, np.eye(4))  # the restored store keeps reaching the clusterer
    assert list(restored.clusterer.keyframe_of) == stored(restored) == [0, 0, 3, 3, 6, 6]


def test_an_object_s_centre_is_robust_to_a_few_views_of_its_neighbour() -> None:
    # 40 views of a chair at the origin (2 cm of scatter) and 10 of the chair 0.5 m beside it that a track
    # carried over: the pooled mean moves 10 cm towards the neighbour, the robust centre stays within 2 cm
    rng = np.random.default_rng(0)
    chair = rng.normal(0.0, 0.02, (40, 3))
    neighbour = np.array([0.5, 0.0, 0.0]) + rng.normal(0.0, 0.02, (10, 3))
    means = np.vstack([chair, neighbour])
    covs = np.tile(np.diag([0.12**2, 0.12**2, 0.25**2]), (len(means), 1, 1))
    weights = np.full(len(means), 100.0)
    pooled = merge_features([FeatureVector(m, c, 100, "chair") for m, c in zip(means, covs, strict=True)])
    assert pooled.mean[0] > 0.08
    centre, cov = robust_gaussian(means, covs, weights)
    assert np.linalg.norm(centre) < 0.02
    # the neighbour's views widen the object less than in the pooled moments
    assert cov[0, 0] < pooled.cov[0, 0]
    # views that all agree: the pooled centre, and the views' own extent without the 2 cm scatter of their
    # centres, which the pooled moments add to it
    same, same_cov = robust_gaussian(chair, covs[:40], weights[:40])
    agree = merge_features([FeatureVector(m, c, 100, "chair") for m, c in zip(chair, covs[:40], strict=True)])
    assert np.allclose(same, agree.mean, atol=0.005) and np.allclose(same_cov, covs[0], atol=1e-12)
    assert np.all(np.diag(agree.cov - same_cov) > 0.015**2)


def test_a_large_object_s_views_are_parts_and_are_pooled_as_they_are() -> None:
    # a 2 m table seen in parts: 30 views of its left half, 10 of its right; the median of parts would follow the
    # left half, the pooled moments keep the whole table
    left = np.tile([-0.5, 0.0, 0.7], (30, 1))
    right = np.tile([0.5, 0.0, 0.7], (10, 1))
    means = np.vstack([left, right])
    covs = np.tile(np.diag([0.45**2, 0.3**2, 0.01]), (len(means), 1, 1))
    weights = np.full(len(means), 100.0)
    centre, cov = robust_gaussian(means, covs, weights)
    pooled = merge_features([FeatureVector(m, c, 100, "dining table") for m, c in zip(means, covs, strict=True)])
    assert np.allclose(centre, pooled.mean) and np.allclose(cov, pooled.cov)


def test_same_class_objects_standing_in_one_place_are_one_but_neighbours_in_a_row_stay_two() -> None:
    from perception.coincident import coincident_groups, extent_radius

    chair = np.diag([0.15, 0.15, 0.25]) ** 2  # a chair's spread of points (m^2)
    cup = np.diag([0.03, 0.03, 0.04]) ** 2
    assert extent_radius(chair, 1.5) == pytest.approx(1.5 * 0.15)
    means = np.array([[0.0, 0, 0.45], [0.12, 0, 0.45], [0.5, 0, 0.45], [0.0, 0.0, 0.8], [0.06, 0, 0.8]])
    covs = np.array([chair, chair, chair, cup, cup])
    labels = ["chair", "chair", "chair", "cup", "cup"]
    # the first two chairs stand inside each other: one; the third, 0.5 m along a row: its own; a cup on the
    # first chair is another class; two cups 6 cm apart, each 4.5 cm across its median half-extent: two
    assert coincident_groups(labels, means, covs, 1.5) == [[0, 1], [2], [3], [4]]
    assert coincident_groups(labels, means, covs, 0.0) == [[0], [1], [2], [3], [4]]


def test_one_object_under_two_labels_is_one_but_a_cup_on_a_book_and_a_plant_in_a_vase_stay_two() -> None:
    from perception.coincident import coincident_groups

    mug = np.diag([0.027, 0.028, 0.03]) ** 2
    book = np.diag([0.1, 0.07, 0.01]) ** 2
    plant, vase = np.diag([0.12, 0.12, 0.2]) ** 2, np.diag([0.05, 0.05, 0.08]) ** 2
    means = np.array([[0.0, 0, 0.8], [0.011, 0, 0.8], [1.0, 0, 0.75], [1.0, 0.01, 0.8], [2.0, 0, 0.6], [2.0, 0, 0.35]])
    covs = np.array([mug, mug, book, mug, plant, vase])
    labels = ["cup", "bowl", "book", "cup", "potted plant", "vase"]
    # the mug seen as a cup and as a bowl, 1 cm apart and as large: one; a cup on a book (5 cm above its centre,
    # far smaller) and a plant above its vase stay two
    assert coincident_groups(labels, means, covs, 1.5) == [[0, 1], [2], [3], [4], [5]]
    # 3 cm apart (inside the reach, 4.2 cm): still one, a cup and a bowl as large cannot stand inside each other;
    # side by side, 9.6 cm apart (their width), two
    means[1, 0] = 0.03
    assert coincident_groups(labels, means, covs, 1.5) == [[0, 1], [2], [3], [4], [5]]
    means[1, 0] = 0.096
    assert coincident_groups(labels, means, covs, 1.5) == [[0], [1], [2], [3], [4], [5]]


def test_parts_of_one_table_never_seen_together_are_one_but_two_tables_seen_together_and_chairs_stay_apart() -> None:
    from perception.coincident import coincident_groups, touching

    def box(x: float, y: float) -> np.ndarray:  # a uniform extent x by y by 0.75 m
        return np.diag(np.array([x, y, 0.75]) ** 2 / 12.0)

    # the two ends of a 1.6 m table, each cluster's views showing 0.8 m of its top: centres 0.8 m apart
    means = np.array([[0.0, 0, 0.37], [0.8, 0, 0.37], [3.0, 0, 0.37], [3.85, 0, 0.37], [6.0, 0, 0.45], [6.5, 0, 0.45]])
    covs = np.array([box(0.8, 0.7), box(0.8, 0.7), box(0.8, 0.7), box(0.8, 0.7), box(0.5, 0.5), box(0.5, 0.5)])
    labels = ["dining table"] * 4 + ["chair"] * 2
    assert touching(means[0], covs[0], means[1], covs[1]) and not touching(means[2], covs[2], means[3], covs[3])
    assert touching(means[4], covs[4], means[5], covs[5])
    seen = [{1, 2, 3}, {7, 8}, {20, 21}, {22, 23}, {30, 31}, {32}]
    # without the keyframes, as before: each its own (their centres lie outside each other's reach)
    assert coincident_groups(labels, means, covs, 1.5) == [[0], [1], [2], [3], [4], [5]]
    # the table's two ends are one; two tables 5 cm apart stay two; two chairs touching are not a large class
    assert coincident_groups(labels, means, covs, 1.5, seen) == [[0, 1], [2], [3], [4], [5]]
    # two tables side by side, detected in one keyframe, are two however they touch
    seen[1] = {3, 7, 8}
    assert coincident_groups(labels, means, covs, 1.5, seen) == [[0], [1], [2], [3], [4], [5]]


def test_the_clusterer_names_an_object_seen_under_two_labels_by_its_larger_cluster() -> None:
    clusterer = Clusterer(ClusterConfig(min_cluster_size=3, min_samples=3))
    rng = np.random.default_rng(7)
    views = [
        FeatureVector(np.array([0.2, -0.2, 1.7]) + rng.normal(0, 0.003, 3), np.diag([0.028] * 3) ** 2, 40, label, k)
        for k, label in enumerate(["cup"] * 12 + ["bowl"] * 5)
    ]
    clusterer.add(views)
    objects = clusterer.recluster()
    assert [(o.label, o.n_observations) for o in objects] == [("cup", 17)]
    clusterer.config = ClusterConfig(min_cluster_size=3, min_samples=3, coincident=0.0)
    assert sorted(o.label for o in clusterer.recluster()) == ["bowl", "cup"]


def test_the_clusterer_joins_two_clusters_of_one_chair_that_share_a_keyframe() -> None:
    """Two clusters 0.1 m apart, each holding a view of one keyframe (the cannot-link kept them apart): one
    chair; a chair 0.65 m away in the same keyframes stays its own."""
    clusterer = Clusterer(ClusterConfig(min_cluster_size=3, min_samples=3))
    rng = np.random.default_rng(4)
    views = []
    for k, x in enumerate([0.0] * 8 + [0.1] * 8 + [0.75] * 8):
        mean = np.array([x, 0.0, 0.45]) + rng.normal(0, 0.005, 3)
        views.append(FeatureVector(mean, np.diag([0.02, 0.02, 0.05]), 50, "chair", k, (k,)))
    clusterer.keyframe_of = [k % 8 for k in range(24)]  # every keyframe saw all three
    clusterer.add(views)
    assert len(clusterer.recluster()) == 2
    clusterer.config = ClusterConfig(min_cluster_size=3, min_samples=3, coincident=0.0)
    assert len(clusterer.recluster()) == 3
