"""Trajectory accuracy: Umeyama SE(3) alignment, ATE and RPE (pure math, no I/O)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.geometry import inverse, rotation_angle
from graph.trajectory import Trajectory, match_timestamps


@dataclass(frozen=True)
class TrajectoryError:
    """Absolute trajectory error after alignment, and per-step relative pose error."""

    pairs: int
    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    alignment: np.ndarray


def umeyama(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 rigid transform T minimising sum ||target - T source||^2 (Umeyama 1991, no scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    T = np.eye(4)
    T[:3, :3] = U @ S @ Vt
    T[:3, 3] = mu_t - T[:3, :3] @ mu_s
    return T


def trajectory_error(est: np.ndarray, ref: np.ndarray) -> TrajectoryError:
    """ATE after SE(3) alignment of ``est`` (N,4,4) onto ``ref`` (N,4,4), and RPE between consecutive poses."""
    if len(est) < 3:
        raise ValueError(f"need at least 3 matched poses, got {len(est)}")
    T = umeyama(est[:, :3, 3], ref[:, :3, 3])
    aligned = T[:3, :3] @ est[:, :3, 3].T + T[:3, 3:4]
    err = np.linalg.norm(aligned.T - ref[:, :3, 3], axis=1)
    rel_t, rel_r = [], []
    for i in range(len(est) - 1):
        d = inverse(inverse(ref[i]) @ ref[i + 1]) @ (inverse(est[i]) @ est[i + 1])
        rel_t.append(np.linalg.norm(d[:3, 3]))
        rel_r.append(np.degrees(rotation_angle(d[:3, :3])))
    return TrajectoryError(
        pairs=len(est),
        ate_rmse_m=float(np.sqrt(np.mean(err**2))),
        ate_mean_m=float(err.mean()),
        ate_median_m=float(np.median(err)),
        ate_max_m=float(err.max()),
        rpe_trans_rmse_m=float(np.sqrt(np.mean(np.square(rel_t)))),
        rpe_rot_rmse_deg=float(np.sqrt(np.mean(np.square(rel_r)))),
        alignment=T,
    )


def evaluate(traj: Trajectory, gt: Trajectory | None) -> TrajectoryError | None:
    """ATE / RPE of ``traj`` against ground truth matched by timestamp, or None without ground truth."""
    if gt is None or len(traj) < 3:
        return None
    i_est, i_ref = match_timestamps(traj.timestamps, gt.timestamps)
    if len(i_est) < 3:
        return None
    return trajectory_error(traj.poses[i_est], gt.poses[i_ref])


def error_dict(err: TrajectoryError) -> dict[str, float]:
    return {
        "pairs": err.pairs,
        "ate_rmse_m": err.ate_rmse_m,
        "ate_mean_m": err.ate_mean_m,
        "ate_median_m": err.ate_median_m,
        "ate_max_m": err.ate_max_m,
        "rpe_trans_rmse_m": err.rpe_trans_rmse_m,
        "rpe_rot_rmse_deg": err.rpe_rot_rmse_deg,
        "alignment": np.asarray(err.alignment, float).tolist(),
    }
