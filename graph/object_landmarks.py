"""Objects as Point3 landmarks of the pose graph (SPEC 6.8, Sec. 2.4.7): which measurement is whose.

Each stable object (a cluster pooling at least ``landmark_min_support`` feature vectors) is the landmark
``L(object id)``. Every keyframe observation of a track (the centroid of its depth points in the keyframe's
pose frame) measures the landmark of the object that holds the track. Measurements of tracks that belong to
no stable object yet are kept, and enter the graph once a re-clustering puts their track into one. When a
re-clustering moves a track to another object (clusters merged or split) or drops its object, its
measurements are retracted (``removeFactorIndices``, or withdrawn while their landmark still waits to be
observable) and re-added under the new landmark. The graph itself holds a landmark back until it is
observable, so no IndeterminantLinearSystemException reaches the service.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from graph.errors import SolverError
from graph.interface import Graph
from graph.row_log import RowLog

log = logging.getLogger(__name__)

Key = tuple[int, int]  # (keyframe, track id)


class LandmarkSettings(BaseModel):
    """How objects enter the graph (fields of the ``objects`` settings section)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    landmark_sigma_m: float = Field(
        0.1,
        gt=0,
        description="sigma of an object centroid measurement (m): the visible surface's centroid moves "
        "with the viewpoint",
    )
    landmark_huber_k: float | None = Field(
        1.345,
        gt=0,
        description="Huber kernel of object measurements; null = none (a wrong association must not "
        "bend the trajectory)",
    )
    landmark_min_support: int = Field(5, ge=1, description="feature vectors an object needs to become a landmark")
    landmark_extent_scale: float = Field(
        1.0, ge=0, description="a measurement's sigma is at least this times the largest std of the object's points"
    )
    landmark_range_scale: float = Field(
        3.0,
        ge=1,
        description="sigma along the viewing ray = this times the sigma across it: the visible surface's "
        "centroid lies short of the object's",
    )


