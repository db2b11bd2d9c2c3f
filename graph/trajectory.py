"""Timestamped poses and the matching of timestamps between trajectories (pure, no I/O)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Trajectory:
    """Timestamped camera-to-world poses: ``timestamps`` (N,), ``poses`` (N, 4, 4)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps)


def nearest_timestamps(times_a: np.ndarray, times_b: np.ndarray, max_diff: float) -> np.ndarray:
    """For each time in ``times_a`` the index of the nearest time in ``times_b``, or -1 beyond ``max_diff``."""
    times_a, times_b = np.asarray(times_a, float), np.asarray(times_b, float)
    if len(times_b) == 0:
        return np.full(len(times_a), -1)
    order = np.argsort(times_b)
    sorted_b = times_b[order]
    pos = np.clip(np.searchsorted(sorted_b, times_a), 0, len(sorted_b) - 1)
    left = np.maximum(pos - 1, 0)
    pick = np.where(np.abs(sorted_b[left] - times_a) <= np.abs(sorted_b[pos] - times_a), left, pos)
    result = order[pick]
    result[np.abs(times_b[result] - times_a) > max_diff] = -1
    return result


def match_timestamps(t_est: np.ndarray, t_ref: np.ndarray, max_diff: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (est, ref) of nearest timestamps within ``max_diff`` seconds."""
    ref = nearest_timestamps(t_est, t_ref, max_diff)
    est = np.nonzero(ref >= 0)[0]
    return est, ref[est]
