"""iSAM2 pose graph over keyframes: a prior on the first pose and odometry between-factors (SPEC 6.8)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

log = logging.getLogger(__name__)


class SolverError(Exception):
    """iSAM2 rejected an update (e.g. an indeterminant system); the caller counts it and carries on."""


@dataclass(frozen=True)
class NoiseSettings:
    """Standard deviations of the pose prior and of odometry between-factors."""

    odometry_sigma_m: float = 0.02
    odometry_sigma_deg: float = 1.0
    prior_sigma_m: float = 1e-4
    prior_sigma_deg: float = 0.01
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1


def pose_noise(sigma_m: float, sigma_deg: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal Pose3 noise; gtsam orders the tangent space as (rotation, translation)."""
    r = np.deg2rad(sigma_deg)
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, sigma_m, sigma_m, sigma_m]))


class PoseGraph:
    """Keyframe poses in an incremental iSAM2 graph. Keys are ``X(i)`` for keyframe i = 0, 1, ..."""

    def __init__(self, noise: NoiseSettings = NoiseSettings()):
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(noise.relinearize_threshold)
        params.relinearizeSkip = noise.relinearize_skip
        self.isam = gtsam.ISAM2(params)
        self.noise = noise
        self._odometry_noise = pose_noise(noise.odometry_sigma_m, noise.odometry_sigma_deg)
        self._prior_noise = pose_noise(noise.prior_sigma_m, noise.prior_sigma_deg)
        self._estimate: gtsam.Values | None = None
        self._latest = np.eye(4)
        self.num_keyframes = 0
        self.num_factors = 0
        self.updates = 0

    def add_first(self, pose: np.ndarray) -> int:
        """Anchor keyframe 0 at ``pose`` (camera-to-world) with a tight prior."""
        if self.num_keyframes:
            raise ValueError("the graph already has a first keyframe")
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(pose), self._prior_noise))
        values.insert(X(0), gtsam.Pose3(pose))
        self._update(graph, values)
        return 0

    def add_keyframe(self, relative: np.ndarray, sigma_m: float | None = None, sigma_deg: float | None = None) -> int:
        """Append a keyframe linked to the previous one by the odometry ``relative`` pose (prev -> new).

        Sigmas default to the configured odometry noise (external odometry); visual odometry passes its own.
        """
        if not self.num_keyframes:
            raise ValueError("add_first must come before add_keyframe")
        k = self.num_keyframes
        noise = self._odometry_noise if sigma_m is None else pose_noise(
            sigma_m, sigma_deg or self.noise.odometry_sigma_deg)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        rel = gtsam.Pose3(relative)
        graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), rel, noise))
        values.insert(X(k), gtsam.Pose3(self._latest).compose(rel))
        self._update(graph, values)
        return k

    def add_between(self, k_a: int, k_b: int, T_a_b: np.ndarray, sigma_m: float, sigma_deg: float) -> int:
        """An extra Gaussian between-factor of existing keyframes (e.g. a skip edge of the odometry)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(X(k_a), X(k_b), gtsam.Pose3(T_a_b), pose_noise(sigma_m, sigma_deg)))
        result = self._update(graph, gtsam.Values())
        return int(result.getNewFactorsIndices()[0])

    def add_loop(self, k_a: int, k_b: int, T_a_b: np.ndarray, sigma_m: float, sigma_deg: float,
                 robust_k: float = 3.0, iterations: int = 10) -> int:
        """Add a loop-closure between-factor (pose of b in a) under a Huber kernel; returns its factor index.

        Huber rather than Cauchy: after long drift a true loop starts tens of sigmas away, where Cauchy's
        weight vanishes and the loop would barely pull; outliers are kept out by the verifier instead.
        """
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k),
                                               pose_noise(sigma_m, sigma_deg))
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(X(k_a), X(k_b), gtsam.Pose3(T_a_b), noise))
        result = self._update(graph, gtsam.Values())
        index = int(result.getNewFactorsIndices()[0])
        self._converge(iterations)
        return index

    def _converge(self, iterations: int) -> None:
        """Extra iSAM2 steps until the newest pose settles: a loop change moves many poses at once."""
        for _ in range(iterations):
            before = self._latest
            self._update(gtsam.NonlinearFactorGraph(), gtsam.Values())
            if np.abs(self._latest - before).max() < 1e-5:
                break

    def remove_factors(self, indices: list[int]) -> None:
        """Retract factors (e.g. a loop closure found inconsistent) through iSAM2's removeFactorIndices."""
        self._update(gtsam.NonlinearFactorGraph(), gtsam.Values(), remove=indices)
        self.num_factors -= len(indices)
        self._converge(10)

    def pose(self, k: int) -> np.ndarray:
        """Current estimate of keyframe ``k`` (camera-to-world 4x4)."""
        return self.isam.calculateEstimatePose3(X(k)).matrix()

    def poses(self) -> np.ndarray:
        """All keyframe estimates, (K, 4, 4), cached until the next update."""
        if self._estimate is None:
            self._estimate = self.isam.calculateEstimate()
        return np.stack([self._estimate.atPose3(X(k)).matrix() for k in range(self.num_keyframes)]) \
            if self.num_keyframes else np.zeros((0, 4, 4))

    def marginal_covariance(self, k: int) -> np.ndarray:
        """6x6 marginal covariance of keyframe ``k`` (rotation, translation), from iSAM2's Bayes tree."""
        return np.asarray(self.isam.marginalCovariance(X(k)))

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                remove: list[int] | None = None) -> gtsam.ISAM2Result:
        try:
            if remove:
                result = self.isam.update(graph, values, remove)
            else:
                result = self.isam.update(graph, values)
        except RuntimeError as exc:
            log.error("iSAM2 update failed: %s", exc)
            raise SolverError(str(exc)) from exc
        self.updates += 1
        self.num_factors += graph.size()
        self.num_keyframes += values.size()
        self._estimate = None
        self._latest = self.pose(self.num_keyframes - 1)
        return result
