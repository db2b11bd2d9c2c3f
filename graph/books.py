"""What every graph keeps, and what its halves (``graph.keyframes``, ``graph.landmarks``) need of it, declared.

``Books``: the records of a graph's successful updates (factors, guesses, the update log, which landmarks are
in the solver, which observations wait, which factors were removed), all that ``state()`` saves and a replay
needs. ``GraphBase``: a graph's books, its settings, its one update primitive and its keyframe estimates, the
members the mixins are written against (``PoseGraph`` and ``WindowedGraph`` implement them).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from graph.factors import FactorRecord, to_columns
from graph.settings import GraphSettings

log = logging.getLogger(__name__)

LogEntry = tuple[int, int, tuple[int, ...], tuple[int, ...]]
"""One successful update in the log: new factors, new keyframes, removed factor indices, new landmark ids."""


@dataclass(frozen=True)
class UpdateResult:
    """What one update added: the factor index of each of its new factors, in the order given."""

    factor_indices: tuple[int, ...]


@dataclass
class Books:
    """The books of a graph's successful updates (factor index = position in ``factors``)."""

    factors: list[FactorRecord] = field(default_factory=list)
    initial: list[np.ndarray] = field(default_factory=list)  # keyframe pose guesses in insertion order
    landmark_initial: list[np.ndarray] = field(default_factory=list)  # landmark position guesses, insertion order
    log: list[LogEntry] = field(default_factory=list)
    landmarks: dict[int, int] = field(default_factory=dict)  # landmark id in the solver -> insertion order
    pending: dict[int, list[FactorRecord]] = field(default_factory=dict)  # declared, not observable yet -> its
    # held-back observations
    removed: set[int] = field(default_factory=set)  # factor indices removed from the solver
    num_keyframes: int = 0
    num_factors: int = 0  # live factors
    updates: int = 0

    def record(
        self,
        factors: Sequence[FactorRecord],
        poses: Sequence[np.ndarray],
        landmarks: Sequence[tuple[int, np.ndarray]],
        remove: Sequence[int],
    ) -> None:
        """The books of a successful update: records, guesses, the log, counters. (Landmarks left without
        factors by ``remove`` are the graph's to find: ``lose_landmark``.)"""
        self.factors.extend(factors)
        self.initial.extend(np.asarray(p, float) for p in poses)
        for j, position in landmarks:
            self.landmarks[j] = len(self.landmark_initial)
            self.landmark_initial.append(np.asarray(position, float))
        self.log.append((len(factors), len(poses), tuple(remove), tuple(j for j, _ in landmarks)))
        self.removed.update(remove)
        self.updates += 1
        self.num_factors += len(factors) - len(remove)
        self.num_keyframes += len(poses)

    def lose_landmark(self, j: int) -> None:
        """Landmark ``j`` lost its last factor (iSAM2 dropped its variable): it waits to be observable again."""
        del self.landmarks[j]
        self.pending[j] = []
        log.info("landmark %d lost its last factor: out of the solver until observable again", j)

    def copy(self) -> Books:
        """Books with containers of their own (the records and arrays in them shared)."""
        return replace(
            self,
            factors=list(self.factors),
            initial=list(self.initial),
            landmark_initial=list(self.landmark_initial),
            log=list(self.log),
            landmarks=dict(self.landmarks),
            pending={j: list(observations) for j, observations in self.pending.items()},
            removed=set(self.removed),
        )

    def columns(self) -> dict[str, Any]:
        """The replay log's fields of a graph's state: ``factors`` in columns (removed ones included), the
        initial guesses of keyframes and landmarks in insertion order, the update log, and the landmarks still
        waiting to be observable with their held-back observations (``joined_columns`` of ``parts``)."""
        return joined_columns(*self.parts())

    def parts(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """``columns()`` in two parts: the observations still waiting, and the append-only logs (live, not
        copied): the factor records, the guesses and the update log."""
        pending = [r for observations in self.pending.values() for r in observations]
        small = {"pending_landmarks": np.array(list(self.pending), np.int64), "pending": to_columns(pending)}
        logs = {"factors": self.factors, "initial": self.initial, "landmark_initial": self.landmark_initial}
        return small, {**logs, "updates": self.log}


def joined_columns(small: dict[str, Any], logs: dict[str, Any], records: bool = False) -> dict[str, Any]:
    """``Books.columns()`` of its parts (logs as any sequences); ``records``: the factors as the list of records
    they are (``from_columns`` takes either), not turned into columns only to be turned back."""
    return {
        **small,
        "factors": list(logs["factors"]) if records else to_columns(list(logs["factors"])),
        "initial": np.array(list(logs["initial"]), float).reshape(-1, 4, 4),
        "landmark_initial": np.array(list(logs["landmark_initial"]), float).reshape(-1, 3),
        "updates": list(logs["updates"]),
    }


class GraphBase(ABC):
    """What the keyframe and landmark halves of a graph use: its books and settings, the update primitive and
    the keyframe estimates; and the counters every graph reports."""

    books: Books
    settings: GraphSettings

    @abstractmethod
    def update(
        self,
        factors: Sequence[FactorRecord],
        poses: Sequence[np.ndarray] = (),
        landmarks: Sequence[tuple[int, np.ndarray]] = (),
        remove: Sequence[int] | None = None,
    ) -> UpdateResult:
        """One update of the solver: new factors (keyframe ids of the whole graph), guesses of the next keyframes
        and of new landmarks, factor indices to remove. Recorded in the books on success; SolverError when the
        solver rejects it (the graph then as before it)."""

    @abstractmethod
    def pose(self, k: int) -> np.ndarray:
        """Current estimate of keyframe ``k`` (camera-to-world 4x4)."""

    @property
    def factors(self) -> list[FactorRecord]:
        """Every factor as a record, removed ones included (index = factor index)."""
        return self.books.factors

    @property
    def num_keyframes(self) -> int:
        return self.books.num_keyframes

    @property
    def num_factors(self) -> int:
        """Factors in the solver (removed ones not counted)."""
        return self.books.num_factors

    @property
    def updates(self) -> int:
        """Successful updates so far."""
        return self.books.updates
