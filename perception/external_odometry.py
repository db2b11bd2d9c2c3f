"""External odometry: the poses the frames carry (a robot's wheel or VIO odometry), keyframed by motion."""

from __future__ import annotations

import math

import numpy as np

from graph.geometry import motion_magnitude, relative
from perception.frame import Frame
from perception.keyframing import KeyframeSettings, Step


class ExternalOdometry:
    """Odometry poses carried by the frames; the factor is the odometry increment between keyframes."""

    def __init__(self, policy: KeyframeSettings):
        self.policy = policy
        self._kf_pose: np.ndarray | None = None
        self._since = 0

    def track(self, frame: Frame) -> Step:
        if frame.odometry is None:
            raise ValueError("external odometry needs frames that carry odometry")
        return self.track_pose(frame.odometry)

    def track_pose(self, pose: np.ndarray) -> Step:
        """The step of a frame whose odometry pose is ``pose``."""
        if self._kf_pose is None:
            self._kf_pose, self._since = pose, 0
            return Step(pose, True, method="odometry")
        rel = relative(self._kf_pose, pose)
        trans, rot = motion_magnitude(rel)
        self._since += 1
        p = self.policy
        if trans >= p.translation_m or rot >= math.radians(p.rotation_deg) or self._since >= p.max_interval:
            self._kf_pose, self._since = pose, 0
            return Step(pose, True, rel, method="odometry")
        return Step(pose, False, method="odometry")

    def continue_from(self, kf_pose: np.ndarray | None, since: int) -> None:
        """The last keyframe (made by another front end) is at ``kf_pose``, ``since`` frames ago."""
        self._kf_pose, self._since = kf_pose, since

    def state(self) -> dict:
        """Plain tracking state (the last keyframe's pose, frames since it)."""
        return {"kf_pose": self._kf_pose, "since": self._since}

    def restore(self, state: dict) -> None:
        self._kf_pose, self._since = state["kf_pose"], state["since"]
