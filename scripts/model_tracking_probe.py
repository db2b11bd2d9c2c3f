"""Hand-run probe (issue 4): KinectFusion-style frame-to-model depth tracking on 7-Scenes, odometry only.

Every frame's depth is registered by point-to-plane ICP (OpenCV 5 ``cv2.Odometry``, DEPTH) against the
raycast of a TSDF surface model (``cv2.Volume``, HashTSDF) built from the frames before it, then
integrated at the tracked pose: the method that made the ground truth of this data. With ``--predict RUN``
the raycast is taken at the pose predicted by the run's own frame-to-frame odometry (``RUN/odometry.tum``,
ORB + PnP), and an ICP correction larger than ``--gate-m`` / ``--gate-deg`` is refused (the predicted pose
is kept). ``--out DIR`` writes the poses as ``DIR/odometry.txt``, the external-odometry file of a dataset
directory, so that ``objslam run DIR`` puts them through the service's graph with its loops and landmarks.
``--compare RUN`` compares the probe, the run's odometry and the ground truth over 25-frame windows: where
two independent odometries agree with each other and not with the ground truth, the ground truth is off.

    python scripts/model_tracking_probe.py [--frames N] [--voxel M] [--stride S] [--predict RUN]
        [--gate-m M] [--gate-deg D] [--model-frames N] [--out DIR] [--compare RUN] [--depth-scale U]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from evaluation.trajectory_metrics import trajectory_error
from graph.geometry import motion_magnitude, relative
from service.outputs import tum_text
from sources import Trajectory, open_dataset
from sources.tum import read_trajectory

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "7scenes_redkitchen_1000"


class SurfaceModelTracker:
    """A TSDF volume and an ICP odometry on the depth camera (``stride`` subsamples the depth image)."""

    def __init__(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        voxel_m: float,
        stride: int,
        depth_scale: float,
        max_depth_m: float = 4.0,
        model_frames: int = 0,
    ):
        self.stride, self.model_frames, self.frames = stride, model_frames, 0
        K = np.array([[fx / stride, 0, cx / stride], [0, fy / stride, cy / stride], [0, 0, 1]], np.float32)
        settings = cv2.VolumeSettings(cv2.VolumeType_HashTSDF)
        settings.setVoxelSize(voxel_m)
        settings.setTsdfTruncateDistance(4 * voxel_m)
        settings.setMaxWeight(64)
        settings.setRaycastStepFactor(0.25)
        settings.setDepthFactor(depth_scale)
        settings.setMaxDepth(max_depth_m)
        for set_width in (settings.setIntegrateWidth, settings.setRaycastWidth):
            set_width(width // stride)
        for set_height in (settings.setIntegrateHeight, settings.setRaycastHeight):
            set_height(height // stride)
        settings.setCameraIntegrateIntrinsics(K)
        settings.setCameraRaycastIntrinsics(K)
        # With ``model_frames``, two volumes reset in turn every 2 x model_frames frames, half a period apart;
        # tracking uses the older one, so the model holds the last model_frames .. 2 x model_frames frames only
        # (no surfaces of an earlier pass, which carry that pass's drift).
        self.volumes = [cv2.Volume(cv2.VolumeType_HashTSDF, settings) for _ in range(2 if model_frames else 1)]
        odometry_settings = cv2.OdometrySettings()
        odometry_settings.setCameraMatrix(K)
        odometry_settings.setMaxDepth(max_depth_m)
        self.odometry = cv2.Odometry(cv2.OdometryType_DEPTH, odometry_settings, cv2.OdometryAlgoType_COMMON)
        self.depth_scale = depth_scale
        self.seconds = np.zeros(3)  # raycast, ICP, integration

    def depth(self, raw: np.ndarray) -> np.ndarray:
        """Raw depth units as float32, invalid (0 or 65535) as 0, subsampled by ``stride``."""
        sub = raw[:: self.stride, :: self.stride]
        return np.ascontiguousarray(np.where((sub == 0) | (sub == 65535), 0, sub).astype(np.float32))

    def correction(self, depth: np.ndarray, predicted: np.ndarray) -> np.ndarray | None:
        """``T_pred_cur`` aligning ``depth`` with the model seen from ``predicted``, or None if ICP fails."""
        t0 = time.perf_counter()
        points, _ = self._tracked().raycast(predicted.astype(np.float32))
        model = np.nan_to_num(points[..., 2], nan=0.0).astype(np.float32)
        t1 = time.perf_counter()
        ok, Rt = self.odometry.compute(depth / self.depth_scale, model)
        self.seconds += [t1 - t0, time.perf_counter() - t1, 0.0]
        return Rt if ok else None

    def _tracked(self):
        if not self.model_frames:
            return self.volumes[0]
        phase = [(self.frames + i * self.model_frames) % (2 * self.model_frames) for i in range(2)]
        return self.volumes[int(np.argmax(phase))]

    def integrate(self, depth: np.ndarray, pose: np.ndarray) -> None:
        t0 = time.perf_counter()
        for i, volume in enumerate(self.volumes):
            if (
                self.model_frames
                and self.frames >= i * self.model_frames
                and (self.frames - i * self.model_frames) % (2 * self.model_frames) == 0
            ):
                volume.reset()
            volume.integrate(depth, pose.astype(np.float32))
        self.frames += 1
        self.seconds[2] += time.perf_counter() - t0


def window_disagreement(a: np.ndarray, b: np.ndarray, start: int, stop: int) -> tuple[float, float]:
    """How far two trajectories' motions from frame ``start`` to ``stop`` differ: (mm, deg)."""
    t, r = motion_magnitude(relative(relative(a[start], a[stop]), relative(b[start], b[stop])))
    return 1000 * t, math.degrees(r)


