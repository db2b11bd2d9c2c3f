"""Poses appended one by one, held in one array: a log a map store copies instead of pickling pose by pose; and
the poses object observations were placed with, revised a few at a time and logged as their revisions."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from graph.row_log import RowLog


class PoseLog(RowLog):
    """4 x 4 poses, appended at the end, in one array whose capacity doubles as it fills (``graph.row_log``).
    Poses are never changed in place: a new set is a new ``PoseLog``."""

    def __init__(self, poses: Iterable[np.ndarray] | np.ndarray = ()):
        super().__init__((4, 4), float, poses)


REVISION = 17
"""A revision row: the keyframe, then its 4 x 4 pose row by row."""


class PlacedPoses:
    """Per keyframe, the pose its object observations were placed with (``slam.repose``), and the log of its
    revisions that a map store writes: a row (keyframe, pose) per appended or changed pose.

    A re-placement after an optimisation changes a few poses (those the sliding window moved: 5-260 of 4,000
    on the long run) and only after a whole-graph solve most of them; writing the whole set each time wrote
    ~128 B per keyframe at every re-placement. Only changed poses are logged; when a revision changes more than
    half of them, or the log has grown past twice their number, it starts again from the poses themselves (a
    new container, written whole): at most about twice the poses changed are written, and the log in memory
    stays within a few times the poses.
    """

    def __init__(self, poses: Iterable[np.ndarray] | np.ndarray = (), revisions: np.ndarray | None = None):
        if revisions is None:
            self._poses = PoseLog(poses)
            self._restart()
        else:
            self._poses = PoseLog(replayed(revisions))
            self._log = RowLog((REVISION,), float, revisions)

    def append(self, pose: np.ndarray) -> None:
        self._log.append(np.r_[len(self._poses), np.ravel(pose)])
        self._poses.append(pose)

    def revise(self, poses: np.ndarray) -> None:
        """Replace the poses with ``poses`` (as many), logging the ones that changed."""
        if len(poses) != len(self._poses):
            raise ValueError(f"{len(poses)} poses to revise {len(self._poses)}")
        changed = np.flatnonzero((poses != self._poses.rows()).reshape(len(poses), 16).any(axis=1))
        self._poses = PoseLog(poses)
        if 2 * len(changed) > len(poses) or len(self._log) + len(changed) > 2 * len(poses) + 64:
            self._restart()
            return
        for k in changed:
            self._log.append(np.r_[k, poses[k].ravel()])

    def _restart(self) -> None:
        rows = self._poses.rows().reshape(-1, 16)
        self._log = RowLog((REVISION,), float, np.c_[np.arange(len(rows)), rows])

    def revisions(self) -> np.ndarray:
        """The revision log, (m, 17): a read-only view of the array it is held in (``graph.row_log``)."""
        return self._log.rows()

    def rows(self) -> np.ndarray:
        return self._poses.rows()

    def __len__(self) -> int:
        return len(self._poses)

    def __getitem__(self, k: int) -> np.ndarray:
        return self._poses[k]


def replayed(revisions: np.ndarray) -> np.ndarray:
    """The poses a revision log ends with: each keyframe's last row (keyframes 0..n-1, each logged at least
    once)."""
    revisions = np.asarray(revisions, float).reshape(-1, REVISION)
    if len(revisions) == 0:
        return np.zeros((0, 4, 4))
    keyframes = revisions[:, 0].astype(np.int64)
    n = int(keyframes.max()) + 1
    last = len(keyframes) - 1 - np.unique(keyframes[::-1], return_index=True)[1]  # each keyframe's last row
    if len(last) != n:
        raise ValueError(f"pose revisions cover {len(last)} of keyframes 0-{n - 1}")
    return revisions[last, 1:].reshape(n, 4, 4)
