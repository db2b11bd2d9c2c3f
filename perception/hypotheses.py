"""Candidate motions of a frame relative to its keyframe, and how each was found (the tracking methods)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

Method = Literal["odometry", "tracked", "features", "wide", "guided", "icp", "dense", "relocalized", "lost"]
"""How a step was found: the frames' own odometry (external odometry); else by visual odometry: the keyframe's
points followed by optical flow (between keyframes, ``perception.keyframe_tracker``), ORB features (keyframes,
and frames the flow failed on), wide-baseline features (more of them), guided matching around a motion
prior's projections, depth ICP, dense photometric alignment from the prior, relocalization against the
keyframe database, or not at all (lost: a new map segment, or no pose)."""


@dataclass(frozen=True)
class Hypothesis:
    """A candidate ``T_kf_frame`` (body frame), the method that found it and its factor sigmas."""

    method: Method
    T: np.ndarray
    sigma_m: float
    sigma_deg: float
    inliers: int = 0


def scaled_motion(T: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion ``T`` scaled along its geodesic by ``factor`` (rotation vector and translation scaled
    alike: close enough for a motion prior)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(T[:3, :3]).as_rotvec() * factor).as_matrix()
    out[:3, 3] = T[:3, 3] * factor
    return out
