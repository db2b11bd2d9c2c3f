"""The fallback chain of visual odometry: candidate poses of a frame when its features fail (or disagree with
the depth), each from a constant-velocity prior: wide-baseline features, guided matching around the prior's
projections, dense photometric alignment (optional), and depth ICP from each of them, from the prior and from
the keyframe. ``VisualOdometry`` judges them by depth agreement."""

from __future__ import annotations

import math

import numpy as np

from graph.geometry import inverse, motion_magnitude, relative
from perception.camera import Intrinsics
from perception.dense import align
from perception.frame import CameraModel, Frame
from perception.hypotheses import Hypothesis
from perception.icp import degenerate_directions, icp_ambiguity, icp_pyramid
from perception.odometry import (
    FeatureExtractor,
    Features,
    OdometrySettings,
    Rejected,
    RelativePoseEstimator,
    gray_image,
)
from perception.registration import depth_in_color

KeyframeView = tuple[Features, np.ndarray | None, np.ndarray]
"""What the chain reads of the keyframe: its features, grey image (None: not kept) and metric depth."""


def icp_hypothesis(
    K: Intrinsics,
    cfg: OdometrySettings,
    T: np.ndarray,
    depth: np.ndarray,
    ref_depth: np.ndarray,
) -> Hypothesis | None:
    """A pose from depth alone: coarse-to-fine point-to-plane ICP from ``T``; None when it fails, leaves a
    motion direction unconstrained (a plain wall, a corridor), ends far from its start (``icp_max_travel_*``)
    or depends on where ICP starts (``icp_max_ambiguity_m``)."""
    result = icp_pyramid(depth, ref_depth, K, T)
    if result is None:
        return None
    if degenerate_directions(result.information) > 0:
        return None
    travel_m, travel_rad = motion_magnitude(relative(T, result.T))
    if travel_m > cfg.icp_max_travel_m or math.degrees(travel_rad) > cfg.icp_max_travel_deg:
        return None  # beyond the coarsest level's reach: ICP jumped to another minimum
    if icp_ambiguity(depth, ref_depth, K, result) > cfg.icp_max_ambiguity_m:
        return None  # depth alone leaves a direction free: the motion along it would be a guess
    return Hypothesis("icp", result.T, cfg.icp_sigma_m, cfg.icp_sigma_deg, result.inliers)


class FallbackChain:
    """The candidates of one frame against its keyframe (``candidates``)."""

    def __init__(self, camera: CameraModel, config: OdometrySettings, estimator: RelativePoseEstimator):
        self.camera, self.config, self.estimator = camera, config, estimator
        self.wide_extractor = FeatureExtractor(camera, config.model_copy(update={"n_features": config.wide_features}))

    def candidates(
        self, kf: KeyframeView, features: Features, depth: np.ndarray, frame: Frame, prior: np.ndarray
    ) -> list[Hypothesis]:
        """``T_kf_frame`` candidates (body frame) from the motion ``prior``."""
        kf_features, kf_gray, kf_depth = kf
        cfg, out = self.config, []
        wide_kf = self.wide_extractor.extract_gray(kf_gray, kf_depth) if kf_gray is not None else None
        wide = self.wide_extractor.extract(frame) if wide_kf is not None else None
        if wide_kf is not None and wide is not None:
            try:
                rel = self.estimator.estimate(wide_kf, wide)
                out.append(Hypothesis("wide", rel.T_a_b, rel.sigma_m, rel.sigma_deg, rel.inliers))
            except Rejected:
                pass
        a, b = (wide_kf, wide) if wide_kf is not None and wide is not None else (kf_features, features)
        try:
            rel = self.estimator.estimate_guided(a, b, prior, cfg.guided_radius_px)
            out.append(Hypothesis("guided", rel.T_a_b, rel.sigma_m, rel.sigma_deg, rel.inliers))
        except Rejected:
            pass
        if cfg.dense and kf_gray is not None:
            h = self.dense(kf_gray, kf_depth, frame, prior)
            if h is not None:
                out.append(h)
        for T in [h.T for h in out] + [prior, np.eye(4)]:
            h = icp_hypothesis(self.camera.depth, cfg, T, depth, kf_depth)
            if h is not None:
                out.append(h)
        return out

    def dense(self, kf_gray: np.ndarray, kf_depth: np.ndarray, frame: Frame, prior: np.ndarray) -> Hypothesis | None:
        """Dense photometric alignment of the keyframe to the frame from ``prior`` (``perception.dense``)."""
        E, E_inv = self.estimator.E, self.estimator.E_inv  # body -> colour camera
        ref_depth = depth_in_color(kf_depth, self.camera, scale=2)
        result = align(kf_gray, ref_depth, gray_image(frame), self.camera.color, inverse(E @ prior @ E_inv))
        if result is None:
            return None
        cfg = self.config
        return Hypothesis("dense", E_inv @ inverse(result.T) @ E, cfg.icp_sigma_m, cfg.icp_sigma_deg, result.pixels)
