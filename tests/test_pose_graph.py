"""iSAM2 pose graph: odometry-only graphs reproduce the chained odometry; covariances grow along the chain."""

from __future__ import annotations

import numpy as np
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