class ObjectLandmarks:
    """Keeps the graph's object landmarks in step with the clustering."""

    def __init__(self, graph: Graph, config: LandmarkSettings | None = None):
        self.graph, self.config = graph, config or LandmarkSettings()
        self.measurements: dict[Key, np.ndarray] = {}  # (x, y, z, sigma)
        self.assigned: dict[Key, tuple[int, int | None]] = {}  # -> (landmark, factor index; None while waiting)
        self.journal = _journal()  # every change of ``assigned`` (``_assign``): what a store writes of it
        self.track_landmark: dict[int, int] = {}
        self.failures = 0

    def _assign(self, key: Key, j: int, i: int | None) -> None:
        self.assigned[key] = (j, i)
        self.journal.append((key[0], key[1], j, -1 if i is None else i))

    def _unassign(self, key: Key) -> tuple[int, int | None]:
        self.journal.append((key[0], key[1], UNASSIGNED, -1))
        return self.assigned.pop(key)

    def _compact(self) -> None:
        """Start the journal again from the assignments once it holds more changes than twice their number (a
        store writes the new journal whole: amortised, a constant cost per change)."""
        if len(self.journal) > 2 * len(self.assigned) + COMPACT_SLACK:
            self.journal = _journal(self.assigned)

    def observe(self, k: int, observations: Iterable[tuple[int, np.ndarray, float]]) -> int:
        """Keyframe ``k``'s measurements ``(track id, p, extent)``: the centroid ``p`` in the keyframe's pose
        frame and the largest std of the points (m). Those of mapped tracks go into the graph now.

        Returns how many entered the graph (or wait there for their landmark to become observable).
        """
        items = []
        for track, p, extent in observations:
            p = np.asarray(p, float).reshape(3)
            if not np.all(np.isfinite(p)) or np.linalg.norm(p) < 1e-3 or not np.isfinite(extent):
                continue
            sigma = max(self.config.landmark_sigma_m, self.config.landmark_extent_scale * float(extent))
            self.measurements[(k, track)] = np.r_[p, sigma]
            if track in self.track_landmark:
                items.append(((k, track), self.track_landmark[track]))
        return self._add(items)

    def sync(self, objects: Sequence[Any], retired: Iterable[int] = ()) -> tuple[int, int]:
        """Follow a re-clustering (objects with ``id``, ``tracks``, ``n_observations``): retract the measurements
        whose track changed object, add the newly mapped ones. ``retired``: tracks the re-clustering retired
        into their object's anchor (``perception.track_retirement``): their measurements stay where they are
        for good, and are no longer followed (so the assignments kept stay bounded).

        Returns (added, retracted) measurement counts.
        """
        if gone := set(retired):
            for key in [key for key in self.assigned if key[1] in gone]:
                self._unassign(key)  # the journal forgets it; its factor stays in the graph
        mapping = {t: o.id for o in objects if o.n_observations >= self.config.landmark_min_support for t in o.tracks}
        stale = [key for key, (j, _) in self.assigned.items() if mapping.get(key[1]) != j]
        self._retract(stale)
        self.track_landmark = mapping
        missing = [
            (key, mapping[key[1]]) for key in self.measurements if key[1] in mapping and key not in self.assigned
        ]
        return self._add(missing), len(stale)

    def positions(self) -> dict[int, np.ndarray]:
        """Landmark estimates (world) of the objects that are in the solver, by object id."""
        return self.graph.landmarks()

    def _add(self, items: list[tuple[Key, int]]) -> int:
        if not items:
            return 0
        for j in {j for _, j in items}:
            self.graph.add_landmark(j)  # declares it; a no-op for a landmark the graph already knows
        waiting = {j for _, j in items} - self.graph.landmarks_in_solver()
        try:
            m = [self.measurements[key] for key, _ in items]
            indices = self.graph.add_landmark_measurements(
                [(k, j, x[:3]) for ((k, _), j), x in zip(items, m, strict=True)],
                [x[3] for x in m],
                self.config.landmark_huber_k,
                [self.config.landmark_range_scale * x[3] for x in m],
            )
        except SolverError as exc:
            self.failures += 1
            log.error("object landmark measurements rejected by the solver (%d items): %s", len(items), exc)
            return 0
        for (key, j), i in zip(items, indices, strict=True):
            self._assign(key, j, i)
        self._resolve(waiting & self.graph.landmarks_in_solver())
        self._compact()
        return len(items)

    def _resolve(self, entered: set[int]) -> None:
        """Factor indices of held-back measurements whose landmark has just entered the solver."""
        if not entered:
            return
        found = self.graph.landmark_factor_indices(entered)
        for key, (j, i) in list(self.assigned.items()):
            if i is None and j in entered:
                self._assign(key, j, found.get((j, key[0], self.measurements[key][:3].tobytes())))

    def _retract(self, keys: list[Key]) -> None:
        indices = []
        for key in keys:
            j, i = self._unassign(key)
            if i is None:
                self.graph.withdraw_waiting(j, key[0], self.measurements[key][:3])
            else:
                indices.append(i)
        if indices:
            try:
                self.graph.remove_factors(indices)
            except SolverError as exc:
                self.failures += 1
                log.error("retracting %d object landmark measurements failed: %s", len(indices), exc)
        self._compact()

    def state(self) -> dict:
        small, logs = self.parts()
        return {**small, **logs}

    def parts(self) -> tuple[dict, dict]:
        """``state()`` in two parts: the small one, and two append-only logs (live): the measurements (one per
        keyframe and track) and the journal of the assignments' changes, rows (keyframe, track, landmark or
        ``UNASSIGNED``, factor index or -1) in one array. A checkpoint writes the changes since the last one,
        not the assignments, which grow with the map (stored whole, they were most of a checkpoint's bytes)."""
        return {"track_landmark": self.track_landmark, "failures": self.failures}, {
            "measurements": self.measurements,
            "journal": self.journal.rows(),
        }

    def restore(self, state: dict) -> None:
        self.measurements = state["measurements"]
        if state.get("journal") is not None:
            self.assigned = replayed(state["journal"])
            self.journal = _journal(rows=state["journal"])
        else:  # saved before 2026-12-04: the assignments themselves
            self.assigned = _assignments(state["assigned"])
            self.journal = _journal(self.assigned)
        self.track_landmark = state["track_landmark"]
        self.failures = state["failures"]


UNASSIGNED = -1
"""The landmark of a journal row that takes an assignment back."""
COMPACT_SLACK = 1024
"""Journal rows beyond twice the assignments before it is started again from them."""


def _journal(assigned: dict[Key, tuple[int, int | None]] | None = None, rows: np.ndarray | None = None) -> RowLog:
    """A journal of ``assigned`` (each assignment a row), or of the journal ``rows`` read back."""
    if rows is None:
        rows = np.array(
            [(k, t, j, -1 if i is None else i) for (k, t), (j, i) in (assigned or {}).items()], np.int64
        ).reshape(-1, 4)
    return RowLog((4,), np.int64, rows)


def replayed(journal: np.ndarray) -> dict[Key, tuple[int, int | None]]:
    """The assignments after the changes of ``journal`` in order."""
    assigned: dict[Key, tuple[int, int | None]] = {}
    for k, t, j, i in np.asarray(journal, np.int64).reshape(-1, 4).tolist():
        if j == UNASSIGNED:
            assigned.pop((k, t), None)
        else:
            assigned[(k, t)] = (j, None if i < 0 else i)
    return assigned


def _assignments(saved: dict | np.ndarray) -> dict[Key, tuple[int, int | None]]:
    """The assignments of a state saved before 2026-12-04: an array (keyframe, track, landmark, factor index or
    -1), or before 2026-12-03 the dict itself."""
    if isinstance(saved, dict):
        return saved
    return {(int(k), int(t)): (int(j), None if i < 0 else int(i)) for k, t, j, i in saved.tolist()}
