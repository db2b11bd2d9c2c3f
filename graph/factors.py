"""Factors of the graph as plain data (``FactorRecord``), their gtsam form, and a columnar form for snapshots.

Keys: ``X(k)`` is keyframe k's pose (Pose3, camera-to-world), ``L(j)`` is landmark j's position (Point3, world).
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, fields
from enum import Enum
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X


class FactorKind(Enum):
    """What a ``FactorRecord`` constrains; the value is the ``kind`` column of snapshots."""

    POSE = 0
    LANDMARK = 1


def pose_noise(sigma_m: float, sigma_deg: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal Pose3 noise; gtsam orders the tangent space as (rotation, translation)."""
    r = np.deg2rad(sigma_deg)
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, sigma_m, sigma_m, sigma_m]))


def position_noise(p_cam: np.ndarray, sigma_m: float, range_sigma_m: float | None = None) -> gtsam.noiseModel.Diagonal:
    """A camera-frame position sigma as (bearing, bearing, range) sigmas: ``sigma_m`` across the ray (as
    sigma / range rad) and ``range_sigma_m`` along it (``sigma_m`` when None: isotropic)."""
    r = float(np.linalg.norm(p_cam))
    along = sigma_m if range_sigma_m is None else range_sigma_m
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m / r, sigma_m / r, along]))


def position_covariance(p_cam: np.ndarray, sigma_m: float, range_sigma_m: float | None = None) -> np.ndarray:
    """The 3x3 camera-frame covariance of ``position_noise``: ``sigma_m`` across the ray, ``range_sigma_m`` along."""
    u = np.asarray(p_cam, float).reshape(3) / np.linalg.norm(p_cam)
    along = sigma_m if range_sigma_m is None else range_sigma_m
    return sigma_m**2 * np.eye(3) + (along**2 - sigma_m**2) * np.outer(u, u)


@dataclass(frozen=True)
class FactorRecord:
    """One factor as plain data.

    ``kind`` POSE: a prior on keyframe ``a`` (``b`` None, ``measurement`` the 4x4 pose) or a between-factor
    a -> b (``measurement`` = T_a_b). ``kind`` LANDMARK: a prior on landmark ``a`` (``b`` None, ``measurement``
    the world position) or the position of landmark ``b`` measured in keyframe ``a``'s camera frame
    (``measurement`` a 3-vector; a bearing-range factor with equivalent noise: ``sigma_m`` across the viewing
    ray, ``range_sigma_m`` along it when set). ``huber_k`` set means a Huber robust kernel; ``sigma_deg`` is
    unused by landmark factors. A factor with ``covariance`` uses it instead of the sigmas: 6x6 on a pose (a
    between-factor turned into a prior on its first keyframe, ``graph.window_factors``), 3x3 on a landmark
    prior (a measurement from a fixed keyframe turned into a world prior).

    Records pickled by release 0.1.0 (an int ``kind``, ``b`` = -1 on a prior) unpickle in this form.
    """

    a: int
    b: int | None
    measurement: np.ndarray
    sigma_m: float
    sigma_deg: float
    huber_k: float | None = None
    kind: FactorKind = FactorKind.POSE
    covariance: np.ndarray | None = None  # a full 6x6 (rotation, translation) or 3x3 covariance instead of sigmas
    range_sigma_m: float | None = None  # a landmark measurement's sigma along the viewing ray

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickling, also of release 0.1.0's records: ``kind`` an int, ``b`` -1 on a prior."""
        state = {**_DEFAULTS, **state}
        if not isinstance(state["kind"], FactorKind):
            state["kind"] = FactorKind(int(state["kind"]))
        if state["b"] is not None and state["b"] < 0:
            state["b"] = None
        self.__dict__.update(state)

    def to_gtsam(self) -> gtsam.NonlinearFactor:
        m = self.measurement
        noise: gtsam.noiseModel.Base
        if self.kind == FactorKind.LANDMARK:
            if self.b is None:
                noise = (
                    gtsam.noiseModel.Isotropic.Sigma(3, self.sigma_m)
                    if self.covariance is None
                    else gtsam.noiseModel.Gaussian.Covariance(np.asarray(self.covariance, float))
                )
                return gtsam.PriorFactorPoint3(L(self.a), m, self._robust(noise))
            return gtsam.BearingRangeFactor3D(
                X(self.a),
                L(self.b),
                gtsam.Unit3(m),
                float(np.linalg.norm(m)),
                self._robust(position_noise(m, self.sigma_m, self.range_sigma_m)),
            )
        noise = self._robust(
            pose_noise(self.sigma_m, self.sigma_deg)
            if self.covariance is None
            else gtsam.noiseModel.Gaussian.Covariance(np.asarray(self.covariance, float))
        )
        if self.b is None:
            return gtsam.PriorFactorPose3(X(self.a), gtsam.Pose3(m), noise)
        return gtsam.BetweenFactorPose3(X(self.a), X(self.b), gtsam.Pose3(m), noise)

    def _robust(self, noise: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        if self.huber_k is None:
            return noise
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.huber_k), noise)


