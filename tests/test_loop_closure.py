"""Loop-closure verification: a true revisit is accepted, a same-looking place at the wrong pose is not."""

from __future__ import annotations

import numpy as np
import pytest

from graph.geometry import relative
from graph.pose_graph import PoseGraph
from loops.acceptance import AcceptedLoop, LoopAcceptance
from loops.closer import LoopCloser
from loops.place_recognition import PlaceIndex, global_descriptor
from loops.records import KeyframeEntry, LoopRecord
from loops.settings import LoopSettings
from perception.odometry import FeatureExtractor, RelativePoseEstimator
from sources import open_dataset


@pytest.fixture(scope="module")
def room():
    return open_dataset("synthetic:room?seed=0&frames=300")


def _closer(room, i: int, j: int, claimed_offset_m: float = 0.0) -> tuple[LoopCloser, list[LoopRecord]]:
    """Keyframes i and j in a graph whose relative pose is the truth plus an offset; returns j's records."""
    gt = room.ground_truth.poses
    graph = PoseGraph()
    graph.add_first(gt[i])
    rel = relative(gt[i], gt[j])
    rel[:3, 3] += [claimed_offset_m, 0.0, 0.0]
    graph.add_keyframe(rel)
    fe = FeatureExtractor(room.camera)
    config = LoopSettings(min_gap_s=0.0, min_similarity=-1.0, proximity=False)
    closer = LoopCloser(graph, RelativePoseEstimator(room.camera), config)
    fi, fj = room.frame(i), room.frame(j)
    closer.add_keyframe(KeyframeEntry(0, fi.timestamp, i, fe.extract(fi)), fi.rgb)
    return closer, closer.add_keyframe(KeyframeEntry(1, fj.timestamp, j, fe.extract(fj)), fj.rgb)


def test_true_revisit_is_verified_and_becomes_a_factor(room):
    i, j = room.loops[len(room.loops) // 2]
    closer, records = _closer(room, i, j)
    assert len(records) == 1
    r = records[0]
    assert r.accepted and r.reason == "verified" and r.source == "appearance"
    assert (r.match_frame, r.query_frame) == (i, j) and r.inliers is not None and r.inliers >= 40
    assert r.translation_diff_m is not None and r.translation_diff_m < 0.02 and closer.graph.num_factors == 3
    assert r.to_json()["factor"] == r.factor and list(r.to_json())[-3:] == ["rotation_diff_deg", "reason", "factor"]


def test_same_place_at_a_contradicting_pose_is_rejected_as_inconsistent(room):
    i, j = room.loops[len(room.loops) // 2]
    closer, records = _closer(room, i, j, claimed_offset_m=2.0)
    assert not records[0].accepted and records[0].reason == "inconsistent_with_odometry"
    assert closer.graph.num_factors == 2  # nothing entered the graph


def test_different_places_are_rejected_by_geometry(room):
    gt = room.ground_truth.poses
    dist = np.linalg.norm(gt[:, :3, 3] - gt[0, :3, 3], axis=1)
    far = int(np.argmax(dist))
    _, records = _closer(room, 0, far)
    assert not records[0].accepted
    assert records[0].reason in ("too_few_matches", "too_few_inliers")
    assert "residual_px" not in records[0].to_json()  # a candidate PnP rejected has no residual


def test_place_index_respects_time_gap_and_ranks_by_similarity(room):
    index = PlaceIndex(capacity=2)
    for k in range(5):
        index.add(k, float(k), global_descriptor(room.frame(k * 10).rgb))
    query = global_descriptor(room.frame(0).rgb)
    best = index.query(query, timestamp=10.0, min_gap_s=0.0, top_k=2, min_similarity=-1.0)
    assert best[0].index == 0 and best[0].similarity == pytest.approx(1.0, abs=1e-5)
    assert index.query(query, timestamp=2.5, min_gap_s=2.0, top_k=5, min_similarity=-1.0)[0].index == 0
    assert all(c.index == 0 for c in index.query(query, timestamp=0.5, min_gap_s=0.0, top_k=5, min_similarity=-1.0))


def test_an_accepted_loop_that_the_graph_contradicts_is_retracted(room):
    gt = room.ground_truth.poses
    graph = PoseGraph()
    graph.add_first(gt[0])
    for a, b in ((0, 10), (10, 20)):
        graph.add_keyframe(relative(gt[a], gt[b]), 0.001, 0.05)  # confident odometry
    acceptance = LoopAcceptance(graph, LoopSettings(retract_m=0.15))
    wrong = relative(gt[0], gt[20])
    wrong[:3, 3] += [0.5, 0.0, 0.0]
    factor = graph.add_loop(0, 2, wrong, 0.05, 2.0)
    acceptance.accepted[factor] = AcceptedLoop(0, 2, wrong)
    acceptance.records.append(LoopRecord(0.0, 2.0, 0, 20, 0, 2, "appearance", True, reason="verified", factor=factor))
    factors = graph.num_factors
    assert acceptance.recheck() == [factor]
    assert acceptance.records[0].accepted is False and acceptance.records[0].reason == "retracted_inconsistent"
    assert factor not in acceptance.accepted and graph.num_factors == factors - 1
    np.testing.assert_allclose(graph.pose(2), gt[20], atol=1e-3)


def test_proximity_candidates_are_the_nearest_old_archived_keyframes_within_reach():
    """``nearby``: archived keyframes at least ``min_gap_s`` older than the new one, within ``proximity_m`` and
    ``proximity_deg`` of its estimate, nearest first, at most ``proximity_k``."""
    from scipy.spatial.transform import Rotation

    from loops.archive import ColdLog, KeyframeArchive
    from loops.candidates import nearby

    settings = LoopSettings(proximity_m=0.3, proximity_deg=25.0, proximity_k=2, min_gap_s=5.0)
    xs = [0.0, 0.1, 0.05, 0.25, 0.2, 1.0, 0.02, 0.0]  # keyframe k at x = xs[k], time k seconds
    poses = np.stack([np.eye(4)] * len(xs))
    poses[:, 0, 3] = xs
    poses[4, :3, :3] = Rotation.from_euler("z", 40, degrees=True).as_matrix()  # near but turned away
    kept = [k for k in range(len(xs)) if k != 2]  # keyframe 2 not archived
    archive = KeyframeArchive([(k, float(k), k) for k in kept], ColdLog([None] * len(kept)))
    new = KeyframeEntry(7, 7.0, 7, None)
    assert nearby(new, archive, poses, settings) == [0, 1]  # 2: not archived, 6 and 7: too recent
    far = KeyframeEntry(7, 30.0, 7, None)
    assert nearby(far, archive, poses, settings) == [0, 7]  # the nearest two (the new one is excluded by time only)
    assert nearby(far, archive, poses, settings.model_copy(update={"proximity_k": 9})) == [0, 7, 6, 1, 3]
