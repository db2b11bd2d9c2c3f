"""Relocalization: placing a keyframe that tracking lost, and joining map segments (``slam.segments``).

A lost keyframe is matched against the keyframe database (``LoopCloser.relocalize``: appearance candidates
verified by PnP). A match is a measured factor from the stored keyframe; without one the keyframe starts a
new segment held by a gauge prior. Each later keyframe of a segment not tied to the map tries again against
the other segments' keyframes, and a match joins them (the joined segment's gauge prior is then removed).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from graph.interface import Graph
from loops.closer import LoopCloser
from perception.frame import Frame
from perception.keyframing import Step
from perception.odometry import OdometrySettings, Relative
from slam.segments import Segments

log = logging.getLogger(__name__)

GAUGE_SIGMA_M, GAUGE_SIGMA_DEG = 0.05, 2.0
"""A new segment's gauge prior: these x ``OdometrySettings.lost_sigma_scale`` (5 m and 200 degrees)."""


def relocalize(
    loops: LoopCloser | None, frame: Frame, step: Step, allowed: Callable[[int], bool]
) -> tuple[int, Relative] | None:
    """A stored keyframe (``allowed`` ones) that verifies against the frame, and ``T_keyframe_frame``."""
    if loops is None or step.features is None:
        return None
    return loops.relocalize(step.features, frame.rgb, allowed)


def place_lost(
    graph: Graph,
    segments: Segments,
    loops: LoopCloser | None,
    frame: Frame,
    step: Step,
    kf_odometry: list,
    odometry: OdometrySettings | None = None,
) -> int:
    """Add a keyframe the front end could not pose: relocalized (a measured factor from the matching keyframe;
    ``step`` then holds its pose and the method ``relocalized``), else the first keyframe of a new segment."""
    found = relocalize(loops, frame, step, lambda m: True)
    if found is not None:
        m, rel = found
        kf = graph.add_keyframe_from(m, rel.T_a_b, rel.sigma_m, rel.sigma_deg)
        segments.add_keyframe(kf)
        segments.relocalizations, segments.last_match = segments.relocalizations + 1, m
        step.pose, step.lost, step.method = kf_odometry[m] @ rel.T_a_b, False, "relocalized"
        log.info("relocalized at t=%.3f against keyframe %d (%d inliers)", frame.timestamp, m, rel.inliers)
        return kf
    scale = (odometry or OdometrySettings()).lost_sigma_scale
    kf, gauge = graph.add_segment(step.pose, GAUGE_SIGMA_M * scale, GAUGE_SIGMA_DEG * scale)
    segments.add_keyframe(kf, new_segment=True, gauge_factor=gauge)
    log.warning("t=%.3f: keyframe %d starts map segment %d", frame.timestamp, kf, segments.count - 1)
    return kf


def try_join(graph: Graph, segments: Segments, loops: LoopCloser | None, kf: int, frame: Frame, step: Step) -> None:
    """Keyframe ``kf`` of a segment not tied to the map, relocalized against the other segments' keyframes:
    a match is a measured factor that joins the segments."""
    found = relocalize(loops, frame, step, lambda m: not segments.joined(m, kf))
    if found is None:
        return
    m, rel = found
    graph.add_between(m, kf, rel.T_a_b, rel.sigma_m, rel.sigma_deg)
    segments.relocalizations += 1
    join(graph, segments, m, kf)


def join(graph: Graph, segments: Segments, a: int, b: int) -> None:
    """Join keyframes ``a`` (the older, stored one) and ``b``'s segments (a measured factor links them: a
    relocalization or a loop closure) and drop the gauge prior."""
    gauges = segments.join(a, b)
    segments.last_match = a
    if gauges:
        graph.remove_factors(gauges)
    log.info("map segments of keyframes %d and %d joined", a, b)