_DEFAULTS = {f.name: f.default for f in fields(FactorRecord) if f.default is not MISSING}
"""The fields with defaults: a record pickled before one existed has none of it."""


def to_columns(records: list[FactorRecord]) -> dict[str, np.ndarray]:
    """Records as arrays (one row per factor); a landmark factor's 3-vector sits in the 4x4's translation, and
    a landmark prior's 3x3 covariance in the 6x6's top-left block; ``b`` is -1 on a prior, ``kind`` the
    ``FactorKind`` value."""
    measurement = np.tile(np.eye(4), (len(records), 1, 1))
    for i, r in enumerate(records):
        if r.kind == FactorKind.LANDMARK:
            measurement[i, :3, 3] = r.measurement
        else:
            measurement[i] = r.measurement
    return {
        "a": np.array([r.a for r in records], np.int64),
        "b": np.array([-1 if r.b is None else r.b for r in records], np.int64),
        "measurement": measurement,
        "sigma_m": np.array([r.sigma_m for r in records], float),
        "sigma_deg": np.array([r.sigma_deg for r in records], float),
        "huber_k": np.array([np.nan if r.huber_k is None else r.huber_k for r in records], float),
        "kind": np.array([r.kind.value for r in records], np.int64),
        "covariance": np.array([_covariance_column(r.covariance) for r in records], float).reshape(-1, 6, 6),
        "range_sigma_m": np.array([np.nan if r.range_sigma_m is None else r.range_sigma_m for r in records], float),
    }


def _covariance_column(covariance: np.ndarray | None) -> np.ndarray:
    if covariance is None:
        return np.full((6, 6), np.nan)
    out = np.eye(6)
    n = len(covariance)
    out[:n, :n] = covariance
    return out


def from_columns(c: dict[str, Any] | list[FactorRecord]) -> list[FactorRecord]:
    """The records of ``to_columns`` (columns without ``kind``, from before landmarks, are all POSE; without
    ``covariance`` or ``range_sigma_m``, from older snapshots, none has one); records given as they are."""
    if isinstance(c, list):
        return c
    n = len(c["a"])
    kinds = [FactorKind(int(kind)) for kind in c.get("kind", np.zeros(n, np.int64))]
    covariances = c.get("covariance", np.full((n, 6, 6), np.nan))
    ranges = c.get("range_sigma_m", np.full(n, np.nan))
    return [
        FactorRecord(
            int(a),
            None if b < 0 else int(b),
            m[:3, 3].copy() if kind == FactorKind.LANDMARK else m,
            float(sm),
            float(sd),
            None if np.isnan(k) else float(k),
            kind,
            None if np.isnan(cov).any() else (cov[:3, :3].copy() if kind == FactorKind.LANDMARK else cov),
            None if np.isnan(rs) else float(rs),
        )
        for a, b, m, sm, sd, k, kind, cov, rs in zip(
            c["a"],
            c["b"],
            c["measurement"],
            c["sigma_m"],
            c["sigma_deg"],
            c["huber_k"],
            kinds,
            covariances,
            ranges,
            strict=True,
        )
    ]
