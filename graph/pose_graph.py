"""iSAM2 graph over keyframe poses and Point3 landmarks (SPEC 6.8).

Keyframes: a prior on the first pose, odometry and loop-closure between-factors. Landmarks: camera-frame
position measurements, inserted into iSAM2 only once observable (a prior, or observations from two
keyframes), so an underdetermined landmark never reaches the solver.

Every factor is kept as plain data (``graph.factors.FactorRecord``) and every successful iSAM2 update is
logged, so ``state()`` is picklable and ``from_state()`` rebuilds the identical solver by replaying the
updates into a fresh iSAM2 (gtsam objects do not pickle; iSAM2's estimate depends on its update history).
A failed update (iSAM2 throws, e.g. an indeterminant system) may leave its variables inside iSAM2, so the
solver is rebuilt from the log without it: the graph is then exactly as before the failed update.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from graph.books import Books, LogEntry, UpdateResult
from graph.errors import SolverError
from graph.factors import FactorKind, FactorRecord, from_columns, pose_noise
from graph.keyframes import Keyframes
from graph.landmarks import Landmarks
from graph.settings import GraphSettings, from_noise_state, noise_state

__all__ = ["FactorRecord", "PoseGraph", "SolverError", "pose_noise"]

log = logging.getLogger(__name__)


class PoseGraph(Keyframes, Landmarks):
    """Keyframe poses ``X(i)`` (i = 0, 1, ...) and landmarks ``L(j)`` in an incremental iSAM2 graph.

    ``factorization``: iSAM2's, CHOLESKY until Cholesky found the system indeterminant (then QR, ``update``).
    """

    def __init__(self, settings: GraphSettings | None = None, factorization: str = "CHOLESKY"):
        self.settings = GraphSettings() if settings is None else settings
        self.factorization = factorization
        self.isam = self._new_isam()
        self.books = Books()
        self._estimate: gtsam.Values | None = None
        self._latest = np.eye(4)
        self.timings: list[float] | None = None  # a list: the seconds of each ISAM2.update call are appended

    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.settings.relinearize_threshold)
        params.relinearizeSkip = self.settings.relinearize_skip
        params.enablePartialRelinearizationCheck = self.settings.partial_relinearization_check
        params.setFactorization(self.factorization)
        return gtsam.ISAM2(params)

    # ------------------------------------------------------------ queries

    def _newest(self) -> np.ndarray:
        return self._latest

    def pose(self, k: int) -> np.ndarray:
        """Current estimate of keyframe ``k`` (camera-to-world 4x4)."""
        return self.isam.calculateEstimatePose3(X(k)).matrix()

    def poses(self) -> np.ndarray:
        """All keyframe estimates, (K, 4, 4), cached until the next update."""
        if not self.num_keyframes:
            return np.zeros((0, 4, 4))
        return self._keyframe_poses(self._current())

    def _keyframe_poses(self, values: gtsam.Values) -> np.ndarray:
        """The keyframe poses in ``values``, (K, 4, 4) in keyframe order."""
        rows = gtsam.utilities.extractPose3(values)  # (K, 12): rotation row-major, translation; in key order
        if len(rows) != self.num_keyframes:  # never expected (the keyframes are the only Pose3 values)
            return np.stack([values.atPose3(X(k)).matrix() for k in range(self.num_keyframes)])
        out = np.zeros((len(rows), 4, 4))
        out[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        out[:, :3, 3] = rows[:, 9:]
        out[:, 3, 3] = 1.0
        return out

    def marginal_covariance(self, k: int) -> np.ndarray:
        """6x6 marginal covariance of keyframe ``k`` (rotation, translation), from iSAM2's Bayes tree."""
        return np.asarray(self.isam.marginalCovariance(X(k)))

    def optimum(self) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Keyframe poses and landmark positions at the batch Levenberg-Marquardt optimum of the live factors,
        started from the iSAM2 estimate (which stops short of it: a variable is relinearized only once its
        update exceeds ``relinearize_threshold``). The graph itself is left as it is. Should the batch problem
        fail (gtsam throws, e.g. an indeterminant system), iSAM2's estimate is returned, with a warning."""
        factors = gtsam.NonlinearFactorGraph()
        for i, f in enumerate(self.books.factors):
            if i not in self.books.removed:
                factors.add(f.to_gtsam())
        try:
            values = gtsam.LevenbergMarquardtOptimizer(factors, self._current()).optimize()
        except RuntimeError as exc:
            log.warning("the batch optimisation failed, keeping iSAM2's estimate: %s", exc)
            return self.poses(), self.landmarks()
        return self._keyframe_poses(values), {j: np.asarray(values.atPoint3(L(j))) for j in self.books.landmarks}

    def _current(self) -> gtsam.Values:
        if self._estimate is None:
            self._estimate = self.isam.calculateEstimate()
        return self._estimate

    def landmark(self, j: int) -> np.ndarray:
        """Current estimate of landmark ``j`` (world position)."""
        return np.asarray(self.isam.calculateEstimatePoint3(L(j)))

    def landmarks(self) -> dict[int, np.ndarray]:
        """All landmark estimates by id: from the cached full estimate when there is one, else one key at a time
        (a full estimate costs O(poses) under the GIL; the service asks for the landmarks after every keyframe)."""
        if self._estimate is not None:
            return {j: np.asarray(self._estimate.atPoint3(L(j))) for j in self.books.landmarks}
        return {j: np.asarray(self.isam.calculateEstimatePoint3(L(j))) for j in self.books.landmarks}

    def flush(self, timeout: float = 600.0) -> None:
        """Nothing to wait for: every factor is in this one iSAM2 (its estimate stays iSAM2's; ``optimum`` gives
        the batch optimum without changing the graph). For the ``Graph`` interface."""

    def polish(self) -> bool:
        """Nothing to move: the estimate stays iSAM2's (``optimum`` gives the batch optimum without changing the
        graph). For the ``Graph`` interface."""
        return False

    def close(self) -> None:
        """Nothing to stop (no child process). For the ``Graph`` interface."""

    # ------------------------------------------------------------ updates

    def update(
        self,
        factors: Sequence[FactorRecord],
        poses: Sequence[np.ndarray] = (),
        landmarks: Sequence[tuple[int, np.ndarray]] = (),
        remove: Sequence[int] | None = None,
    ) -> UpdateResult:
        """One iSAM2 update: new factors, guesses of the next keyframes and of new landmarks, factors to remove.

        When iSAM2 throws, the solver is rebuilt from the log (without this update) and SolverError raised. An
        indeterminant system under Cholesky (its information form loses precision as uncertainty grows along a
        long chain) first switches the solver to QR for good: rebuilt, and the update retried.
        """
        try:
            return self._apply(factors, poses, landmarks, list(remove or []))
        except RuntimeError as exc:
            error = exc
        if self.factorization == "CHOLESKY" and "ndetermina" in str(error):
            log.warning(
                "iSAM2 found the system indeterminant with Cholesky; rebuilding with QR factorization "
                "(numerically stabler on long chains without loop closures) and retrying"
            )
            self.factorization = "QR"
            self._rebuild()
            try:
                return self._apply(factors, poses, landmarks, list(remove or []))
            except RuntimeError as exc:
                error = exc
        log.error("iSAM2 update failed, rebuilding the solver without it: %s", error)
        self._rebuild()
        raise SolverError(str(error)) from error

    def _apply(
        self,
        factors: Sequence[FactorRecord],
        poses: Sequence[np.ndarray],
        landmarks: Sequence[tuple[int, np.ndarray]],
        remove: list[int],
    ) -> UpdateResult:
        """The iSAM2 update itself, and on success its bookkeeping (records, log, counters)."""
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f.to_gtsam())
        initial = gtsam.Values()
        for i, pose in enumerate(poses):
            initial.insert(X(self.num_keyframes + i), gtsam.Pose3(pose))
        for j, position in landmarks:
            initial.insertPoint3(L(j), np.asarray(position, float))
        t0 = time.perf_counter()
        result = self.isam.update(graph, initial, list(remove)) if remove else self.isam.update(graph, initial)
        if self.timings is not None:
            self.timings.append(time.perf_counter() - t0)
        self.books.record(factors, poses, landmarks, remove)
        if remove:
            self._drop_unconstrained(remove)
        self._estimate = None
        if self.num_keyframes:
            self._latest = self.pose(self.num_keyframes - 1)
        return UpdateResult(tuple(int(i) for i in result.getNewFactorsIndices()))

    def _drop_unconstrained(self, removed: list[int]) -> None:
        """Landmarks left without factors: iSAM2 removed their variables, so they wait to be observable again."""
        books = self.books
        touched = {
            f.a if f.b is None else f.b for f in (books.factors[i] for i in removed) if f.kind == FactorKind.LANDMARK
        }
        for j in touched & books.landmarks.keys():
            if not any(
                f.kind == FactorKind.LANDMARK and (f.a if f.b is None else f.b) == j and i not in books.removed
                for i, f in enumerate(books.factors)
            ):
                books.lose_landmark(j)

    def _rebuild(self) -> None:
        """A fresh iSAM2 with every logged update replayed: the graph as it was before a failed update (the
        observations waiting for their landmarks kept as they are)."""
        old = self.books
        self.isam = self._new_isam()
        self.books, self._estimate, self._latest = Books(pending=old.pending), None, np.eye(4)
        self.replay(old.log, old.factors, old.initial, old.landmark_initial)

    def replay(
        self,
        entries: Sequence[LogEntry],
        factors: Sequence[FactorRecord],
        initial: Sequence[np.ndarray],
        landmark_initial: Sequence[np.ndarray],
    ) -> None:
        """Apply an update log (``books.log``) with its records and guesses, update by update, to this graph (a
        new one: the log's factor indices and keyframe ids start at 0). RuntimeError if iSAM2 rejects one."""
        nf = nv = nl = 0
        for n_factors, n_poses, removed, landmark_ids in entries:
            landmarks = list(zip(landmark_ids, landmark_initial[nl : nl + len(landmark_ids)], strict=False))
            self._apply(factors[nf : nf + n_factors], initial[nv : nv + n_poses], landmarks, list(removed))
            nf, nv, nl = nf + n_factors, nv + n_poses, nl + len(landmark_ids)

    # ------------------------------------------------------------ plain state

    def state(self) -> dict[str, Any]:
        """Plain data (numbers, strings, arrays) from which ``from_state`` rebuilds this graph exactly.

        ``factors`` in columns (index = iSAM2 factor index, removed ones included), the initial guesses
        of keyframes and landmarks in insertion order, the update log, landmarks still waiting to be
        observable with their held-back observations, and the current estimate (a replay check).
        """
        return {
            "noise": noise_state(self.settings),
            "factorization": self.factorization,
            **self.books.columns(),
            "estimate": self.poses(),
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> PoseGraph:
        """Replay the recorded updates into a fresh iSAM2: same factor indices, removals and estimate."""
        graph = cls(from_noise_state(state["noise"]), state.get("factorization", "CHOLESKY"))
        entries, factors, initial = _without_failed(
            state["updates"], from_columns(state["factors"]), list(state["initial"])
        )
        try:
            graph.replay(entries, factors, initial, list(state.get("landmark_initial", [])))
        except RuntimeError as exc:
            raise SolverError(f"replaying the saved graph failed: {exc}") from exc
        pending = from_columns(state["pending"]) if "pending" in state else []
        graph.books.pending = {int(j): [r for r in pending if r.b == j] for j in state.get("pending_landmarks", [])}
        drift = float(np.abs(graph.poses() - state["estimate"]).max(initial=0.0)) if "estimate" in state else 0.0
        if drift > 1e-9:  # a map store keeps no estimate to check against
            log.warning("replayed pose graph differs from the recorded estimate by %.3g", drift)
        return graph


def _without_failed(
    entries: list, factors: list[FactorRecord], initial: list[np.ndarray]
) -> tuple[list[LogEntry], list[FactorRecord], list[np.ndarray]]:
    """The update log in the current form. Logs from before landmarks are ``(factors, poses, removed, ok)``
    and kept failed updates, whose factors and guesses are dropped here (the solver no longer keeps them)."""
    if not entries or not isinstance(entries[0][3], (bool, np.bool_)):
        return [tuple(e) for e in entries], factors, initial
    kept: list[LogEntry] = []
    kept_factors: list[FactorRecord] = []
    kept_initial: list[np.ndarray] = []
    nf = nv = 0
    for n_factors, n_poses, removed, ok in entries:
        if ok:
            kept.append((n_factors, n_poses, tuple(removed), ()))
            kept_factors += factors[nf : nf + n_factors]
            kept_initial += initial[nv : nv + n_poses]
        else:
            log.warning("dropping a failed iSAM2 update of an old snapshot (%d factors, %d poses)", n_factors, n_poses)
        nf, nv = nf + n_factors, nv + n_poses
    return kept, kept_factors, kept_initial
