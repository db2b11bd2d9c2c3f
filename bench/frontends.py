"""``objslam bench frontends``: the odometry candidates compared on a real segment (SPEC 6.4: measure, keep the best).

Candidates: ORB + PnP-RANSAC + LM (the default), the same with depth ICP at keyframes, and SIFT + PnP.
Each tracks the first N frames of a dataset frame to keyframe; ATE after SE(3) alignment, RPE, time.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
from rich.console import Console

from bench.report import markdown_table, record
from evaluation.trajectory_metrics import trajectory_error
from perception.frame import Frame
from perception.frontend import VisualOdometry
from perception.keyframing import KeyframeSettings
from perception.odometry import FeatureExtractor, Features, OdometrySettings
from sources import ground_truth_of, open_dataset


class SiftExtractor(FeatureExtractor):
    """SIFT keypoints and descriptors in place of ORB; the keypoints' 3D points as the ORB extractor finds them."""

    def __init__(self, orb: FeatureExtractor):
        super().__init__(orb.camera, orb.config)
        self.sift = cv2.SIFT.create(orb.config.n_features)

    def extract(self, frame: Frame) -> Features:
        kps, desc = self.sift.detectAndCompute(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY), None)
        px = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
        return Features(
            px, desc if desc is not None else np.zeros((0, 128), np.float32), self._points(px, frame.depth_m())
        )


def _sift(vo: VisualOdometry) -> None:
    """Swap the ORB extractor and Hamming matcher of ``vo`` for SIFT with an L2 matcher."""
    vo.extractor = SiftExtractor(vo.extractor)
    vo.estimator.matcher = cv2.BFMatcher(cv2.NORM_L2)


def measure(dataset: str, frames: int) -> list[list[object]]:
    """One row per candidate: name, ATE, RPE, ms/frame, tracking losses."""
    data = open_dataset(dataset)
    n = min(frames, len(data))
    images = [data.frame(i) for i in range(n)]
    gt = ground_truth_of(data).poses[:n]
    rows = []
    for name, icp, sift, tracker in (
        ("ORB + PnP-RANSAC + LM", False, False, "features"),
        ("ORB + PnP + depth ICP at keyframes", True, False, "features"),
        ("SIFT + PnP-RANSAC + LM", False, True, "features"),
        ("ORB at keyframes, optical flow + PnP between", False, False, "flow"),
        ("... and depth ICP at keyframes (the service's default)", True, False, "flow"),
    ):
        vo = VisualOdometry(data.camera, KeyframeSettings(), OdometrySettings(icp=icp, tracker=tracker))
        if sift:
            _sift(vo)
        t0 = time.perf_counter()
        poses = np.stack([vo.track(f).pose for f in images])
        ms = (time.perf_counter() - t0) / n * 1000
        err = trajectory_error(poses, gt)
        rows.append(
            [
                name,
                n,
                f"{err.ate_rmse_m * 100:.2f}",
                f"{err.rpe_trans_rmse_m * 100:.3f}",
                f"{err.rpe_rot_rmse_deg:.3f}",
                f"{ms:.1f}",
                vo.lost_count,
            ]
        )
    return rows


def run_frontends_bench(console: Console, dataset: str, frames: int, write: Path | None) -> list[list[object]]:
    rows = measure(dataset, frames)
    header = ["front end", "frames", "ATE (cm)", "RPE (cm/frame)", "RPE (deg/frame)", "ms/frame", "lost"]
    console.print(markdown_table(header, rows))
    notes = (
        "Front end alone (no graph), frame to keyframe, on the first frames of the sequence, one thread. Optical "
        "flow between keyframes (the keyframe's points followed by pyramidal LK and posed by PnP; ORB only at "
        "keyframes) is the default tracker: more accurate per frame than ORB on every frame and faster. Depth ICP "
        "halves the per-frame RPE when applied to every frame but biases keyframe-to-keyframe motion on this "
        "Kinect data; the service applies it to keyframe factors and skip edges, where it measured better once "
        "loops close (see the odometry table). The last row is the service's configuration: its frames/s = 1000 "
        "/ ms per frame (issue 28's target: >= 60)."
    )
    record(
        "frontends",
        "Odometry front-end candidates",
        f"objslam bench frontends --dataset {dataset} --frames {frames}",
        markdown_table(header, rows),
        notes,
        write,
    )
    return rows
