"""iSAM2 pose graph over keyframes: a prior on the first pose and odometry between-factors (SPEC 6.8).

Every factor is kept as plain data (``FactorRecord``) and every iSAM2 update is logged, so ``state()`` is
picklable and ``from_state()`` rebuilds the identical solver by replaying the updates into a fresh iSAM2
(gtsam objects themselves do not pickle; iSAM2's estimate depends on its update history, not only on
the factors).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Any

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


@dataclass(frozen=True)
class FactorRecord:
    """One factor as plain data: a prior on keyframe ``a`` (``b`` = -1) or a between-factor a -> b.

    ``measurement`` is the prior pose or ``T_a_b`` (4x4); ``huber_k`` set means a Huber robust kernel.
    """

    a: int
    b: int
    measurement: np.ndarray
    sigma_m: float
    sigma_deg: float
    huber_k: float | None = None

    def to_gtsam(self) -> gtsam.NonlinearFactor:
        noise = pose_noise(self.sigma_m, self.sigma_deg)
        if self.huber_k is not None:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.huber_k), noise)
        if self.b < 0:
            return gtsam.PriorFactorPose3(X(self.a), gtsam.Pose3(self.measurement), noise)
        return gtsam.BetweenFactorPose3(X(self.a), X(self.b), gtsam.Pose3(self.measurement), noise)


class PoseGraph:
    """Keyframe poses in an incremental iSAM2 graph. Keys are ``X(i)`` for keyframe i = 0, 1, ..."""

    def __init__(self, noise: NoiseSettings = NoiseSettings()):
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(noise.relinearize_threshold)
        params.relinearizeSkip = noise.relinearize_skip
        self.isam = gtsam.ISAM2(params)
        self.noise = noise
        self.factors: list[FactorRecord] = []  # index = iSAM2 factor index
        self._initial: list[np.ndarray] = []  # initial guesses in the order they were inserted
        self._log: list[tuple[int, int, tuple[int, ...], bool]] = []  # per update: factors, values, removed, ok
        self._estimate: gtsam.Values | None = None
        self._latest = np.eye(4)
        self.num_keyframes = 0
        self.num_factors = 0
        self.updates = 0

    def add_first(self, pose: np.ndarray) -> int:
        """Anchor keyframe 0 at ``pose`` (camera-to-world) with a tight prior."""
        if self.num_keyframes:
            raise ValueError("the graph already has a first keyframe")
        n = self.noise
        self._update([FactorRecord(0, -1, np.array(pose, float), n.prior_sigma_m, n.prior_sigma_deg)],
                     [np.array(pose, float)])
        return 0

    def add_keyframe(self, relative: np.ndarray, sigma_m: float | None = None, sigma_deg: float | None = None) -> int:
        """Append a keyframe linked to the previous one by the odometry ``relative`` pose (prev -> new).

        Sigmas default to the configured odometry noise (external odometry); visual odometry passes its own.
        """
        if not self.num_keyframes:
            raise ValueError("add_first must come before add_keyframe")
        k = self.num_keyframes
        if sigma_m is None:
            sigma_m, sigma_deg = self.noise.odometry_sigma_m, self.noise.odometry_sigma_deg
        rel = np.array(relative, float)
        guess = gtsam.Pose3(self._latest).compose(gtsam.Pose3(rel)).matrix()
        self._update([FactorRecord(k - 1, k, rel, sigma_m, sigma_deg or self.noise.odometry_sigma_deg)], [guess])
        return k

    def add_between(self, k_a: int, k_b: int, T_a_b: np.ndarray, sigma_m: float, sigma_deg: float) -> int:
        """An extra Gaussian between-factor of existing keyframes (e.g. a skip edge of the odometry)."""
        result = self._update([FactorRecord(k_a, k_b, np.array(T_a_b, float), sigma_m, sigma_deg)])
        return int(result.getNewFactorsIndices()[0])

    def add_loop(self, k_a: int, k_b: int, T_a_b: np.ndarray, sigma_m: float, sigma_deg: float,
                 robust_k: float = 3.0, iterations: int = 10) -> int:
        """Add a loop-closure between-factor (pose of b in a) under a Huber kernel; returns its factor index.

        Huber rather than Cauchy: after long drift a true loop starts tens of sigmas away, where Cauchy's
        weight vanishes and the loop would barely pull; outliers are kept out by the verifier instead.
        """
        result = self._update([FactorRecord(k_a, k_b, np.array(T_a_b, float), sigma_m, sigma_deg, robust_k)])
        index = int(result.getNewFactorsIndices()[0])
        self._converge(iterations)
        return index

    def _converge(self, iterations: int) -> None:
        """Extra iSAM2 steps until the newest pose settles: a loop change moves many poses at once."""
        for _ in range(iterations):
            before = self._latest
            self._update([])
            if np.abs(self._latest - before).max() < 1e-5:
                break

    def remove_factors(self, indices: list[int]) -> None:
        """Retract factors (e.g. a loop closure found inconsistent) through iSAM2's removeFactorIndices."""
        self._update([], remove=indices)
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

    def _update(self, factors: list[FactorRecord], values: list[np.ndarray] = (),
                remove: list[int] | None = None) -> gtsam.ISAM2Result:
        """One iSAM2 update: new factors, initial guesses of the next keyframes, factor indices to remove."""
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f.to_gtsam())
        initial = gtsam.Values()
        for i, pose in enumerate(values):
            initial.insert(X(self.num_keyframes + i), gtsam.Pose3(pose))
        self.factors.extend(factors)  # logged even when iSAM2 throws: it may hold them already
        self._initial.extend(values)
        try:
            if remove:
                result = self.isam.update(graph, initial, list(remove))
            else:
                result = self.isam.update(graph, initial)
        except RuntimeError as exc:
            self._log.append((len(factors), len(values), tuple(remove or ()), False))
            log.error("iSAM2 update failed: %s", exc)
            raise SolverError(str(exc)) from exc
        self._log.append((len(factors), len(values), tuple(remove or ()), True))
        self.updates += 1
        self.num_factors += len(factors) - len(remove or ())
        self.num_keyframes += len(values)
        self._estimate = None
        self._latest = self.pose(self.num_keyframes - 1)
        return result

    # ------------------------------------------------------------ plain state

    def state(self) -> dict[str, Any]:
        """Plain data (numbers, strings, arrays) from which ``from_state`` rebuilds this graph exactly.

        ``factors`` in columns (index = iSAM2 factor index, removed ones included), the initial guesses
        in insertion order, the update log (failed updates too), and the current estimate (a replay check).
        """
        f = self.factors
        return {
            "noise": asdict(self.noise),
            "factors": {
                "a": np.array([r.a for r in f], np.int64), "b": np.array([r.b for r in f], np.int64),
                "measurement": np.array([r.measurement for r in f]).reshape(-1, 4, 4),
                "sigma_m": np.array([r.sigma_m for r in f]), "sigma_deg": np.array([r.sigma_deg for r in f]),
                "huber_k": np.array([np.nan if r.huber_k is None else r.huber_k for r in f])},
            "initial": np.array(self._initial).reshape(-1, 4, 4),
            "updates": list(self._log),
            "estimate": self.poses(),
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> PoseGraph:
        """Replay the recorded updates into a fresh iSAM2: same factor indices, removals and estimate."""
        graph = cls(NoiseSettings(**state["noise"]))
        c = state["factors"]
        factors = [FactorRecord(int(a), int(b), m, float(sm), float(sd), None if np.isnan(k) else float(k))
                   for a, b, m, sm, sd, k in zip(c["a"], c["b"], c["measurement"], c["sigma_m"], c["sigma_deg"],
                                                 c["huber_k"])]
        initial = list(state["initial"])
        nf = nv = 0
        for n_factors, n_values, removed, ok in state["updates"]:
            try:
                graph._update(factors[nf:nf + n_factors], initial[nv:nv + n_values], list(removed))
            except SolverError:
                if ok:
                    raise
            nf, nv = nf + n_factors, nv + n_values
        drift = float(np.abs(graph.poses() - state["estimate"]).max(initial=0.0))
        if drift > 1e-9:
            log.warning("replayed pose graph differs from the recorded estimate by %.3g", drift)
        return graph
