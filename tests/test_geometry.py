"""Rigid-transform arithmetic (graph/geometry.py): the batch form agrees with the one-at-a-time form."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from graph.geometry import disagreements, motion_magnitude, relative


def _poses(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=scale, size=(n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(scale=3.0, size=(n, 3))
    return T


def test_disagreements_of_many_loops_at_once_are_each_loops_own():
    rng = np.random.default_rng(2)
    T_a, T_b = _poses(rng, 200, 2.0), _poses(rng, 200, 2.0)
    measured = np.stack([relative(a, b) for a, b in zip(T_a, T_b, strict=True)]) @ _poses(rng, 200, 0.05)
    measured[:, :3, 3] += rng.normal(scale=0.1, size=(200, 3))
    dt, dr = disagreements(T_a, T_b, measured)
    expected = np.array(
        [motion_magnitude(relative(relative(a, b), m)) for a, b, m in zip(T_a, T_b, measured, strict=True)]
    )
    np.testing.assert_allclose(dt, expected[:, 0], atol=1e-9)
    np.testing.assert_allclose(dr, expected[:, 1], atol=1e-6)
    assert dr.max() > 0.05 and dt.max() > 0.1  # the measurements do disagree, some by much
