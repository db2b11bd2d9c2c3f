"""RGB-D visual odometry (Sec. 2.4.4, SPEC 6.4): ORB features with depth, PnP-RANSAC, LM refinement.

Poses are those of the body frame: the colour camera when depth is registered, else the depth camera
(``T_body = T_color * depth_to_color``), which is the frame the ground truth of Kinect data refers to.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from graph.geometry import inverse
from perception.camera import pixels_to_points
from perception.frame import CameraModel, Frame
from perception.registration import depth_at_color_pixels

log = logging.getLogger(__name__)

MAX_GUIDED_HAMMING = 64
"""Guided matching: the largest ORB descriptor distance (of 256 bits) accepted near a predicted pixel."""


class OdometrySettings(BaseModel):
    """RGB-D visual odometry, used for frames that carry no odometry: ORB features with depth, the geometric
    acceptance of a relative pose, its factor's sigmas, and the depth ICP refinement of keyframe poses."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    visual: bool = Field(
        default=True, description="track frames without odometry visually (off: they are rejected as no_odometry)"
    )
    tracker: Literal["flow", "features"] = Field(
        default="flow",
        description="between keyframes: follow the keyframe's points by optical flow and solve PnP (flow), or "
        "extract and match ORB in every frame (features); keyframes always use features",
    )
    flow_points: int = Field(default=400, ge=20, description="flow: keyframe points followed at most")
    flow_max_fb_px: float = Field(
        default=1.0, gt=0, description="flow: a track whose backward flow misses its start by more is dropped"
    )
    n_features: int = Field(default=1500, ge=100)
    ratio: float = Field(default=0.8, gt=0, le=1, description="Lowe ratio test")
    min_matches: int = Field(default=30, ge=6)
    min_inliers: int = Field(default=25, ge=6)
    ransac_px: float = Field(default=3.0, gt=0)
    max_residual_px: float = Field(default=2.0, gt=0)
    min_depth_m: float = Field(default=0.2, ge=0, description="keypoints nearer than this have no 3D point")
    max_depth_m: float = Field(default=6.0, gt=0, description="... nor those farther than this")
    max_edge_ratio: float | None = Field(
        default=0.02,
        gt=0,
        description="... nor those on a depth edge: their 5 x 5 depth neighbourhood has holes or spans this "
        "fraction of their depth or more; null = no edge test",
    )
    lost_sigma_scale: float = Field(
        default=100.0,
        ge=1,
        description="after a tracking loss the new map segment is held by a gauge prior at the last pose with "
        "sigmas of this x 5 cm and x 2 deg (a gauge, not a measurement: removed when the segment is attached)",
    )
    fallback: bool = Field(
        default=True,
        description="when feature tracking fails: a constant-velocity prediction, then wide-baseline features, "
        "guided matching around the predicted projections and coarse-to-fine depth ICP, chosen by depth agreement",
    )
    wide_features: int = Field(default=3000, ge=100, description="fallback: ORB features per image")
    guided_radius_px: float = Field(default=40.0, gt=0, description="fallback: guided matching search radius")
    dense: bool = Field(
        default=False,
        description="fallback: also dense photometric RGB-D alignment from the prior (perception.dense; off: "
        "no clear gain on the development scenes, synthetic:blank seeds 0-5 ATE unchanged in four, 1.61 -> "
        "1.34 cm in one, 1.64 -> 2.28 cm in one)",
    )
    min_agreement: float = Field(
        default=0.75,
        gt=0,
        le=1,
        description="fallback: a pose is used only when at least this fraction of the frame's depth points "
        "lands on the keyframe's surface (perception.icp.depth_agreement)",
    )
    fallback_override_m: float = Field(
        default=0.10,
        gt=0,
        description="fallback: a candidate replaces a feature pose that passed its own checks only when it lies "
        "farther than this from it (and agrees more with the depth)",
    )
    fallback_override_deg: float = Field(default=5.0, gt=0, description="... or is turned more than this from it")
    icp_max_ambiguity_m: float = Field(
        default=0.01,
        gt=0,
        description="fallback: a pose from depth ICP alone is used only when ICP restarted 5 cm away along its "
        "least constrained direction ends within this of it (perception.icp.icp_ambiguity)",
    )
    icp_max_travel_m: float = Field(
        default=0.5,
        gt=0,
        description="fallback: a pose from depth ICP alone must lie within this of where ICP started (its "
        "coarsest level corrects starts some 30 cm off; an answer a metre away is another minimum)",
    )
    icp_max_travel_deg: float = Field(default=30.0, gt=0, description="... and turned at most this from it")
    icp_sigma_m: float = Field(
        default=0.01, gt=0, description="factor translation sigma of a pose found by ICP or dense alignment"
    )
    icp_sigma_deg: float = Field(default=0.5, gt=0, description="factor rotation sigma of a pose found by ICP or dense")
    icp: bool = Field(default=True, description="refine keyframe-to-keyframe poses by depth point-to-plane ICP")
    icp_max_correction_m: float = Field(
        default=0.03,
        gt=0,
        description="an ICP result moving the feature-based pose farther than this is not used",
    )
    icp_max_correction_deg: float = Field(default=2.0, gt=0, description="... nor one turning it more than this")
    sigma_m_coeff: float = Field(default=0.08, gt=0, description="factor translation sigma = coeff / sqrt(inliers)")
    sigma_deg_coeff: float = Field(default=3.0, gt=0, description="factor rotation sigma = coeff / sqrt(inliers)")


