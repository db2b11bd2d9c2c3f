"""``map.png``: a top-down view of the trajectory (and, later, objects and loop-closure links)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from graph.metrics import TrajectoryError  # noqa: E402
from service.sources.base import Trajectory  # noqa: E402


def ground_axes(points: np.ndarray) -> np.ndarray:
    """Two unit vectors spanning the trajectory's dominant plane (the ground plane for handheld motion)."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[:2]


def plot_map(path: Path, trajectory: Trajectory, odometry: Trajectory, gt: Trajectory | None,
             error: TrajectoryError | None) -> None:
    """Draw optimised trajectory, odometry and (aligned) ground truth projected on the ground plane."""
    fig, ax = plt.subplots(figsize=(7, 7), dpi=110)
    if len(trajectory):
        pts = trajectory.poses[:, :3, 3]
        axes = ground_axes(pts) if len(pts) >= 3 else np.eye(3)[:2]
        if gt is not None and error is not None:
            g = gt.poses[:, :3, 3]
            inv = np.linalg.inv(error.alignment)
            g_est = (inv[:3, :3] @ g.T + inv[:3, 3:4]).T
            ax.plot(*(g_est @ axes.T).T, color="0.6", lw=1.5, label="ground truth (aligned)")
        ax.plot(*(odometry.poses[:, :3, 3] @ axes.T).T, color="tab:orange", lw=1, ls="--", label="odometry")
        ax.plot(*(pts @ axes.T).T, color="tab:blue", lw=1.5, label="optimised")
        ax.scatter(*(pts[:1] @ axes.T).T, color="green", zorder=5, label="start")
    title = "objslam map (top-down)"
    if error is not None:
        title += f"  ATE RMSE {error.ate_rmse_m * 100:.2f} cm"
    ax.set_title(title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
