"""The messages between the window (``graph.solver_proxy``) and the whole-graph child (``graph.solver_child``).

They go over a socket pair as pickles (``multiprocessing.connection.Connection``), in order. To the child:
``Replay`` first (the history so far), then ``Update`` for each update of the window, ``Solve`` when the
window asks for an estimate, ``Stop`` at the end. From the child: ``Solution``, one per answered ``Solve``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.books import LogEntry
from graph.factors import FactorRecord
from graph.settings import GraphSettings


@dataclass(frozen=True)
class Replay:
    """The whole history so far (a graph's books), replayed by a new child before anything else."""

    settings: GraphSettings
    factors: list[FactorRecord]
    initial: list[np.ndarray]
    landmark_initial: list[np.ndarray]
    log: list[LogEntry]


@dataclass(frozen=True)
class Update:
    """One update of the window, in the whole graph's keyframe ids and factor indices: its new factors (numbered
    from ``first``), keyframe guesses, new landmarks with their guesses, factor indices removed."""

    factors: list[FactorRecord]
    poses: list[np.ndarray]
    landmarks: list[tuple[int, np.ndarray]]
    remove: list[int]
    first: int


@dataclass(frozen=True)
class Solve:
    """Request ``token`` (1, 2, ...): an estimate of everything sent so far; ``exact``: the batch optimum."""

    token: int
    exact: bool


@dataclass(frozen=True)
class Stop:
    """The end: the child exits."""


@dataclass(frozen=True)
class Solution:
    """The answer to request ``token`` (and to any earlier one still open): keyframe poses (K, 4, 4) and
    landmark positions by id."""

    token: int
    poses: np.ndarray
    landmarks: dict[int, np.ndarray]


ToChild = Replay | Update | Solve | Stop
