"""Camera-rate tracking (issue 28): optical flow between keyframes, keyframes made beside the tracking."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import cv2
import numpy as np
import pytest

from bench.live import BareCamera
from evaluation.trajectory_metrics import trajectory_error
from perception.frontend import VisualOdometry
from perception.keyframe_deferral import DeferredKeyframes
from perception.keyframe_tracker import KeyframeTracker, spread
from perception.keyframing import KeyframeSettings
from perception.odometry import OdometrySettings
from service.config import load_settings
from service.scheduler import ThreadedRunner
from slam.build import build_core
from slam.core import LIVE_MAX_PENDING
from slam.map_views import anchored_frames
from slam.records import FrameRecord
from slam.runner import Handle, InlineRunner, Lane
from sources import ground_truth_of, open_dataset
from tests.conftest import REDKITCHEN, requires_redkitchen


def _texture(seed: int = 0) -> np.ndarray:
    """Texture at every scale (LK's coarse pyramid levels need some too): blurred noise at four widths."""
    rng = np.random.default_rng(seed)
    layers = [cv2.GaussianBlur(rng.random((240, 320)), (0, 0), sigma) for sigma in (1.5, 4.0, 10.0, 25.0)]
    image = sum(layer / layer.std() for layer in layers)
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def test_spread_takes_points_from_every_cell_before_a_second_from_any():
    pixels = np.array([[5, 5]] * 50 + [[100, 100], [200, 150]], np.float32)  # 50 in one cell, two elsewhere
    chosen = spread(pixels, (240, 320), 3)
    assert sorted(pixels[chosen].tolist()) == [[5, 5], [100, 100], [200, 150]]
    assert len(spread(pixels, (240, 320), 100)) == len(pixels)


def test_flow_follows_a_shifted_image_to_a_tenth_of_a_pixel_and_drops_points_that_left_it():
    gray = _texture()
    rng = np.random.default_rng(1)
    pixels = np.column_stack([rng.uniform(20, 300, 200), rng.uniform(20, 220, 200)]).astype(np.float32)
    points = np.column_stack([pixels, np.ones(200)]).astype(np.float32)  # any 3D point: the tracker carries it
    tracker = KeyframeTracker(max_points=200)
    tracker.start(gray, pixels, points)
    shift = np.float32([[1, 0, 7.0], [0, 1, -4.0]])
    moved = cv2.warpAffine(gray, shift, (320, 240), borderMode=cv2.BORDER_REFLECT)
    tracks = tracker.track(moved)
    assert len(tracks) >= 0.9 * len(pixels)
    error = tracks.pixels - (tracks.points[:, :2] + np.float32([7.0, -4.0]))
    assert np.median(np.abs(error)) < 0.1
    gone = tracker.track(np.zeros_like(gray))  # nothing to follow: every track fails its backward check
    assert len(gone) == 0 and len(tracker.track(moved)) == 0  # a lost track stays lost until the next keyframe


def _track_all(vo: VisualOdometry, frames: list) -> tuple[np.ndarray, int, int]:
    poses, keyframes, tracked = [], 0, 0
    for f in frames:
        step = vo.track(f)
        poses.append(step.pose)
        keyframes += int(step.keyframe) + int(step.deferred is not None)
        tracked += int(step.method == "tracked")
    return np.stack(poses), keyframes, tracked


@pytest.fixture(scope="module")
def room():
    data = open_dataset("synthetic:room?seed=2&frames=300&width=320&height=240")  # 2 cm per frame
    return data, [data.frame(i) for i in range(90)], ground_truth_of(data).poses[:90]


def test_flow_tracks_the_frames_between_keyframes_as_accurately_as_features(room):
    data, frames, truth = room
    errors = {}
    for tracker in ("features", "flow"):
        vo = VisualOdometry(data.camera, KeyframeSettings(), OdometrySettings(tracker=tracker))
        poses, keyframes, tracked = _track_all(vo, frames)
        errors[tracker] = trajectory_error(poses, truth).ate_rmse_m
        assert vo.lost_count == 0 and keyframes < len(frames) / 2
        assert (tracked > len(frames) / 2) == (tracker == "flow")
    assert errors["flow"] < 0.02 and errors["flow"] < 1.5 * errors["features"]


class Slow:
    """A keyframe job that is ready ``frames`` frames after it was submitted (polled once a frame): a thread
    that takes that long, deterministically."""

    def __init__(self, value: object, frames: int):
        self.value, self.polls_left = value, frames

    def done(self) -> bool:
        self.polls_left -= 1
        return self.polls_left < 0

    def result(self) -> object:
        return self.value


@pytest.mark.parametrize("frames_per_job", [1, 4])
def test_keyframes_made_beside_the_tracking_reach_the_map_frames_later_and_track_as_well(room, frames_per_job):
    data, frames, truth = room
    sync = VisualOdometry(data.camera, KeyframeSettings(), OdometrySettings())
    sync_poses, sync_keyframes, _ = _track_all(sync, frames)
    live = VisualOdometry(data.camera, KeyframeSettings(), OdometrySettings())
    live.deferral = DeferredKeyframes(lambda fn, *args: Slow(fn(*args), frames_per_job))
    steps = [live.track(f) for f in frames]
    deferred = [(i, s.deferred) for i, s in enumerate(steps) if s.deferred is not None]
    assert deferred and live.deferral.submitted >= len(deferred) and live.deferral.failed == 0
    gaps = []
    for i, (kf_frame, kf_step) in deferred:  # each keyframe is an earlier frame, posed by flow when it came
        j = next(k for k, f in enumerate(frames) if f is kf_frame)
        assert i - j == frames_per_job + 1 and kf_step.keyframe and kf_step.factor is not None
        assert steps[j].method == "tracked"
        gaps.append(np.linalg.norm(steps[j].pose[:3, 3] - kf_step.pose[:3, 3]))
    # the features then refine its pose: the two agree to the odometry's error (here 0.1-2 cm)
    assert np.median(gaps) < 0.01 and max(gaps) < 0.03
    at_once = sum(s.keyframe for s in steps)  # the first frame, and frames the flow failed on
    # one job at a time: a keyframe at most every frames_per_job + 1 frames, else as many as without deferral
    assert at_once <= 2 and len(deferred) + at_once >= 0.8 * min(sync_keyframes, len(frames) / (frames_per_job + 1))
    live_error = trajectory_error(np.stack([s.pose for s in steps]), truth).ate_rmse_m
    assert live_error < 0.02 and live_error < 1.5 * trajectory_error(sync_poses, truth).ate_rmse_m + 0.002


def test_keyframes_made_on_a_thread_are_the_frames_posed_by_flow(room):
    data, frames, _ = room
    live = VisualOdometry(data.camera, KeyframeSettings(), OdometrySettings())
    with ThreadPoolExecutor(1) as pool:
        live.deferral = DeferredKeyframes(lambda *job: pool.submit(*job))
        steps = [live.track(f) for f in frames]
    deferred = [(i, s.deferred) for i, s in enumerate(steps) if s.deferred is not None]
    assert len(deferred) >= 5 and live.deferral.failed == 0 and live.lost_count == 0
    for i, (kf_frame, _) in deferred:  # however long the thread took, the keyframe is an earlier, flowed frame
        j = next(k for k, f in enumerate(frames) if f is kf_frame)
        assert j < i and steps[j].method == "tracked"


@requires_redkitchen
def test_flow_tracks_real_kinect_frames_no_worse_than_features():
    data = open_dataset(str(REDKITCHEN))
    frames = [data.frame(i) for i in range(150)]
    truth = ground_truth_of(data).poses[:150]
    errors = {}
    for tracker in ("features", "flow"):
        vo = VisualOdometry(data.camera, KeyframeSettings(), OdometrySettings(tracker=tracker, icp=False))
        errors[tracker] = trajectory_error(_track_all(vo, frames)[0], truth).ate_rmse_m
    assert errors["flow"] < 0.05 and errors["flow"] < 1.2 * errors["features"]


class SlowDetector(ThreadedRunner):
    """The service's runner with a detector that takes 0.3 s longer a keyframe (a bigger model, a busier machine),
    so that it falls behind whatever the load on the machine running the test."""

    def submit(self, lane: Lane, stage: Callable[..., Any], *args: Any) -> Handle:
        if lane is not Lane.DETECT:
            return super().submit(lane, stage, *args)

        def slow() -> Any:
            time.sleep(0.3)
            return stage(*args)

        return super().submit(lane, slow)


def test_a_live_core_never_waits_for_a_detector_that_is_behind_and_skips_its_keyframes():
    settings = load_settings(None, {})  # the shipped ONNX detector on keyframes without detections
    data = BareCamera(open_dataset("synthetic:room?seed=1&frames=300&width=320&height=240"))
    frames = [data.frame(i) for i in range(120)]
    core = build_core(settings, SlowDetector())
    core.live = True
    try:
        most_pending = 0
        for f in frames:  # as fast as the tracking goes: the detector (300+ ms a keyframe here) cannot keep up
            core.step(f)
            most_pending = max(most_pending, len(core.pending))
        keyframes = len(core.kf_odometry)
        core.flush()
        assert most_pending <= LIVE_MAX_PENDING and 0 < core.detections_skipped < keyframes
        assert core.detector_loaded  # the keyframes not skipped went to the ONNX detector
        assert len(core.keyframe_detections) == keyframes  # every keyframe mapped (some without detections)
        # a keyframe the detector skipped did not look at any object (it would count as a miss of every one)
        assert core.objects is not None and len(core.objects.looks.poses) == keyframes - core.detections_skipped
        assert len(core.trajectory()) == len(frames) and core.tracking_lost == 0
    finally:
        core.close()


def test_a_live_core_knows_the_frame_of_every_keyframe_made_beside_the_tracking(room):
    _, frames, truth = room
    core = build_core(load_settings(None, {"detector": {"enabled": False}}), InlineRunner())
    core.live = True
    try:
        for f in frames:
            core.step(dataclasses.replace(f, odometry=None, detections=None))
        assert core.frontend is not None and core.frontend.defer is not None and core.frontend.defer.submitted > 3
        core.finish()  # the keyframe still being made is added, not lost
        assert not core.frontend.defer.pending
        stamps = np.array(core.kf_stamps)
        assert len(stamps) == len(core.kf_odometry) == core.graph.num_keyframes and np.all(np.diff(stamps) > 0)
        # a keyframe made beside the tracking has no keyframe record: its stamp names its frame all the same
        recorded = {r.timestamp for r in core.records if r.is_keyframe}
        assert len(recorded) < len(stamps)
        index = {f.timestamp: i for i, f in enumerate(frames)}
        rel = [np.linalg.inv(truth[0]) @ truth[index[t]] for t in stamps]
        errors = [np.linalg.norm(p[:3, 3] - r[:3, 3]) for p, r in zip(core.graph.poses(), rel, strict=True)]
        assert max(errors) < 0.05  # each keyframe's pose is its own frame's (a neighbour's is 2 cm away)
        # that frame, and those tracked until its keyframe joined, were posed against the keyframe before it;
        # the trajectory ties them to theirs: each keyframe's frame is posed exactly at its keyframe's estimate
        traj = core.trajectory()
        at = dict(zip(traj.timestamps, traj.poses, strict=True))
        for k, t in enumerate(stamps):
            np.testing.assert_allclose(at[t], core.graph.poses()[k], atol=1e-9)
    finally:
        core.close()


def test_anchored_frames_ties_the_frames_since_a_late_keyframe_to_it():
    def pose(x: float) -> np.ndarray:
        T = np.eye(4)
        T[0, 3] = x
        return T

    # keyframe 1 is made from frame 2 and joins the graph at frame 4: frames 2 and 3 were posed against keyframe 0
    records = [
        FrameRecord(float(i), i, k, i == 0, pose(0.1 * i), pose(0.1 * i - base))
        for i, (k, base) in enumerate([(0, 0.0), (0, 0.0), (0, 0.0), (0, 0.0), (1, 0.2), (1, 0.2)])
    ]
    anchors = anchored_frames(records, [0.0, 2.0])
    assert [k for k, _ in anchors] == [0, 0, 1, 1, 1, 1]
    for (k, T), r in zip(anchors, records, strict=True):
        np.testing.assert_allclose(T, pose(0.1 * r.seq - (0.0 if k == 0 else 0.2)), atol=1e-12)
