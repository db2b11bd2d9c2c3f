"""The per-frame pipeline: temporal checks, keyframe selection and the pose graph. No zenoh, no disk."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from graph.geometry import motion_magnitude, relative
from graph.pose_graph import NoiseSettings, PoseGraph
from perception.frame import Frame
from service.config import Settings
from service.protocol import FrameRejected, Reason
from service.sources.base import Trajectory

log = logging.getLogger(__name__)


@dataclass
class FrameRecord:
    """Where a processed frame sits in the graph: its keyframe and the odometry pose relative to it."""

    timestamp: float
    seq: int
    keyframe: int
    is_keyframe: bool
    odometry: np.ndarray
    from_keyframe: np.ndarray


class Pipeline:
    """Turns validated frames into keyframes and factors (SPEC 6.8).

    Steps per frame: (1) reject stale or duplicate timestamps, unusable depth and missing odometry;
    (2) decide whether the frame is a keyframe; (3) add its odometry factor to iSAM2;
    (4) record the frame relative to its keyframe so the full trajectory follows the optimised graph.
    """

    def __init__(self, settings: Settings):
        self.settings = settings
        g = settings.graph
        self.graph = PoseGraph(NoiseSettings(g.odometry_sigma_m, g.odometry_sigma_deg, g.prior_sigma_m,
                                             g.prior_sigma_deg, g.relinearize_threshold, g.relinearize_skip))
        self.records: list[FrameRecord] = []
        self._kf_odometry: list[np.ndarray] = []
        self._since_keyframe = 0

    @property
    def last_timestamp(self) -> float:
        return self.records[-1].timestamp if self.records else -math.inf

    def process(self, frame: Frame) -> FrameRecord:
        """Add one frame; raises FrameRejected (counted by the caller) when it cannot be used."""
        self._check(frame)
        odom = frame.odometry
        if not self.records:
            record = self._add_keyframe(frame, odom, first=True)
        elif self._is_keyframe(odom):
            record = self._add_keyframe(frame, odom, first=False)
        else:
            kf = len(self._kf_odometry) - 1
            record = FrameRecord(frame.timestamp, frame.seq, kf, False, odom, relative(self._kf_odometry[kf], odom))
            self._since_keyframe += 1
        self.records.append(record)
        return record

    def _check(self, frame: Frame) -> None:
        if frame.timestamp == self.last_timestamp:
            raise FrameRejected(Reason.DUPLICATE_TIMESTAMP, f"timestamp {frame.timestamp} already processed")
        if frame.timestamp < self.last_timestamp:
            raise FrameRejected(Reason.OUT_OF_ORDER, f"timestamp {frame.timestamp} < {self.last_timestamp}")
        if not np.any(frame.depth):
            raise FrameRejected(Reason.EMPTY_DEPTH, "depth image has no valid pixel")
        if frame.odometry is None:
            raise FrameRejected(Reason.NO_ODOMETRY,
                                "frame carries no odometry and the RGB-D odometry front end is not available")

    def _is_keyframe(self, odom: np.ndarray) -> bool:
        k = self.settings.keyframes
        trans, rot = motion_magnitude(relative(self._kf_odometry[-1], odom))
        return (trans >= k.translation_m or rot >= math.radians(k.rotation_deg)
                or self._since_keyframe + 1 >= k.max_interval)

    def _add_keyframe(self, frame: Frame, odom: np.ndarray, first: bool) -> FrameRecord:
        if first:
            kf = self.graph.add_first(odom)
        else:
            kf = self.graph.add_keyframe(relative(self._kf_odometry[-1], odom))
        self._kf_odometry.append(odom)
        self._since_keyframe = 0
        return FrameRecord(frame.timestamp, frame.seq, kf, True, odom, np.eye(4))

    def trajectory(self) -> Trajectory:
        """Optimised poses of every processed frame (keyframe estimate composed with its offset)."""
        kf_poses = self.graph.poses()
        if not self.records:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        poses = np.stack([kf_poses[r.keyframe] @ r.from_keyframe for r in self.records])
        return Trajectory(np.array([r.timestamp for r in self.records]), poses)

    def odometry_trajectory(self) -> Trajectory:
        """The front-end (odometry) poses of every processed frame."""
        if not self.records:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([r.timestamp for r in self.records]), np.stack([r.odometry for r in self.records]))
