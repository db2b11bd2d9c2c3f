"""The pose graph as the rest of objslam uses it (SPEC 6.8): ``Graph``, a structural interface.

Implemented by ``graph.pose_graph.PoseGraph`` (the whole graph in one iSAM2) and ``graph.window.WindowedGraph``
(a bounded iSAM2 window, the whole graph solved in a child process). The pipeline, loop closure, the object
landmarks and the benchmarks are written against it; ``isinstance(graph, Graph)`` checks that the members are
there (``runtime_checkable``), mypy checks their signatures.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from graph.factors import FactorRecord


@runtime_checkable
class Graph(Protocol):
    """Keyframe poses and Point3 landmarks in an incremental graph; factors are numbered in the order added."""

    timings: list[float] | None
    """When set to a list, the seconds of each iSAM2 update of the foreground solver are appended to it."""

    @property
    def factorization(self) -> str:
        """The foreground iSAM2's factorization: CHOLESKY, or QR once Cholesky found the system indeterminant."""
        ...

    @property
    def factors(self) -> list[FactorRecord]:
        """Every factor as a record, removed ones included (index = factor index)."""
        ...

    @property
    def num_keyframes(self) -> int: ...

    @property
    def num_factors(self) -> int:
        """Factors in the graph (removed ones not counted)."""
        ...

    @property
    def num_landmarks(self) -> int:
        """Landmarks in the solver (declared ones still waiting to be observable are not counted)."""
        ...

    @property
    def updates(self) -> int:
        """Successful updates so far (changes whenever the estimate may have)."""
        ...

    # keyframes

    def add_first(self, pose: np.ndarray) -> int:
        """Anchor keyframe 0 at ``pose`` (camera-to-world) with a tight prior; returns 0."""
        ...

    def add_keyframe(self, relative: np.ndarray, sigma_m: float | None = None, sigma_deg: float | None = None) -> int:
        """Append a keyframe linked to the previous one by an odometry factor; returns its id."""
        ...

    def add_keyframe_from(
        self, k_a: int, relative: np.ndarray, sigma_m: float | None = None, sigma_deg: float | None = None
    ) -> int:
        """Append a keyframe linked to keyframe ``k_a`` by a measured relative pose; returns its id."""
        ...

    def add_segment(self, pose: np.ndarray, sigma_m: float, sigma_deg: float) -> tuple[int, int]:
        """Append the first keyframe of a new map segment (a weak gauge prior); its id and the prior's index."""
        ...

    def add_between(self, k_a: int, k_b: int, T_a_b: np.ndarray, sigma_m: float, sigma_deg: float) -> int:
        """An extra Gaussian between-factor of existing keyframes; returns its factor index."""
        ...

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
        """A loop-closure between-factor under a Huber kernel, then convergence steps; returns its factor index."""
        ...

    def remove_factors(self, indices: list[int]) -> None:
        """Retract factors by index (e.g. a loop closure found inconsistent)."""
        ...

    def pose(self, k: int) -> np.ndarray:
        """Current estimate of keyframe ``k`` (camera-to-world 4x4)."""
        ...

    def poses(self) -> np.ndarray:
        """All keyframe estimates, (K, 4, 4)."""
        ...

    def marginal_covariance(self, k: int) -> np.ndarray:
        """6x6 marginal covariance (rotation, translation) of keyframe ``k``."""
        ...

    # landmarks

    def add_landmark(self, j: int, position: np.ndarray | None = None, sigma_m: float = 1.0) -> bool:
        """Declare landmark ``j`` (with a world ``position``: a prior); whether it is in the solver now."""
        ...

    def add_landmark_observation(
        self, j: int, k: int, p_cam: np.ndarray, sigma_m: float, huber_k: float | None = None
    ) -> int | None:
        """A camera-frame measurement of landmark ``j`` from keyframe ``k``; its factor index, None while waiting."""
        ...

    def add_landmark_observations(
        self, k: int, observations: list[tuple[int, np.ndarray]], sigma_m: float, huber_k: float | None = None
    ) -> list[int | None]:
        """Several landmarks seen from keyframe ``k`` in one update."""
        ...

    def add_landmark_measurements(
        self,
        items: Sequence[tuple[int, int, np.ndarray]],
        sigma_m: float | Sequence[float],
        huber_k: float | None = None,
        range_sigma_m: float | Sequence[float] | None = None,
    ) -> list[int | None]:
        """Landmark measurements ``(k, j, p_cam)`` from any keyframes in one update."""
        ...

    def withdraw_waiting(self, j: int, k: int, p_cam: np.ndarray) -> bool:
        """Take back a measurement of landmark ``j`` that still waits for it to be observable; True if found."""
        ...

    def landmarks_in_solver(self) -> set[int]:
        """Ids of the landmarks in the solver now."""
        ...

    def landmark_factor_indices(self, landmarks: set[int]) -> dict[tuple[int, int, bytes], int]:
        """Factor index of each live measurement of these landmarks, by (landmark, keyframe, measurement bytes)."""
        ...

    def landmark(self, j: int) -> np.ndarray:
        """Current estimate of landmark ``j`` (world position)."""
        ...

    def landmarks(self) -> dict[int, np.ndarray]:
        """All landmark estimates by id."""
        ...

    # the graph as a whole

    def flush(self, timeout: float = 600.0) -> None:
        """Bring the estimate up to date with any work running in the background (e.g. before final outputs)."""
        ...

    def polish(self) -> bool:
        """Without blocking for long (no frame is coming): move the estimate towards the batch optimum of
        everything added so far, as ``flush`` does in one go; True when the estimate moved."""
        ...

    def close(self) -> None:
        """Stop what the graph runs in the background (its child process, if any)."""
        ...

    def state(self) -> dict[str, Any]:
        """Plain data from which the implementation's ``from_state`` rebuilds the graph exactly."""
        ...


if TYPE_CHECKING:  # mypy checks here that both graphs implement the interface
    from graph.pose_graph import PoseGraph
    from graph.window import WindowedGraph

    _IMPLEMENTATIONS: tuple[type[Graph], ...] = (PoseGraph, WindowedGraph)