@dataclass
class Features:
    """ORB keypoints of one frame: pixels (N, 2) float32, descriptors (N, 32) uint8, and colour-camera 3D points
    (N, 3) float32 (NaN without depth)."""

    pixels: np.ndarray
    descriptors: np.ndarray
    points: np.ndarray

    def __len__(self) -> int:
        return len(self.pixels)

    def with_depth(self) -> Features:
        """Only the keypoints with a 3D point: all that matching needs of the frame on the 3D side (``a`` of
        ``RelativePoseEstimator.estimate``), in the same order, so it matches exactly as the full set does.
        What loop closure keeps of each keyframe (about half the memory of the full set)."""
        keep = np.isfinite(self.points[:, 2])
        if keep.all():
            return self
        return Features(self.pixels[keep], self.descriptors[keep], self.points[keep])


@dataclass(frozen=True)
class Relative:
    """A verified relative pose ``T_a_b`` (pose of b in a's body frame) and its evidence."""

    T_a_b: np.ndarray
    matches: int
    inliers: int
    residual_px: float
    sigma_m: float
    sigma_deg: float


class Rejected(Exception):
    """Relative pose estimation failed; ``reason`` is one of the documented rejection reasons."""

    def __init__(self, reason: str, detail: str = "", matches: int = 0, inliers: int = 0):
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail, self.matches, self.inliers = reason, detail, matches, inliers


class FeatureExtractor:
    """ORB on the colour image; depth at each keypoint from depth registered to colour."""

    def __init__(self, camera: CameraModel, config: OdometrySettings | None = None):
        self.camera = camera
        self.config = config = config if config is not None else OdometrySettings()
        self.orb = cv2.ORB.create(config.n_features, scaleFactor=1.2, nlevels=8, fastThreshold=12)

    def extract(self, frame: Frame) -> Features:
        """Keypoints, descriptors and 3D points of ``frame``."""
        return self.extract_gray(gray_image(frame), frame.depth_m())

    def extract_gray(self, gray: np.ndarray, depth_m: np.ndarray) -> Features:
        """``extract`` from the grey image and metric depth of a frame."""
        kps, desc = self.orb.detectAndCompute(gray, None)
        if desc is None or not kps:
            return Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros((0, 3), np.float32))
        px = np.array([k.pt for k in kps], dtype=np.float32)
        return Features(px, desc, self._points(px, depth_m))

    def _points(self, px: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        c, cfg = self.camera.color, self.config
        z = depth_at_color_pixels(px, depth_m, self.camera, max_edge_ratio=cfg.max_edge_ratio)
        with np.errstate(invalid="ignore"):
            z[(z < cfg.min_depth_m) | (z > cfg.max_depth_m)] = np.nan
        return pixels_to_points(px[:, 0], px[:, 1], z, c).astype(np.float32)


def gray_image(frame: Frame) -> np.ndarray:
    """The frame's colour image in grey, what ORB reads."""
    return cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)


