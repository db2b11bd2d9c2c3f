"""``map.png``: a top-down view of the trajectory (and, later, objects and loop-closure links)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from evaluation.trajectory_metrics import TrajectoryError
from graph.trajectory import Trajectory
from perception.clustering import ClusterConfig


def ground_axes(points: np.ndarray) -> np.ndarray:
    """Two unit vectors spanning the trajectory's dominant plane (the ground plane for handheld motion)."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[:2]


def plot_objects(ax, objects: list[dict], axes: np.ndarray, origin: np.ndarray) -> None:
    """Each object's ellipse (covariance projected on the ground plane, ``axis_scale`` std as objects.json's
    axes) with its label, and a cross at its iSAM2 landmark when it has one."""
    from matplotlib.patches import Ellipse

    colours = plt.get_cmap("tab10")
    for i, o in enumerate(objects):
        mean = (np.asarray(o["mean"]) - origin) @ axes.T
        cov2 = axes @ np.asarray(o["cov"]) @ axes.T
        vals, vecs = np.linalg.eigh(cov2)
        w, h = 2 * ClusterConfig().axis_scale * np.sqrt(np.clip(vals, 1e-8, None))
        angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
        ax.add_patch(Ellipse(mean, h, w, angle=angle, fill=False, lw=1.5, color=colours(i % 10)))
        ax.annotate(o["label"], mean, fontsize=7, ha="center", color=colours(i % 10))
        if o.get("landmark") is not None:  # the object's iSAM2 landmark
            mark = (np.asarray(o["landmark"]) - origin) @ axes.T
            ax.plot(*mark[:2], marker="x", ms=5, color=colours(i % 10))


def plot_map(
    path: Path,
    trajectory: Trajectory,
    odometry: Trajectory,
    gt: Trajectory | None,
    error: TrajectoryError | None,
    objects: list[dict] | None = None,
    loops: list[dict] | None = None,
) -> None:
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
        by_t = {float(t): p for t, p in zip(trajectory.timestamps, pts, strict=True)}
        for r in loops or []:
            a, b = by_t.get(float(r["match_t"])), by_t.get(float(r["query_t"]))
            if r.get("accepted") and a is not None and b is not None:
                ax.plot(*(np.stack([a, b]) @ axes.T).T, color="tab:red", lw=0.8, alpha=0.6)
        plot_objects(ax, objects or [], axes, np.zeros(3))
        ax.plot(*(pts @ axes.T).T, color="tab:blue", lw=1.5, label="optimised")
        ax.scatter(*(pts[:1] @ axes.T).T, color="green", zorder=5, label="start")
    else:  # an empty map (no frame processed, or none tied to the map) still gets its picture
        ax.text(0.5, 0.5, "no pose in the map", ha="center", va="center", transform=ax.transAxes)
    title = "objslam map (top-down)"
    if error is not None:
        title += f"  ATE RMSE {error.ate_rmse_m * 100:.2f} cm"
    ax.set_title(title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
