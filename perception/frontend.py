"""Odometry front ends: external odometry from the frames, or RGB-D visual odometry (SPEC 6.4).

Both decide keyframes and give, for each keyframe, the relative pose from the previous keyframe with
its noise: the odometry between-factor of the graph.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from graph.geometry import motion_magnitude, relative
from perception.frame import CameraModel, Frame
from perception.icp import icp_refine
from perception.odometry import FeatureExtractor, Features, OdometrySettings, Rejected, RelativePoseEstimator

log = logging.getLogger(__name__)


class KeyframeSettings(BaseModel):
    """A frame becomes a keyframe when it moved enough since the last one, too many frames passed, or (visual
    odometry) too few inliers track it; and external odometry that jumps is rejected (``implausible``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    translation_m: float = Field(default=0.05, gt=0)
    rotation_deg: float = Field(default=5.0, gt=0)
    max_interval: int = Field(default=10, ge=1, description="frames between keyframes at most")
    min_inliers: int = Field(default=120, ge=0, description="visual odometry: new keyframe when tracking weakens")
    skip_edges: int = Field(
        default=2,
        ge=1,
        description="visual odometry: factors from a new keyframe to this many earlier "
        "keyframes (1 = the previous one only)",
    )
    max_jump_m: float = Field(
        default=1.0,
        ge=0,
        description="external odometry: a frame whose pose lies farther than this + max_speed_mps x the time "
        "since the previous frame from the previous frame's is rejected (odometry_jump)",
    )
    max_speed_mps: float = Field(default=10.0, ge=0, description="external odometry: see max_jump_m")

    def implausible(self, previous: np.ndarray, pose: np.ndarray, dt: float) -> bool:
        """External odometry that moved farther than ``max_jump_m`` + ``max_speed_mps`` * dt from the previous
        frame's: a glitch, not motion (it would drag the whole graph, and a kilometre jump makes iSAM2 fail)."""
        jump = float(np.linalg.norm(pose[:3, 3] - previous[:3, 3]))
        return jump > self.max_jump_m + self.max_speed_mps * max(dt, 0.0)


@dataclass
class Step:
    """What the front end made of one frame."""

    pose: np.ndarray
    keyframe: bool
    factor: np.ndarray | None = None
    sigma_m: float | None = None
    sigma_deg: float | None = None
    lost: bool = False
    inliers: int = 0
    features: Features | None = None
    extra: list[tuple[int, np.ndarray, float, float]] = field(default_factory=list)


class ExternalOdometry:
    """Odometry poses carried by the frames; the factor is the odometry increment between keyframes."""

    def __init__(self, policy: KeyframeSettings):
        self.policy = policy
        self._kf_pose: np.ndarray | None = None
        self._since = 0

    def track(self, frame: Frame) -> Step:
        pose = frame.odometry
        if pose is None:
            raise ValueError("external odometry needs frames that carry odometry")
        if self._kf_pose is None:
            self._kf_pose, self._since = pose, 0
            return Step(pose, True)
        rel = relative(self._kf_pose, pose)
        trans, rot = motion_magnitude(rel)
        self._since += 1
        p = self.policy
        if trans >= p.translation_m or rot >= math.radians(p.rotation_deg) or self._since >= p.max_interval:
            self._kf_pose, self._since = pose, 0
            return Step(pose, True, rel)
        return Step(pose, False)

    def state(self) -> dict:
        """Plain tracking state (the last keyframe's pose, frames since it)."""
        return {"kf_pose": self._kf_pose, "since": self._since}

    def restore(self, state: dict) -> None:
        self._kf_pose, self._since = state["kf_pose"], state["since"]


class VisualOdometry:
    """Frame-to-keyframe RGB-D odometry: ORB + depth on the keyframe, PnP-RANSAC against the new frame.

    Tracking loss (too few matches or inliers, no texture, no depth) keeps the last pose, makes the frame
    a keyframe with a weak factor (``OdometrySettings.lost_sigma_scale``) and re-initialises on it; it never
    raises. ``policy`` decides keyframes; ``config`` extracts and matches features and refines by ICP.
    """

    def __init__(self, camera: CameraModel, policy: KeyframeSettings, config: OdometrySettings | None = None):
        config = config if config is not None else OdometrySettings()
        self.policy, self.config = policy, config
        self.camera = camera
        self.extractor = FeatureExtractor(camera, config)
        self.estimator = RelativePoseEstimator(camera, config)
        self._kf_pose: np.ndarray | None = None
        self._kf_features: Features | None = None
        self._kf_depth: np.ndarray | None = None
        self._history: list[tuple[Features, np.ndarray]] = []  # older keyframes, newest last
        self.icp_used = 0
        self._last_pose = np.eye(4)
        self._since = 0
        self.lost_count = 0

    _STATE = ("_kf_pose", "_kf_features", "_kf_depth", "_history", "icp_used", "_last_pose", "_since", "lost_count")

    def state(self) -> dict:
        """Plain tracking state: the keyframe's pose, features and depth, older keyframes, counters.

        The ORB extractor and matcher (cv2 objects) are not state: they are rebuilt from the camera; nor are
        the settings, which come from the configuration (a snapshot holds plain data only).
        """
        return {name.lstrip("_"): getattr(self, name) for name in self._STATE}

    def restore(self, state: dict) -> None:
        for name in self._STATE:
            setattr(self, name, state[name.lstrip("_")])

    def track(self, frame: Frame) -> Step:
        features = self.extractor.extract(frame)
        depth = frame.depth_m()
        kf_pose, kf_features, kf_depth = self._kf_pose, self._kf_features, self._kf_depth
        if kf_pose is None or kf_features is None or kf_depth is None:  # the first frame (all three or none)
            return self._new_keyframe(np.eye(4), features, depth, Step(np.eye(4), True, features=features))
        self._since += 1
        try:
            rel = self.estimator.estimate(kf_features, features)
        except Rejected as exc:
            return self._lost(frame, kf_pose, features, depth, exc)
        pose = kf_pose @ rel.T_a_b
        self._last_pose = pose
        trans, rot = motion_magnitude(rel.T_a_b)
        p = self.policy
        if (
            trans >= p.translation_m
            or rot >= math.radians(p.rotation_deg)
            or self._since >= p.max_interval
            or rel.inliers < p.min_inliers
        ):
            T = self._refine(rel.T_a_b, depth, kf_depth)
            pose = kf_pose @ T
            step = Step(
                pose,
                True,
                T,
                rel.sigma_m,
                rel.sigma_deg,
                inliers=rel.inliers,
                features=features,
                extra=self._skip_edges(features, depth),
            )
            return self._new_keyframe(pose, features, depth, step)
        return Step(pose, False, inliers=rel.inliers, features=features)

    def _skip_edges(self, features: Features, depth: np.ndarray) -> list[tuple[int, np.ndarray, float, float]]:
        """Extra factors to the keyframes before the previous one: (how many back, T_old_new, sigmas)."""
        edges = []
        for back, (old_features, old_depth) in enumerate(reversed(self._history), start=2):
            try:
                rel = self.estimator.estimate(old_features, features)
            except Rejected:
                continue
            edges.append((back, self._refine(rel.T_a_b, depth, old_depth), rel.sigma_m, rel.sigma_deg))
        return edges

    def _refine(self, T_pnp: np.ndarray, depth: np.ndarray, ref_depth: np.ndarray) -> np.ndarray:
        """Depth ICP from the PnP estimate, kept only when it corrects by a plausible amount."""
        if not self.config.icp:
            return T_pnp
        result = icp_refine(depth, ref_depth, self.camera.depth, T_pnp)
        if result is None:
            return T_pnp
        dt, dr = motion_magnitude(relative(T_pnp, result.T))
        if dt > self.config.icp_max_correction_m or math.degrees(dr) > self.config.icp_max_correction_deg:
            return T_pnp
        self.icp_used += 1
        return result.T

    def _lost(self, frame: Frame, kf_pose: np.ndarray, features: Features, depth: np.ndarray, exc: Rejected) -> Step:
        self.lost_count += 1
        log.warning("tracking lost at t=%.3f (%s); re-initialising with a weak factor", frame.timestamp, exc)
        pose = self._last_pose
        scale = self.config.lost_sigma_scale
        step = Step(pose, True, relative(kf_pose, pose), 0.05 * scale, 2.0 * scale, lost=True, features=features)
        return self._new_keyframe(pose, features, depth, step)

    def _new_keyframe(self, pose: np.ndarray, features: Features, depth: np.ndarray, step: Step) -> Step:
        if step.lost:
            self._history = []
        elif self._kf_features is not None and self._kf_depth is not None:  # not the first keyframe
            self._history = (
                [*self._history, (self._kf_features, self._kf_depth)][-(self.policy.skip_edges - 1) :]
                if self.policy.skip_edges > 1
                else []
            )
        self._kf_pose, self._kf_features, self._kf_depth = pose, features, depth
        self._since, self._last_pose = 0, pose
        return step
