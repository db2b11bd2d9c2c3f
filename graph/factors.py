"""Factors of the graph as plain data (``FactorRecord``), their gtsam form, and a columnar form for snapshots.

Keys: ``X(k)`` is keyframe k's pose (Pose3, camera-to-world), ``L(j)`` is landmark j's position (Point3, world).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

POSE, LANDMARK = 0, 1  # FactorRecord.kind


def pose_noise(sigma_m: float, sigma_deg: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal Pose3 noise; gtsam orders the tangent space as (rotation, translation)."""
    r = np.deg2rad(sigma_deg)
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, sigma_m, sigma_m, sigma_m]))


def position_noise(p_cam: np.ndarray, sigma_m: float) -> gtsam.noiseModel.Diagonal:
    """An isotropic camera-frame position sigma as (bearing, bearing, range) sigmas: sigma / range rad, sigma m."""
    r = float(np.linalg.norm(p_cam))
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m / r, sigma_m / r, sigma_m]))


@dataclass(frozen=True)
class FactorRecord:
    """One factor as plain data.

    ``kind`` POSE: a prior on keyframe ``a`` (``b`` = -1, ``measurement`` the 4x4 pose) or a between-factor
    a -> b (``measurement`` = T_a_b). ``kind`` LANDMARK: a prior on landmark ``a`` (``b`` = -1, ``measurement``
    the world position) or the position of landmark ``b`` measured in keyframe ``a``'s camera frame
    (``measurement`` a 3-vector; a bearing-range factor with equivalent noise). ``huber_k`` set means a Huber
    robust kernel; ``sigma_deg`` is unused by landmark factors. A pose factor with ``covariance`` uses it instead
    of the sigmas (a between-factor turned into a prior on its first keyframe, ``graph.window``).
    """

    a: int
    b: int
    measurement: np.ndarray
    sigma_m: float
    sigma_deg: float
    huber_k: float | None = None
    kind: int = POSE
    covariance: np.ndarray | None = None  # a full 6x6 (rotation, translation) covariance instead of the sigmas

    def to_gtsam(self) -> gtsam.NonlinearFactor:
        m = self.measurement
        if self.kind == LANDMARK:
            if self.b < 0:
                noise = gtsam.noiseModel.Isotropic.Sigma(3, self.sigma_m)
                return gtsam.PriorFactorPoint3(L(self.a), m, self._robust(noise))
            return gtsam.BearingRangeFactor3D(X(self.a), L(self.b), gtsam.Unit3(m), float(np.linalg.norm(m)),
                                              self._robust(position_noise(m, self.sigma_m)))
        noise = self._robust(pose_noise(self.sigma_m, self.sigma_deg) if self.covariance is None
                             else gtsam.noiseModel.Gaussian.Covariance(np.asarray(self.covariance, float)))
        if self.b < 0:
            return gtsam.PriorFactorPose3(X(self.a), gtsam.Pose3(m), noise)
        return gtsam.BetweenFactorPose3(X(self.a), X(self.b), gtsam.Pose3(m), noise)

    def _robust(self, noise: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        if self.huber_k is None:
            return noise
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.huber_k), noise)


def to_columns(records: list[FactorRecord]) -> dict[str, np.ndarray]:
    """Records as arrays (one row per factor); a landmark factor's 3-vector sits in the 4x4's translation."""
    measurement = np.tile(np.eye(4), (len(records), 1, 1))
    for i, r in enumerate(records):
        if r.kind == LANDMARK:
            measurement[i, :3, 3] = r.measurement
        else:
            measurement[i] = r.measurement
    return {"a": np.array([r.a for r in records], np.int64), "b": np.array([r.b for r in records], np.int64),
            "measurement": measurement, "sigma_m": np.array([r.sigma_m for r in records], float),
            "sigma_deg": np.array([r.sigma_deg for r in records], float),
            "huber_k": np.array([np.nan if r.huber_k is None else r.huber_k for r in records], float),
            "kind": np.array([r.kind for r in records], np.int64),
            "covariance": np.array([np.full((6, 6), np.nan) if r.covariance is None else r.covariance
                                    for r in records], float).reshape(-1, 6, 6)}


def from_columns(c: dict[str, Any]) -> list[FactorRecord]:
    """The records of ``to_columns`` (columns without ``kind``, from before landmarks, are all POSE)."""
    kinds = c.get("kind", np.zeros(len(c["a"]), np.int64))
    covariances = c.get("covariance", np.full((len(c["a"]), 6, 6), np.nan))
    return [FactorRecord(int(a), int(b), m[:3, 3].copy() if kind == LANDMARK else m, float(sm), float(sd),
                         None if np.isnan(k) else float(k), int(kind), None if np.isnan(cov).any() else cov)
            for a, b, m, sm, sd, k, kind, cov in zip(c["a"], c["b"], c["measurement"], c["sigma_m"], c["sigma_deg"],
                                                     c["huber_k"], kinds, covariances)]