class RelativePoseEstimator:
    """Relative pose between two frames' features by PnP-RANSAC on a's 3D points and b's pixels."""

    def __init__(self, camera: CameraModel, config: OdometrySettings | None = None):
        self.camera = camera
        self.config = config if config is not None else OdometrySettings()
        self.K = camera.color.matrix()
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        E = camera.depth_to_color if (not camera.registered and camera.depth_to_color is not None) else np.eye(4)
        self.E, self.E_inv = E, inverse(E)

    def estimate(self, a: Features, b: Features, config: OdometrySettings | None = None) -> Relative:
        """``T_a_b`` in the body frame, or raise Rejected(reason); ``config`` instead of the estimator's own."""
        cfg = config if config is not None else self.config
        ia, ib = self._match(a, b, cfg)
        if len(ia) < cfg.min_matches:
            raise Rejected("too_few_matches", f"{len(ia)} < {cfg.min_matches}", len(ia))
        return self._solve(a.points[ia], b.pixels[ib], cfg, cfg.min_inliers, 1.0)

    def estimate_guided(
        self, a: Features, b: Features, T_a_b: np.ndarray, radius_px: float, config: OdometrySettings | None = None
    ) -> Relative:
        """``T_a_b`` from matches searched near where a motion prior ``T_a_b`` (body frame) puts a's points in b:
        each of a's 3D points takes b's nearest descriptor among the keypoints within ``radius_px`` of its
        predicted pixel (Hamming distance at most ``MAX_GUIDED_HAMMING``; one match per b keypoint). The
        prediction gates the search, so no ratio test is needed and repeated texture (tiles, a row of chairs)
        still matches; the pose is then measured by PnP as in ``estimate``, its sigmas doubled."""
        cfg = config if config is not None else self.config
        valid = np.nonzero(np.isfinite(a.points[:, 2]))[0]
        if len(valid) < cfg.min_inliers or len(b) < cfg.min_inliers:
            raise Rejected("too_few_matches", f"{min(len(valid), len(b))} keypoints", 0)
        T_color = self.E @ T_a_b @ self.E_inv  # a's colour camera -> b's, inverted below
        T_b_a = inverse(T_color)
        X = a.points[valid].astype(np.float64) @ T_b_a[:3, :3].T + T_b_a[:3, 3]
        front = X[:, 2] > 0.05
        valid, X = valid[front], X[front]
        K = self.K
        uv = np.stack([K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2], K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]], axis=1)
        d2 = ((uv[:, None, :] - b.pixels[None, :, :].astype(np.float64)) ** 2).sum(axis=2)
        ia_local, ib = np.nonzero(d2 < radius_px**2)
        if len(ia_local) == 0:
            raise Rejected("too_few_matches", "no keypoint near a predicted point", 0)
        ham = np.unpackbits(a.descriptors[valid[ia_local]] ^ b.descriptors[ib], axis=1).sum(axis=1)
        keep = ham <= MAX_GUIDED_HAMMING
        ia_local, ib, ham = ia_local[keep], ib[keep], ham[keep]
        order = np.lexsort((ham, ia_local))  # per a point: its best candidate first
        ia_local, ib, ham = ia_local[order], ib[order], ham[order]
        _, first = np.unique(ia_local, return_index=True)
        ia_local, ib, ham = ia_local[first], ib[first], ham[first]
        order = np.argsort(ham, kind="stable")  # per b keypoint: the closest descriptor wins
        ia_local, ib = ia_local[order], ib[order]
        _, first = np.unique(ib, return_index=True)
        ia, ib = valid[ia_local[first]], ib[first]
        if len(ia) < cfg.min_matches:
            raise Rejected("too_few_matches", f"{len(ia)} guided < {cfg.min_matches}", len(ia))
        return self._solve(a.points[ia], b.pixels[ib], cfg, cfg.min_inliers, 2.0)

    def solve(self, points: np.ndarray, pixels: np.ndarray, config: OdometrySettings | None = None) -> Relative:
        """``T_a_b`` from a's colour-camera 3D points and their pixels in b (already matched or tracked)."""
        cfg = config if config is not None else self.config
        if len(points) < cfg.min_matches:
            raise Rejected("too_few_matches", f"{len(points)} < {cfg.min_matches}", len(points))
        return self._solve(points, pixels, cfg, cfg.min_inliers, 1.0)

    def _solve(
        self, points: np.ndarray, pixels: np.ndarray, cfg: OdometrySettings, min_inliers: int, scale: float
    ) -> Relative:
        """PnP-RANSAC and LM refinement of a's 3D points against b's pixels; sigmas x ``scale``."""
        obj, img = points.astype(np.float64), pixels.astype(np.float64)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            self.K,
            None,
            iterationsCount=300,
            reprojectionError=cfg.ransac_px,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
        n_inl = 0 if inl is None else len(inl)
        if not ok or n_inl < min_inliers:
            raise Rejected("too_few_inliers", f"{n_inl} < {min_inliers}", len(obj), n_inl)
        inl = inl[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], self.K, None, rvec, tvec)
        proj, _ = cv2.projectPoints(obj[inl], rvec, tvec, self.K, None)
        residual = float(np.sqrt(np.mean(np.sum((proj[:, 0] - img[inl]) ** 2, axis=1))))
        if residual > cfg.max_residual_px:
            raise Rejected("residual_too_large", f"{residual:.2f} px > {cfg.max_residual_px}", len(obj), n_inl)
        T_b_a = np.eye(4)
        T_b_a[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_b_a[:3, 3] = tvec[:, 0]
        T_color = inverse(T_b_a)
        sigma_m = scale * max(0.002, cfg.sigma_m_coeff / np.sqrt(n_inl))
        sigma_deg = scale * max(0.05, cfg.sigma_deg_coeff / np.sqrt(n_inl))
        return Relative(self.E_inv @ T_color @ self.E, len(obj), n_inl, residual, sigma_m, sigma_deg)

    def _match(self, a: Features, b: Features, cfg: OdometrySettings) -> tuple[np.ndarray, np.ndarray]:
        valid = np.nonzero(np.isfinite(a.points[:, 2]))[0]
        if len(valid) < 2 or len(b) < 2:
            return np.zeros(0, int), np.zeros(0, int)
        knn = self.matcher.knnMatch(a.descriptors[valid], b.descriptors, k=2)
        ia, ib = [], []
        for pair in knn:
            if len(pair) == 2 and pair[0].distance < cfg.ratio * pair[1].distance:
                ia.append(valid[pair[0].queryIdx])
                ib.append(pair[0].trainIdx)
        qa, qb = np.asarray(ia, int), np.asarray(ib, int)
        _, first = np.unique(qb, return_index=True)  # one match per b keypoint
        return qa[first], qb[first]
