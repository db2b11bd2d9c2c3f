"""ATE / RPE: Umeyama alignment recovers known transforms and agrees with evo on the same files."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluation.trajectory_metrics import trajectory_error, umeyama
from service.outputs import tum_text
from sources.base import Trajectory


def _random_trajectory(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(1, n):
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
        step[:3, 3] = rng.normal(0, 0.1, 3)
        poses[i] = poses[i - 1] @ step
    return poses


def test_umeyama_recovers_a_rigid_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.3, -1.0, 2.0]).as_matrix()
    T[:3, 3] = [1, -2, 3]
    dst = (T[:3, :3] @ src.T).T + T[:3, 3]
    np.testing.assert_allclose(umeyama(src, dst), T, atol=1e-10)


def test_ate_is_zero_for_a_rigidly_moved_copy_and_positive_with_noise():
    ref = _random_trajectory(100, 2)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 1.2).as_matrix()
    T[:3, 3] = [5, 0, 1]
    moved = T @ ref
    assert trajectory_error(moved, ref).ate_rmse_m < 1e-10
    noisy = moved.copy()
    noisy[:, :3, 3] += np.random.default_rng(3).normal(0, 0.01, (100, 3))
    err = trajectory_error(noisy, ref)
    assert 0.01 < err.ate_rmse_m < 0.025 and err.rpe_trans_rmse_m > 0.005


def test_ate_matches_evo_on_the_same_tum_files(tmp_path):
    evo_file = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics, sync

    ref = _random_trajectory(200, 4)
    est = ref.copy()
    rng = np.random.default_rng(5)
    est[:, :3, 3] += np.cumsum(rng.normal(0, 0.003, (200, 3)), axis=0)  # drift
    t = np.arange(200) * 0.1
    (tmp_path / "ref.tum").write_text(tum_text(Trajectory(t, ref)))
    (tmp_path / "est.tum").write_text(tum_text(Trajectory(t, est)))
    traj_ref = evo_file.read_tum_trajectory_file(str(tmp_path / "ref.tum"))
    traj_est = evo_file.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est)
    traj_est.align(traj_ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    ours = trajectory_error(est, ref).ate_rmse_m
    assert ours == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
