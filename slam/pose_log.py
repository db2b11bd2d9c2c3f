"""Poses appended one by one, held in one array: a log a map store copies instead of pickling pose by pose."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from graph.row_log import RowLog


class PoseLog(RowLog):
    """4 x 4 poses, appended at the end, in one array whose capacity doubles as it fills (``graph.row_log``).
    Poses are never changed in place: a new set is a new ``PoseLog``."""

    def __init__(self, poses: Iterable[np.ndarray] | np.ndarray = ()):
        super().__init__((4, 4), float, poses)
