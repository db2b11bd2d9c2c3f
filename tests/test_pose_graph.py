"""iSAM2 pose graph: odometry-only graphs reproduce the chained odometry; covariances grow along the chain."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from graph.pose_graph import PoseGraph


def _step(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 0.05, 3)
    return T


def test_odometry_chain_is_reproduced_exactly():
    rng = np.random.default_rng(0)
    start = np.eye(4)
    start[:3, 3] = [1.0, 2.0, 0.5]
    g = PoseGraph()
    g.add_first(start)
    chain = [start]
    for _ in range(300):
        rel = _step(rng)
        g.add_keyframe(rel)
        chain.append(chain[-1] @ rel)
    assert g.num_keyframes == 301 and g.num_factors == 301
    np.testing.assert_allclose(g.poses(), np.stack(chain), atol=1e-9)
    np.testing.assert_allclose(g.pose(150), chain[150], atol=1e-9)


def test_marginal_covariance_grows_with_distance_from_the_prior():
    rng = np.random.default_rng(1)
    g = PoseGraph()
    g.add_first(np.eye(4))
    for _ in range(50):
        g.add_keyframe(_step(rng))
    c1, c50 = g.marginal_covariance(1), g.marginal_covariance(50)
    assert c1.shape == (6, 6)
    assert np.trace(c50[3:, 3:]) > 10 * np.trace(c1[3:, 3:])


def test_loop_closure_pulls_a_drifted_chain_back_and_can_be_retracted():
    true = [np.eye(4)]
    for i in range(1, 41):  # a square loop of 40 keyframes returning to the start
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 2 * np.pi * i / 40).as_matrix()
        T[:3, 3] = [np.cos(2 * np.pi * i / 40) - 1, np.sin(2 * np.pi * i / 40), 0.0]
        true.append(T)
    g = PoseGraph()
    g.add_first(true[0])
    drift = np.eye(4)
    drift[:3, :3] = Rotation.from_euler("z", 0.01).as_matrix()
    for a, b in zip(true[:-1], true[1:]):
        g.add_keyframe(np.linalg.inv(a) @ b @ drift)
    before = np.linalg.norm(g.pose(40)[:3, 3] - true[40][:3, 3])
    index = g.add_loop(0, 40, np.linalg.inv(true[0]) @ true[40], 0.01, 0.5)
    after = np.linalg.norm(g.pose(40)[:3, 3] - true[40][:3, 3])
    assert before > 0.1 and after < 0.02
    g.remove_factors([index])
    assert np.linalg.norm(g.pose(40)[:3, 3] - true[40][:3, 3]) == pytest.approx(before, rel=0.05)
