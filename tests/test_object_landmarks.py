"""Objects in the graph (SPEC 6.8): re-posing feature vectors, object landmarks through merges and splits,
and the pipeline keeping both in step with the optimisation."""

from __future__ import annotations

from dataclasses import replace
from itertools import pairwise

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.association import load_scene
from graph import object_landmarks
from graph.object_landmarks import LandmarkSettings, ObjectLandmarks, replayed
from graph.pose_graph import PoseGraph
from graph.row_log import RowLog
from perception.clustering import ObjectEllipsoid
from perception.features import FeatureConfig, transform_feature
from perception.object_map import ObjectMapper
from service.config import load_settings
from slam.build import build_core
from sources import open_dataset


@pytest.fixture(scope="module")
def scene():
    return load_scene(seed=2, frames=150)


def _map(scene, poses) -> ObjectMapper:
    mapper = ObjectMapper()
    for j in range(0, len(poses), 2):
        mapper.add_keyframe(j, scene.dets[j], scene.depth_m(j), scene.K, poses[j])
    return mapper


def _rigid(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_repose_equals_mapping_again_with_the_new_poses(scene):
    """A rigid change of every pose keeps the relative poses, so NPDA and tracks are the same: re-posing must
    give exactly the feature vectors and objects of mapping the sequence again with the moved poses."""
    G = _rigid([0.1, -0.3, 0.7], [1.0, -2.0, 0.3])
    mapper = _map(scene, scene.poses)
    assert len(mapper.clusterer.features) > 50 and mapper.objects
    objects = mapper.repose({j: G @ T for j, T in enumerate(scene.poses)})
    again = _map(scene, G @ scene.poses)
    again.clusterer.recluster()
    got, want = mapper.clusterer.features, again.clusterer.features
    assert len(got) == len(want)
    for f, g in zip(got, want, strict=True):
        assert f.sources == g.sources and f.track_id == g.track_id
        np.testing.assert_allclose(f.mean, g.mean, atol=1e-9)
        np.testing.assert_allclose(f.cov, g.cov, atol=1e-9)
    assert [(o.label, o.tracks) for o in objects] == [(o.label, o.tracks) for o in again.objects]
    for o, p in zip(objects, again.objects, strict=True):
        np.testing.assert_allclose(o.mean, p.mean, atol=1e-9)


def test_repose_follows_a_pose_correction_of_part_of_the_sequence(scene):
    """Only the second half's poses move (as after a loop closure): those observations move with them."""
    mapper = _map(scene, scene.poses)
    shift = _rigid([0.0, 0.0, 0.05], [0.2, 0.0, 0.0])
    moved = {j: (shift @ T if j >= 75 else T) for j, T in enumerate(scene.poses)}
    mapper.repose(moved)
    for f in mapper.clusterer.features:
        parts = [transform_feature(local, moved[k]) for k, local in map(mapper.observation, f.sources)]
        np.testing.assert_allclose(
            f.mean, np.average([p.mean for p in parts], axis=0, weights=[p.n for p in parts]), atol=1e-9
        )


def _chain(n: int) -> tuple[PoseGraph, list[np.ndarray]]:
    g = PoseGraph()
    poses = [_rigid([0.0, 0.02 * k, 0.0], [0.1 * k, 0.0, 0.0]) for k in range(n)]
    g.add_first(poses[0])
    for a, b in pairwise(poses):
        g.add_keyframe(np.linalg.inv(a) @ b)
    return g, poses


def _seen(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    Ti = np.linalg.inv(T)
    return Ti[:3, :3] @ p + Ti[:3, 3]


def _obj(oid: int, tracks: set[int], n: int = 6) -> ObjectEllipsoid:
    return ObjectEllipsoid(oid, "chair", np.zeros(3), np.eye(3), np.eye(3), n, frozenset(tracks))


def test_landmarks_follow_splits_merges_and_dropped_objects():
    g, poses = _chain(8)
    a, b = np.array([0.5, 0.2, 2.0]), np.array([-0.4, 0.1, 2.5])
    lm = ObjectLandmarks(g, LandmarkSettings(landmark_sigma_m=0.01, landmark_huber_k=None, landmark_min_support=5))
    for k in range(4):  # tracks 1 and 2 see point a, track 3 sees point b
        lm.observe(k, [(1, _seen(poses[k], a), 0.0), (2, _seen(poses[k], a), 0.0), (3, _seen(poses[k], b), 0.0)])
    assert g.num_landmarks == 0 and not lm.assigned  # no stable object yet: measurements only kept
    assert lm.sync([_obj(1, {1, 2}), _obj(2, {3}, n=4)]) == (8, 0)  # object 2 is below the support threshold
    assert g.landmarks_in_solver() == {1}
    np.testing.assert_allclose(g.landmark(1), a, atol=1e-6)
    lm.observe(4, [(1, _seen(poses[4], a), 0.0), (3, _seen(poses[4], b), 0.0)])  # mapped track: in at once
    assert len(lm.assigned) == 9
    factors = g.num_factors
    assert lm.sync([_obj(1, {1}), _obj(5, {2}), _obj(2, {3})]) == (4 + 5, 4)  # split: track 2 moves to object 5
    assert g.landmarks_in_solver() == {1, 2, 5} and g.num_factors == factors - 4 + 4 + 5
    for j, p in ((1, a), (5, a), (2, b)):
        np.testing.assert_allclose(g.landmark(j), p, atol=1e-6)
    live = {i for _, i in lm.assigned.values()}
    assert None not in live and not live & g.books.removed
    assert all(g.factors[i].b == j for j, i in lm.assigned.values())
    lm.sync([_obj(1, {1, 2, 3})])  # everything merged into one object (an over-merge); then it is dropped
    assert g.landmarks_in_solver() == {1} and len(lm.assigned) == 14
    lm.sync([])
    assert g.num_landmarks == 0 and not lm.assigned
    np.testing.assert_allclose(g.poses(), np.stack(poses), atol=1e-6)


def test_a_measurement_still_waiting_is_withdrawn_when_its_track_moves():
    g, poses = _chain(4)
    p = np.array([0.0, 0.0, 2.0])
    lm = ObjectLandmarks(g, LandmarkSettings(landmark_min_support=1))
    lm.observe(0, [(7, _seen(poses[0], p), 0.05)])
    lm.sync([_obj(3, {7})])
    assert lm.assigned == {(0, 7): (3, None)} and g.num_landmarks == 0  # one keyframe: not observable yet
    lm.sync([_obj(4, {7})])
    assert g.books.pending[3] == [] and lm.assigned == {(0, 7): (4, None)} and len(g.books.pending[4]) == 1
    lm.observe(2, [(7, _seen(poses[2], p), 0.05)])
    assert g.landmarks_in_solver() == {4} and all(i is not None for _, i in lm.assigned.values())
    # sigma: at least the configured floor, at least the points' extent
    assert [g.factors[i].sigma_m for _, i in sorted(lm.assigned.values())] == [0.1, 0.1]


def test_the_pipeline_puts_objects_in_the_graph_and_re_clusters_after_loop_closures():
    ds = open_dataset("synthetic:room?seed=0&frames=300")
    p = build_core(load_settings(None, {"loops": {"source": "appearance"}}))
    for i in range(len(ds)):
        p.step(ds.frame(i))
    assert p.loops.n_accepted > 0 and p.reposes > 0
    objects = p.object_list()
    with_landmark = [o for o in objects if o["landmark"] is not None]
    assert len(with_landmark) >= 8 and p.graph.num_landmarks == len(with_landmark)
    for o in with_landmark:  # the landmark (uncut views' centroids) lies within 2 std of its object's centre
        d = np.subtract(o["landmark"], o["mean"])
        assert d @ np.linalg.solve(np.asarray(o["cov"]) + 1e-4 * np.eye(3), d) <= 4.0, o
    # the feature vectors were last placed with poses within the re-pose thresholds of the current estimate
    # (translation, plus the rotation threshold's sweep at the far side of the 6 m room)
    bound = p.settings.objects.repose_m + 6.0 * np.radians(p.settings.objects.repose_deg)
    poses = p.graph.poses()
    mapper = p.objects
    worst = max(
        np.linalg.norm(
            f.mean
            - np.average(
                [transform_feature(local, poses[k]).mean for k, local in map(mapper.observation, f.sources)],
                axis=0,
                weights=[mapper.observation(i)[1].n for i in f.sources],
            )
        )
        for f in mapper.clusterer.features
    )
    assert worst <= bound
    # every landmark measurement the bookkeeping holds is a live factor of the landmark it names
    assert all(
        i is not None and i not in p.graph.books.removed and p.graph.factors[i].b == j
        for j, i in p.landmarks.assigned.values()
        if j in p.graph.landmarks_in_solver()
    )


def test_a_view_cut_by_the_image_border_weighs_less_in_the_pooled_object(scene):
    """The same box seen whole and cut by the border: the cut view's points count ``cut_weight`` as much, so
    the object's pooled Gaussian leans on the whole view; only whole views measure landmarks."""
    j = next(
        i
        for i, dets in enumerate(scene.dets)
        if any(d.box[0] > 10 and d.box[2] < scene.depth_m(i).shape[1] - 10 for d in dets)
    )
    whole = next(d for d in scene.dets[j] if d.box[0] > 10 and d.box[2] < scene.depth_m(j).shape[1] - 10)
    cut = replace(whole, box=(0.0, *whole.box[1:]))
    counts = {}
    for weight in (1.0, 0.25):
        mapper = ObjectMapper(features=FeatureConfig(cut_weight=weight))
        mapper.add_keyframe(0, [whole, cut], scene.depth_m(j), scene.K, scene.poses[j])
        counts[weight] = [mapper.observation(i)[1].n for i in range(mapper.observations)]
        assert len(mapper.last_observations) == 1  # the whole view only
    assert counts[1.0][0] == counts[0.25][0]
    assert counts[0.25][1] == round(0.25 * counts[1.0][1])


def test_the_journal_of_assignments_replays_to_them_and_stays_bounded(monkeypatch):
    monkeypatch.setattr(object_landmarks, "COMPACT_SLACK", 8)
    g, poses = _chain(12)
    a, b = np.array([0.5, 0.2, 2.0]), np.array([-0.4, 0.1, 2.5])
    lm = ObjectLandmarks(g, LandmarkSettings(landmark_sigma_m=0.01, landmark_huber_k=None, landmark_min_support=1))
    splits = [[_obj(1, {1, 2}), _obj(2, {3})], [_obj(1, {1}), _obj(5, {2}), _obj(2, {3})], [_obj(1, {1, 2, 3})]]
    compacted = 0
    for k in range(12):  # tracks move between objects after every keyframe; waiting ones resolve on the way
        lm.observe(k, [(1, _seen(poses[k], a), 0.0), (2, _seen(poses[k], a), 0.0), (3, _seen(poses[k], b), 0.0)])
        journal = lm.journal
        lm.sync(splits[k % 3])
        compacted += lm.journal is not journal
        assert replayed(lm.journal.rows()) == lm.assigned
        assert len(lm.journal) <= 2 * len(lm.assigned) + 8 + 3 * 3  # compacted after each change at most
    assert compacted > 0 and len(lm.assigned) == 36
    restored = ObjectLandmarks(g, lm.config)
    restored.restore(lm.state())
    assert restored.assigned == lm.assigned
    saved = np.array([(k, t, j, -1 if i is None else i) for (k, t), (j, i) in lm.assigned.items()])
    old = {**lm.state(), "journal": None, "assigned": saved}  # a state saved before the journal
    restored.restore(old)
    assert restored.assigned == lm.assigned and replayed(restored.journal.rows()) == lm.assigned


def test_a_row_log_keeps_its_rows_as_it_grows_and_hands_out_read_only_views():
    log = RowLog((4,), np.int64)
    for n in range(40):
        log.append((n, -n, 2 * n, 7))
    rows = log.rows()
    assert rows.shape == (40, 4) and rows[:, 0].tolist() == list(range(40)) and rows[39].tolist() == [39, -39, 78, 7]
    with pytest.raises(ValueError):
        rows[0, 0] = 1
    again = RowLog((4,), np.int64, rows)
    assert np.array_equal(again.rows(), rows) and len(again) == 40


def test_retired_tracks_keep_their_measurements_in_the_graph_and_leave_the_assignments():
    """A re-clustering that retired tracks 2 and 3 into object 1's anchor track 1 no longer names them: their
    measurements stay on landmark 1 (not retracted as a track that left its object would be) and are no
    longer followed, so the assignments kept do not grow with the tracks a long run makes."""
    g, poses = _chain(6)
    a = np.array([0.5, 0.2, 2.0])
    lm = ObjectLandmarks(g, LandmarkSettings(landmark_sigma_m=0.01, landmark_huber_k=None, landmark_min_support=1))
    for k in range(6):
        lm.observe(k, [(1 + k // 2, _seen(poses[k], a), 0.0)])  # tracks 1, 2, 3: two keyframes each
    assert lm.sync([_obj(1, {1, 2, 3})]) == (6, 0)
    factors, removed = g.num_factors, set(g.books.removed)
    assert lm.sync([_obj(1, {1})], retired=[2, 3]) == (0, 0)
    assert set(lm.assigned) == {(0, 1), (1, 1)} and set(g.books.removed) == removed and g.num_factors == factors
    assert replayed(lm.journal.rows()) == lm.assigned
    lm.sync([_obj(1, {1})])  # later re-clusterings leave them alone
    assert set(g.books.removed) == removed
    np.testing.assert_allclose(g.landmark(1), a, atol=1e-6)