def compare(probe: np.ndarray, odometry: np.ndarray, truth: np.ndarray, window: int = 25) -> None:
    """Print the median disagreement of each pair over ``window``-frame windows, and the windows where both
    odometries are over 4 cm from the ground truth."""
    pairs = {"probe-truth": (probe, truth), "run-truth": (odometry, truth), "probe-run": (probe, odometry)}
    starts = range(0, len(probe) - window, window)
    table = {
        name: np.array([window_disagreement(a, b, s, s + window) for s in starts]) for name, (a, b) in pairs.items()
    }
    print(
        ", ".join(
            f"{name} median {np.median(v[:, 0]):.0f} mm / {np.median(v[:, 1]):.2f} deg" for name, v in table.items()
        )
    )
    for i, s in enumerate(starts):
        if table["probe-truth"][i, 0] > 40 and table["run-truth"][i, 0] > 40:
            print(
                f"  frames {s}-{s + window}: "
                + ", ".join(f"{name} {v[i, 0]:.0f} mm / {v[i, 1]:.1f} deg" for name, v in table.items())
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--voxel", type=float, default=0.01)
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--predict", type=Path, help="run directory whose odometry.tum predicts each frame")
    parser.add_argument("--gate-m", type=float, default=math.inf)
    parser.add_argument("--gate-deg", type=float, default=math.inf)
    parser.add_argument("--model-frames", type=int, default=0, help="keep only the last N..2N frames in the model")
    parser.add_argument("--out", type=Path, help="dataset directory to write odometry.txt into")
    parser.add_argument("--compare", type=Path, help="run directory whose odometry.tum to compare over windows")
    parser.add_argument("--depth-scale", type=float, help="depth units per metre (objslam calibrate depth-scale)")
    args = parser.parse_args()

    dataset = open_dataset(str(args.data), {"depth_scale": args.depth_scale} if args.depth_scale else None)
    camera = dataset.frame(0).camera
    k = camera.depth
    tracker = SurfaceModelTracker(
        k.fx,
        k.fy,
        k.cx,
        k.cy,
        camera.width,
        camera.height,
        args.voxel,
        args.stride,
        camera.depth_scale,
        model_frames=args.model_frames,
    )
    prediction = read_trajectory(args.predict / "odometry.tum").poses if args.predict else None
    n = min(args.frames, len(dataset))
    pose, poses, refused, failed = np.eye(4), [np.eye(4)], 0, 0
    started = time.perf_counter()
    tracker.integrate(tracker.depth(dataset.frame(0).depth), pose)
    for i in range(1, n):
        depth = tracker.depth(dataset.frame(i).depth)
        motion = np.linalg.inv(prediction[i - 1]) @ prediction[i] if prediction is not None else np.eye(4)
        predicted = pose @ motion
        Rt = tracker.correction(depth, predicted)
        if Rt is None:
            failed += 1
            Rt = np.eye(4)
        dt, dr = motion_magnitude(Rt)
        if dt > args.gate_m or math.degrees(dr) > args.gate_deg:
            refused += 1
            Rt = np.eye(4)
        pose = predicted @ Rt
        poses.append(pose)
        tracker.integrate(depth, pose)
    seconds = time.perf_counter() - started
    truth = dataset.ground_truth.poses[:n]
    estimate = np.array(poses)
    error = trajectory_error(estimate, truth)
    ms = 1000 * tracker.seconds / max(n - 1, 1)
    print(
        f"frames {n} voxel {args.voxel} m stride {args.stride} predict {'run' if prediction is not None else 'none'}"
        f" gate {args.gate_m} m / {args.gate_deg} deg model {args.model_frames or 'all'} frames: "
        f"ATE {100 * error.ate_rmse_m:.2f} cm, "
        f"ICP refused {refused}, failed {failed}; {1000 * seconds / n:.0f} ms/frame "
        f"(raycast {ms[0]:.0f}, ICP {ms[1]:.0f}, integrate {ms[2]:.0f})"
    )
    if args.compare:
        compare(estimate, read_trajectory(args.compare / "odometry.tum").poses[:n], truth)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "odometry.txt").write_text(tum_text(Trajectory(np.asarray(dataset.timestamps[:n]), estimate)))


if __name__ == "__main__":
    main()
