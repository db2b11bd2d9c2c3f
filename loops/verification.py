"""Geometric verification of a loop candidate: PnP-RANSAC between the two keyframes and the viewpoint check.

No graph is involved, so verification can run beside the tracking (SPEC 6.9: a false loop closure is worse
than a missed one; the graph's gate in ``loops.acceptance`` decides afterwards).
"""

from __future__ import annotations

import math

from graph.geometry import motion_magnitude, pose_to_tum
from loops.records import Candidate, KeyframeEntry, LoopRecord, Source, Verified
from loops.settings import LoopSettings
from perception.odometry import OdometrySettings, Rejected, RelativePoseEstimator


def new_record(match: KeyframeEntry, query: KeyframeEntry, candidate: Candidate) -> LoopRecord:
    """The record of a candidate before verification."""
    policy = candidate.source is Source.POLICY
    score = candidate.score
    return LoopRecord(
        query_t=query.timestamp,
        match_t=match.timestamp,
        query_frame=query.frame,
        match_frame=match.frame,
        query_keyframe=query.index,
        match_keyframe=match.index,
        source=candidate.source.value,
        similarity=None if math.isnan(score) or policy else round(score, 4),
        policy_probability=round(score, 4) if policy else None,
    )


def verify(
    match: KeyframeEntry,
    query: KeyframeEntry,
    candidate: Candidate,
    estimator: RelativePoseEstimator,
    config: OdometrySettings,
    settings: LoopSettings,
) -> Verified:
    """PnP-RANSAC between the two keyframes (with the loop thresholds in ``config``) and the viewpoint check."""
    record = new_record(match, query, candidate)
    if match.features is None or query.features is None:
        raise ValueError("loop verification needs the features of both keyframes")
    try:
        rel = estimator.estimate(match.features, query.features, config)
    except Rejected as exc:
        record.reason, record.matches, record.inliers = exc.reason, exc.matches, exc.inliers
        return Verified(record)
    record.matches, record.inliers, record.residual_px = rel.matches, rel.inliers, round(rel.residual_px, 3)
    dist, angle = motion_magnitude(rel.T_a_b)
    record.relative_pose = [round(float(v), 6) for v in pose_to_tum(rel.T_a_b)]
    record.distance_m, record.angle_deg = round(dist, 4), round(math.degrees(angle), 3)
    if dist > settings.max_loop_m or math.degrees(angle) > settings.max_loop_deg:
        record.reason = "viewpoints_too_far_apart"
        return Verified(record)
    return Verified(record, rel)
