"""Keyframes of the pose graph: the first one anchored, odometry, extra between-factors, loop closures (SPEC 6.8).

A mixin over the graph's one update primitive, ``update(factors, poses, landmarks, remove)`` with factors in
keyframe ids (``graph.books.GraphBase``), shared by the whole graph in one iSAM2 (``PoseGraph``) and the bounded
window (``WindowedGraph``).
"""

from __future__ import annotations

import gtsam
import numpy as np

from graph.books import GraphBase
from graph.factors import FactorRecord


class Keyframes(GraphBase):
    """The keyframe half of a pose graph: it uses the graph's ``update``, ``pose`` and ``settings``."""

    def _newest(self) -> np.ndarray:
        """Current estimate of the newest keyframe."""
        return self.pose(self.num_keyframes - 1)

    def add_first(self, pose: np.ndarray) -> int:
        """Anchor keyframe 0 at ``pose`` (camera-to-world) with a tight prior."""
        if self.num_keyframes:
            raise ValueError("the graph already has a first keyframe")
        n = self.settings
        self.update(
            [FactorRecord(0, None, np.array(pose, float), n.prior_sigma_m, n.prior_sigma_deg)], [np.array(pose, float)]
        )
        return 0

    def add_keyframe(self, relative: np.ndarray, sigma_m: float | None = None, sigma_deg: float | None = None) -> int:
        """Append a keyframe linked to the previous one by the odometry ``relative`` pose (prev -> new).

        Sigmas default to the configured odometry noise (external odometry); visual odometry passes its own.
        """
        if not self.num_keyframes:
            raise ValueError("add_first must come before add_keyframe")
        return self.add_keyframe_from(self.num_keyframes - 1, relative, sigma_m, sigma_deg)

    def add_keyframe_from(
        self, k_a: int, relative: np.ndarray, sigma_m: float | None = None, sigma_deg: float | None = None
    ) -> int:
        """Append a keyframe linked to keyframe ``k_a`` by the measured ``relative`` pose (a -> new): the
        previous keyframe for odometry, any earlier one for a relocalization."""
        if not 0 <= k_a < self.num_keyframes:
            raise ValueError(f"keyframe {k_a} does not exist ({self.num_keyframes} keyframes)")
        k = self.num_keyframes
        if sigma_m is None:
            sigma_m, sigma_deg = self.settings.odometry_sigma_m, self.settings.odometry_sigma_deg
        rel = np.array(relative, float)
        guess = gtsam.Pose3(self.pose(k_a)).compose(gtsam.Pose3(rel)).matrix()
        self.update([FactorRecord(k_a, k, rel, sigma_m, sigma_deg or self.settings.odometry_sigma_deg)], [guess])
        return k

    def add_segment(self, pose: np.ndarray, sigma_m: float, sigma_deg: float) -> tuple[int, int]:
        """Append a keyframe that nothing measured links to the map (tracking was lost): a new map segment,
        held by a weak prior at the ``pose`` guess (a gauge for the solver, not a measurement; remove it when
        a measured factor attaches the segment). Returns the keyframe and the prior's factor index."""
        if not self.num_keyframes:
            raise ValueError("add_first must come before add_segment")
        k = self.num_keyframes
        pose = np.array(pose, float)
        result = self.update([FactorRecord(k, None, pose, sigma_m, sigma_deg)], [pose])
        return k, result.factor_indices[0]

    def add_between(self, k_a: int, k_b: int, T_a_b: np.ndarray, sigma_m: float, sigma_deg: float) -> int:
        """An extra Gaussian between-factor of existing keyframes (e.g. a skip edge of the odometry)."""
        return self.update([FactorRecord(k_a, k_b, np.array(T_a_b, float), sigma_m, sigma_deg)]).factor_indices[0]

    def add_loop(
        self,
        k_a: int,
        k_b: int,
        T_a_b: np.ndarray,
        sigma_m: float,
        sigma_deg: float,
        robust_k: float = 3.0,
        iterations: int = 10,
    ) -> int:
        """Add a loop-closure between-factor (pose of b in a) under a Huber kernel; returns its factor index.

        Huber rather than Cauchy: after long drift a true loop starts tens of sigmas away, where Cauchy's
        weight vanishes and the loop would barely pull; outliers are kept out by the verifier instead.
        """
        result = self.update([FactorRecord(k_a, k_b, np.array(T_a_b, float), sigma_m, sigma_deg, robust_k)])
        index = result.factor_indices[0]
        self.converge(iterations)
        return index

    def converge(self, iterations: int) -> None:
        """Extra iSAM2 steps (up to ``iterations``) until the newest pose settles: a loop change moves many poses
        at once."""
        for _ in range(iterations):
            before = self._newest()
            self.update([])
            if np.abs(self._newest() - before).max() < 1e-5:
                break

    def remove_factors(self, indices: list[int]) -> None:
        """Retract factors (e.g. a loop closure found inconsistent) through iSAM2's removeFactorIndices."""
        self.update([], remove=indices)
        self.converge(10)
