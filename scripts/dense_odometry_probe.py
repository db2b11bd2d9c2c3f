"""Hand-run probe (issue 4): OpenCV 5's dense ``cv2.Odometry`` as a 7-Scenes front end, odometry only.

Frames ``0, step, 2*step, ... < N`` are registered pairwise (depth registered to colour, grey image), the
relative poses chained from the ground-truth start and moved to the depth (body) frame; ATE after SE(3)
alignment against the ground truth of the same frames.

    python scripts/dense_odometry_probe.py N rgbd|rgb|depth [step]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from evaluation.trajectory_metrics import trajectory_error
from perception.registration import depth_in_color
from sources import open_dataset

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "7scenes_redkitchen_1000"
TYPES = {"rgbd": cv2.OdometryType_RGB_DEPTH, "rgb": cv2.OdometryType_RGB, "depth": cv2.OdometryType_DEPTH}


def main(n: int, mode: str, step: int) -> None:
    ds = open_dataset(str(DATA))
    camera = ds.frame(0).camera
    c = camera.color
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(c.matrix().astype(np.float32))
    odometry = cv2.Odometry(TYPES[mode], settings, cv2.OdometryAlgoType_COMMON)
    color_from_depth = camera.depth_to_color if camera.depth_to_color is not None else np.eye(4)

    def prepared(i: int) -> tuple[np.ndarray, np.ndarray]:
        frame = ds.frame(i)
        depth = depth_in_color(frame.depth.astype(np.float32) / camera.depth_scale, camera).astype(np.float32)
        return depth, cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)

    truth = ds.ground_truth.poses
    indices = list(range(0, n, step))
    pose, poses, failed, started = truth[0].copy(), [truth[0]], 0, time.perf_counter()
    previous = prepared(0)
    for i in indices[1:]:
        current = prepared(i)
        ok, Rt = odometry.compute(previous[0], previous[1], current[0], current[1])  # Rt maps previous to current
        failed += not ok
        colour_motion = np.linalg.inv(Rt) if ok else np.eye(4)
        pose = pose @ np.linalg.inv(color_from_depth) @ colour_motion @ color_from_depth
        poses.append(pose.copy())
        previous = current
    error = trajectory_error(np.array(poses), truth[indices])
    print(
        f"{mode} frames {n} step {step}: ATE {error.ate_rmse_m * 100:.2f} cm, failed {failed}, "
        f"{(time.perf_counter() - started) / len(indices):.3f} s per frame"
    )


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 1)
