"""Rows of fixed shape appended one by one, held in one array: a log a map store copies instead of pickling
row by row (``service.map_store``)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np


class RowLog:
    """Rows of one shape and dtype, appended at the end, in one array whose capacity doubles as it fills.

    ``rows()`` is the rows as a read-only view of that array: a store writes its new rows as array slices, and a
    new array (the capacity doubled) is a new container, written whole: at most twice the rows over a run. Rows
    are never changed in place: a new set is a new log.
    """

    def __init__(self, row_shape: tuple[int, ...], dtype: type | np.dtype, rows: Iterable | np.ndarray = ()):
        self.row_shape, self.dtype = tuple(row_shape), np.dtype(dtype)
        given = np.asarray(rows if isinstance(rows, np.ndarray) else list(rows), self.dtype)
        given = given.reshape(-1, *self.row_shape)
        self._n = len(given)
        self._buf = np.empty((max(16, 2 * self._n), *self.row_shape), self.dtype)
        self._buf[: self._n] = given

    def append(self, row: Iterable | np.ndarray) -> None:
        if self._n == len(self._buf):
            grown = np.empty((2 * len(self._buf), *self.row_shape), self.dtype)
            grown[: self._n] = self._buf
            self._buf = grown
        self._buf[self._n] = row
        self._n += 1

    def rows(self) -> np.ndarray:
        """The rows, (n, *row_shape): a read-only view of the array they are held in."""
        view = self._buf[: self._n]
        view.flags.writeable = False
        return view

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k: int) -> np.ndarray:
        return self.rows()[k]

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter(self.rows())
