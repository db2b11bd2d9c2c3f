"""Point3 landmarks of the pose graph: declared, held back until observable, then in iSAM2 (SPEC 6.8).

A landmark ``L(j)`` enters the solver only once it is observable: a prior on its position, or camera-frame
position measurements from two keyframes. Until then its observations wait here, so an underdetermined
landmark never reaches iSAM2 (no IndeterminantLinearSystemException). A landmark whose factors are all
removed leaves the solver (iSAM2 drops unused variables) and waits to be observable again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from graph.books import GraphBase
from graph.errors import SolverError
from graph.factors import FactorKind, FactorRecord


class Landmarks(GraphBase):
    """The landmark half of a pose graph (a mixin: it uses the graph's ``update``, ``pose`` and ``books``); the
    estimates (``landmark``, ``landmarks``) are the graph's own."""

    def add_landmark(self, j: int, position: np.ndarray | None = None, sigma_m: float = 1.0) -> bool:
        """Declare landmark ``j``; with a world ``position``, a prior (sigma ``sigma_m``) that makes it observable.

        Returns whether the landmark is in the solver now.
        """
        books = self.books
        if position is None:
            if j not in books.landmarks:
                books.pending.setdefault(j, [])
            return j in books.landmarks
        prior = FactorRecord(
            j, None, np.array(position, float).reshape(3), float(sigma_m), 0.0, kind=FactorKind.LANDMARK
        )
        if j in books.landmarks:
            self.update([prior])
        else:
            books.pending.setdefault(j, [])
            self._insert_landmark(j, prior)
        return True

    def add_landmark_observation(
        self, j: int, k: int, p_cam: np.ndarray, sigma_m: float, huber_k: float | None = None
    ) -> int | None:
        """Landmark ``j`` seen at ``p_cam`` (metres, keyframe ``k``'s camera frame) with isotropic ``sigma_m``.

        Returns the factor index, or None while the landmark waits to be observable: its observations are
        held back until two keyframes saw it (or it has a prior), then inserted with it in one update.
        """
        return self.add_landmark_observations(k, [(j, p_cam)], sigma_m, huber_k)[0]

    def add_landmark_observations(
        self, k: int, observations: list[tuple[int, np.ndarray]], sigma_m: float, huber_k: float | None = None
    ) -> list[int | None]:
        """Several landmarks seen from keyframe ``k`` (``(j, p_cam)`` pairs), in one iSAM2 update.

        Landmarks that become observable enter with their held-back observations; the factor index of each
        observation, or None where its landmark still waits.
        """
        return self.add_landmark_measurements([(k, j, p) for j, p in observations], sigma_m, huber_k)

    def add_landmark_measurements(
        self,
        items: Sequence[tuple[int, int, np.ndarray]],
        sigma_m: float | Sequence[float],
        huber_k: float | None = None,
        range_sigma_m: float | Sequence[float] | None = None,
    ) -> list[int | None]:
        """Landmark measurements ``(k, j, p_cam)`` from any keyframes, in one iSAM2 update (see above).

        ``sigma_m``: one sigma for all, or one per measurement; ``range_sigma_m`` likewise, the sigma along the
        viewing ray (None: ``sigma_m``, isotropic).
        """
        books = self.books
        sigmas = np.broadcast_to(np.asarray(sigma_m, float), (len(items),))
        ranges = (
            [None] * len(items)
            if range_sigma_m is None
            else np.broadcast_to(np.asarray(range_sigma_m, float), (len(items),)).tolist()
        )
        records: list[tuple[int, FactorRecord]] = []  # (landmark, its measurement)
        for (k, j, p_cam), sigma, along in zip(items, sigmas, ranges, strict=True):
            if not 0 <= k < self.num_keyframes:
                raise ValueError(f"keyframe {k} is not in the graph")
            if j not in books.landmarks and j not in books.pending:
                raise ValueError(f"landmark {j} was not added")
            p = np.array(p_cam, float).reshape(3)
            if not np.all(np.isfinite(p)) or np.linalg.norm(p) < 1e-3:
                raise ValueError(f"unusable landmark measurement {p}")
            records.append(
                (j, FactorRecord(k, j, p, float(sigma), 0.0, huber_k, FactorKind.LANDMARK, range_sigma_m=along))
            )
        factors: list[FactorRecord] = []
        landmarks: list[tuple[int, np.ndarray]] = []
        waiting: dict[int, list[FactorRecord]] = {}
        first = 0
        for j, r in records:
            if j in books.landmarks:
                factors.append(r)
            else:
                books.pending[j].append(r)
        for j in sorted({j for j, _ in records if j not in books.landmarks}):
            if len({r.a for r in books.pending[j]}) >= 2:
                waiting[j] = books.pending.pop(j)
                landmarks.append((j, self._guess(waiting[j])))
                factors += waiting[j]
        if factors:
            try:
                first = self.update(factors, landmarks=landmarks).factor_indices[0]
            except SolverError:
                books.pending.update(waiting)
                raise
        index = {id(f): first + i for i, f in enumerate(factors)}
        return [index.get(id(r)) for _, r in records]

    def withdraw_waiting(self, j: int, k: int, p_cam: np.ndarray) -> bool:
        """Take back a measurement of landmark ``j`` from keyframe ``k`` that still waits; True if found."""
        waiting = self.books.pending.get(j, [])
        for i, r in enumerate(waiting):
            if r.a == k and np.array_equal(r.measurement, np.asarray(p_cam, float).reshape(3)):
                del waiting[i]
                return True
        return False

    def _guess(self, observations: list[FactorRecord]) -> np.ndarray:
        """A landmark's initial position: the mean of its observations placed with the current pose estimates."""
        poses = [self.pose(r.a) for r in observations]
        return np.mean([T[:3, :3] @ r.measurement + T[:3, 3] for T, r in zip(poses, observations, strict=True)], axis=0)

    def _insert_landmark(self, j: int, prior: FactorRecord) -> None:
        """Put a landmark with a prior into iSAM2, with any observations held back for it."""
        observations = self.books.pending.pop(j)
        try:
            self.update([prior, *observations], landmarks=[(j, prior.measurement)])
        except SolverError:
            self.books.pending[j] = observations
            raise

    def landmarks_in_solver(self) -> set[int]:
        """Ids of the landmarks that are in the solver now."""
        return set(self.books.landmarks)

    def landmark_factor_indices(self, landmarks: set[int]) -> dict[tuple[int, int, bytes], int]:
        """Factor index of each live measurement of these landmarks, by (landmark, keyframe, measurement bytes)."""
        removed = self.books.removed
        return {
            (f.b, f.a, f.measurement.tobytes()): i
            for i, f in enumerate(self.books.factors)
            if f.kind == FactorKind.LANDMARK and f.b is not None and f.b in landmarks and i not in removed
        }

    @property
    def num_landmarks(self) -> int:
        """Landmarks in the solver (declared ones still waiting to be observable are not counted)."""
        return len(self.books.landmarks)
