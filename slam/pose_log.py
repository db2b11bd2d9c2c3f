"""Poses appended one by one, held in one array: a log a map store copies instead of pickling pose by pose."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np


class PoseLog:
    """4 x 4 poses, appended at the end, in one array whose capacity doubles as it fills.

    ``rows()`` is the poses as a view of that array: a store (``service.map_store``) writes its new rows as
    array slices, and a new array (the capacity doubled) is a new container, written whole: at most twice the
    poses over a run. Poses are never changed in place: a new set is a new ``PoseLog``.
    """

    def __init__(self, poses: Iterable[np.ndarray] | np.ndarray = ()):
        given = np.asarray(list(poses) if not isinstance(poses, np.ndarray) else poses, float).reshape(-1, 4, 4)
        self._n = len(given)
        self._buf = np.empty((max(16, 2 * self._n), 4, 4))
        self._buf[: self._n] = given

    def append(self, pose: np.ndarray) -> None:
        if self._n == len(self._buf):
            grown = np.empty((2 * len(self._buf), 4, 4))
            grown[: self._n] = self._buf
            self._buf = grown
        self._buf[self._n] = pose
        self._n += 1

    def rows(self) -> np.ndarray:
        """The poses, (n, 4, 4): a read-only view of the array they are held in."""
        view = self._buf[: self._n]
        view.flags.writeable = False
        return view

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k: int) -> np.ndarray:
        return self.rows()[k]

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter(self.rows())
