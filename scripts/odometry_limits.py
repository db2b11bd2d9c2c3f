"""Where the 7-Scenes ATE comes from: loop accuracy or the odometry between loops (hand-run analysis).

    python scripts/odometry_limits.py RUN_DIR [--data ../shared/data/7scenes_redkitchen_1000]

RUN_DIR is the output of ``objslam run DATA --out RUN_DIR`` (odometry.tum, trajectory.tum, loops.json).

1. Loops: an offline pose graph of the run's frame odometry chain plus its accepted loop closures, solved
   once with the measured loop poses and once with the ground-truth relative poses of the same pairs. If
   perfect loops do not lower the ATE, the error is in the odometry between and outside the loops.
2. Depth geometry vs ground truth: point-to-plane ICP between frames i and i + gap started *at* the
   ground-truth relative pose; how far it moves away measures how well the depth images agree with the
   ground truth (the ground truth comes from KinectFusion on the same depth, not from motion capture).
3. Timing: the same ICP poses against the ground truth shifted by a fraction of a frame (a time offset
   between depth and the poses would show as a smaller error at a non-zero shift).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from evaluation.trajectory_metrics import trajectory_error
from graph.geometry import motion_magnitude, pose_from_tum, relative
from perception.icp import icp_refine
from sources import open_dataset
from sources.tum import read_trajectory


def offline_graph(odometry: np.ndarray, loops: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """Frame chain (0.3 cm / 0.1 deg per frame) plus Huber loop factors (1 cm / 0.5 deg), batch LM."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(odometry[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    chain = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[math.radians(0.1)] * 3, [0.003] * 3])
    loop = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Diagonal.Sigmas(np.r_[[math.radians(0.5)] * 3, [0.01] * 3]),
    )
    for i, pose in enumerate(odometry):
        values.insert(i, gtsam.Pose3(pose))
        if i:
            graph.add(gtsam.BetweenFactorPose3(i - 1, i, gtsam.Pose3(relative(odometry[i - 1], pose)), chain))
    for a, b, T in loops:
        graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(T), loop))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return np.array([result.atPose3(i).matrix() for i in range(len(odometry))])


def loop_accuracy(run: Path, truth: np.ndarray) -> None:
    odometry, trajectory = (read_trajectory(run / f"{name}.tum").poses for name in ("odometry", "trajectory"))
    n = len(odometry)
    accepted = [r for r in json.loads((run / "loops.json").read_text()) if r.get("accepted")]
    pairs = [(r["match_frame"], r["query_frame"], pose_from_tum(np.array(r["relative_pose"]))) for r in accepted]
    print(
        f"run: ATE odometry {100 * trajectory_error(odometry, truth[:n]).ate_rmse_m:.2f} cm, "
        f"with its graph {100 * trajectory_error(trajectory, truth[:n]).ate_rmse_m:.2f} cm, "
        f"{len(pairs)} accepted loops"
    )
    for name, loops in (
        ("measured", pairs),
        ("ground truth", [(a, b, relative(truth[a], truth[b])) for a, b, _ in pairs]),
    ):
        ate = trajectory_error(offline_graph(odometry, loops), truth[:n]).ate_rmse_m
        print(f"offline graph, {name} loop poses: ATE {100 * ate:.2f} cm")


def depth_vs_truth(data, truth: np.ndarray, gaps: tuple[int, ...] = (5, 15)) -> None:
    K = data.camera.depth
    for gap in gaps:
        pairs = [(i, i + gap) for i in range(3, len(truth) - gap - 3, 7)]
        found = {}
        for i, j in pairs:
            result = icp_refine(data.frame(j).depth_m(), data.frame(i).depth_m(), K, relative(truth[i], truth[j]))
            if result is not None:
                found[(i, j)] = result.T
        errors = np.array([motion_magnitude(relative(relative(truth[i], truth[j]), T)) for (i, j), T in found.items()])
        print(
            f"ICP from the ground truth, gap {gap}: moves {1000 * np.median(errors[:, 0]):.1f} mm / "
            f"{math.degrees(np.median(errors[:, 1])):.2f} deg (median of {len(found)} pairs)"
        )
        if gap == gaps[-1]:
            time_offsets(truth, found)


def time_offsets(truth: np.ndarray, found: dict, shifts=(-1.0, -0.5, 0.0, 0.5, 1.0)) -> None:
    slerp = Slerp(np.arange(len(truth), dtype=float), Rotation.from_matrix(truth[:, :3, :3]))

    def at(t: float) -> np.ndarray:
        i, a = int(np.floor(t)), t - np.floor(t)
        T = np.eye(4)
        T[:3, :3] = slerp([t]).as_matrix()[0]
        T[:3, 3] = (1 - a) * truth[i, :3, 3] + a * truth[min(i + 1, len(truth) - 1), :3, 3]
        return T

    for shift in shifts:
        errors = [
            motion_magnitude(relative(relative(at(i + shift), at(j + shift)), T))[0] for (i, j), T in found.items()
        ]
        print(f"  against the ground truth shifted {shift:+.1f} frames: median {1000 * np.median(errors):.1f} mm")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--data", default="../shared/data/7scenes_redkitchen_1000")
    args = parser.parse_args()
    data = open_dataset(args.data)
    truth = data.ground_truth.poses
    loop_accuracy(args.run, truth)
    depth_vs_truth(data, truth)


if __name__ == "__main__":
    main()
