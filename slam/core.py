"""The SLAM core: one frame in, what changed out (SPEC 6.4-6.9). No threads, no zenoh, no disk.

Per frame (``SlamCore.step``): (1) reject stale, duplicate or implausibly far timestamps (``slam.clock``) and
unusable depth; (2) the front end gives the odometry pose and decides keyframes: the frame's own odometry when
it can be chained, else RGB-D visual odometry (``perception.odometry_choice``); (3) a keyframe adds its
odometry factors to the graph; (4) the mapping of the keyframe ``MAPPING_LAG`` keyframes back is applied: its
landmark measurements and verified loop candidates; (5) this keyframe's mapping stages are handed to the
runner (``slam.stages``: detection, objects, loop verification); (6) every frame is recorded relative to its
keyframe, so the whole trajectory follows the graph. The stages read only what they are given and are applied
at a fixed point, so the map is the same whether the runner runs them at once (``InlineRunner``) or on
threads (``service.scheduler.ThreadedRunner``). Live (``SlamCore.live``, a robot's camera) trades that for
latency: a keyframe's mapping is applied as soon as it is done (``apply_ready``), tracking never waits for it
below ``LIVE_MAX_PENDING`` keyframes, and keyframes arriving while it is behind are not detected on.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from graph.object_landmarks import ObjectLandmarks
from graph.window import WindowedGraph
from loops.archive import ColdLog
from loops.closer import LoopCloser
from loops.records import Candidate, KeyframeEntry, Source
from perception.frame import CameraModel, Detection, Frame, FrameRejected, Reason
from perception.keyframe_deferral import DeferredKeyframes
from perception.keyframing import Step
from perception.object_map import ObjectMapper
from perception.odometry import FeatureExtractor
from perception.odometry_choice import PerFrameOdometry
from perception.registration import map_points
from rl.proposer import PolicyProposer
from slam import relocalization, stages
from slam.clock import StreamClock
from slam.map_views import MapViews
from slam.pose_log import PlacedPoses
from slam.records import FrameRecord, KeyframeLoops, KeyframeObjects, StepResult
from slam.repose import repose_due
from slam.runner import Done, Handle, InlineRunner, Lane, Runner, idle
from slam.segments import Segments, TrackingState
from slam.settings import SlamConfig

if TYPE_CHECKING:
    from perception.detector import Detector

log = logging.getLogger(__name__)

MAPPING_LAG = 3
"""A keyframe's mapping (objects, loop verification) is applied when the keyframe this many later is added:
the mapping thread has that many keyframe intervals before tracking waits for it. `bench throughput` at 30
frames/s with 14-18 % of the CPU stolen by the host: ingest-to-graph p95 67 and 321 ms with 3, 745 and 1594
ms with 2; with 1 the worker waited at p95 80-107 ms per step even on a quieter machine."""

LIVE_BEHIND = 2
"""Live: a keyframe gets no detection while this many keyframes' mapping is unfinished (the detector and the
mapping thread are behind the camera; detecting more would only add to their lag)."""
LIVE_MAX_PENDING = 8
"""Live: tracking waits for the oldest keyframe's mapping only when this many are unapplied (bounds memory)."""


@dataclass
class Tracking:
    """The components that depend on the camera, built when the first frame arrives."""

    camera: CameraModel
    frontend: PerFrameOdometry
    loops: LoopCloser | None = None
    extractor: FeatureExtractor | None = None


TrackingFactory = Callable[[CameraModel, bool], Tracking]
"""Builds the tracking components for a camera; the flag: the frames carry their own odometry."""


class SlamCore(MapViews):
    """Turns validated frames into keyframes, factors, objects and loop closures."""

    def __init__(
        self,
        settings: SlamConfig,
        graph: WindowedGraph,
        tracking: TrackingFactory,
        objects: ObjectMapper | None = None,
        landmarks: ObjectLandmarks | None = None,
        proposer: PolicyProposer | None = None,
        detector: Callable[[], Detector] | None = None,
        runner: Runner | None = None,
    ):
        self.settings = settings
        self.graph = graph
        self.objects = objects
        self.landmarks = landmarks
        self.proposer = proposer
        self.runner: Runner = runner or InlineRunner()
        self.tracking_factory = tracking
        self.detector_factory = detector
        self._detector: Detector | None = None
        self.tracking: Tracking | None = None
        self.records: list[FrameRecord] = []
        self.kf_odometry: list[np.ndarray] = []
        self.kf_stamps: list[float] = []  # per keyframe: its frame's timestamp (live, a keyframe's record may not say)
        self.kf_points: ColdLog[np.ndarray] = ColdLog()  # sparse depth samples per keyframe, camera frame, float32
        self.pending: deque[dict[str, Handle]] = deque()  # per keyframe, oldest first: its unapplied stages
        self.objects_view: list = []  # the objects as of the last applied mapping (read by object_list)
        self.object_poses = PlacedPoses()  # per keyframe: the pose its object observations were placed with
        self.keyframe_detections: dict[int, list[Detection]] = {}
        self.detections_by_class: Counter[str] = Counter()
        self.timings: dict[str, float] = {}
        self.tracking_lost = self.mapping_errors = self.reposes = self.object_map_version = 0
        self.segments = Segments()
        self.clock = StreamClock(settings.keyframes.max_time_jump_s, settings.keyframes.time_jump_frames)
        self.tracking_state = TrackingState.TRACKING
        self.methods: Counter[str] = Counter()  # frames per tracking method (perception.hypotheses.Method)
        self.session_gap_s: float | None = None  # ``begin_session`` until the first frame; then the session's
        self.session_keyframe: int | None = None  # first keyframe when it began anywhere
        self.live = False  # latency first (``ingest.live``): mapping applied when done, never waited for
        self.detections_skipped = 0  # live: keyframes not given to the detector because mapping was behind

    @property
    def frontend(self) -> PerFrameOdometry | None:
        return self.tracking.frontend if self.tracking is not None else None

    @property
    def loops(self) -> LoopCloser | None:
        return self.tracking.loops if self.tracking is not None else None

    @property
    def last_timestamp(self) -> float:
        return self.records[-1].timestamp if self.records else -math.inf

    def begin_session(self, gap_s: float) -> None:
        """A new run on this map: a first frame more than ``gap_s`` after the last one may be anywhere and is
        a lost keyframe, relocalized against the stored ones or starting a segment (``slam.relocalization``)."""
        self.session_gap_s = gap_s if self.records else None

    def step(self, frame: Frame) -> StepResult:
        """Add one frame; raises FrameRejected (counted by the caller) when it cannot be used."""
        self.timings = {}
        self._check(frame)
        assert self.tracking is not None
        if self.session_gap_s is not None:
            if frame.timestamp - self.last_timestamp > self.session_gap_s:
                self.tracking.frontend.new_session()
                self.session_keyframe = len(self.kf_odometry)
            self.session_gap_s = None
        version, n_loops = self.object_map_version, len(self.loops.records) if self.loops is not None else 0
        frontend = self.tracking.frontend
        if self.live and frontend.defer is None:
            frontend.defer = DeferredKeyframes(lambda *job: self.runner.submit(Lane.KEYFRAME, *job))
        t0 = time.perf_counter()
        step = frontend.track(frame)
        self.timings["frontend"] = time.perf_counter() - t0
        self.tracking_lost += int(step.lost)
        added = []
        if step.deferred is not None:  # live: a keyframe made beside the tracking, added before this frame
            kf_frame, kf_step = step.deferred
            added.append((self._add_keyframe(kf_frame, kf_step).keyframe, kf_frame.timestamp))
        if step.keyframe:
            record = self._add_keyframe(frame, step)
            added.append((record.keyframe, frame.timestamp))
        else:
            kf = len(self.kf_odometry) - 1
            offset = np.linalg.inv(self.kf_odometry[kf]) @ step.pose
            record = FrameRecord(frame.timestamp, frame.seq, kf, False, step.pose, offset, step.posed)
        self.records.append(record)
        self.clock.accept(frame.timestamp)
        self.methods[step.method] += 1
        self.tracking_state = TrackingState.of(step, self.segments.tied(record.keyframe))
        return StepResult(
            record,
            record.keyframe if record.is_keyframe else None,
            self.loops.records[n_loops:] if self.loops is not None else [],
            self.object_map_version != version,
            dict(self.timings),
            tuple(added),
        )

    def _check(self, frame: Frame) -> None:
        self.clock.check(frame.timestamp, jump_ok=self.session_gap_s is not None)
        if not np.any(frame.depth):
            raise FrameRejected(Reason.EMPTY_DEPTH, "depth image has no valid pixel")
        if self.tracking is None:
            self.connect(self.tracking_factory(frame.camera, frame.odometry is not None))
        assert self.tracking is not None
        self.tracking.frontend.check(frame, frame.timestamp - self.last_timestamp)

    def connect(self, tracking: Tracking) -> None:
        """Use ``tracking``'s components; loop closures between map segments join them."""
        self.tracking = tracking
        if tracking.loops is not None:
            tracking.loops.acceptance.joined = self.joined

    def joined(self, a: int, b: int) -> bool:
        """Keyframes ``a`` and ``b`` are in map segments joined by measurements."""
        return self.segments.joined(a, b)

    def _add_keyframe(self, frame: Frame, step: Step) -> FrameRecord:
        if not self.kf_odometry:
            kf = self.graph.add_first(step.pose)
            self.segments.add_keyframe(kf)
        elif step.lost:
            assert self.tracking is not None
            frontend = self.tracking.frontend
            kf = relocalization.place_lost(
                self.graph, self.segments, self.loops, frame, step, self.kf_odometry, frontend.config
            )
            if step.method == "relocalized":
                frontend.reanchor(step.pose)
        else:
            if step.factor is None:
                raise ValueError("the front end made a keyframe without an odometry factor")
            kf = self.graph.add_keyframe(step.factor, step.sigma_m, step.sigma_deg)
            self.segments.add_keyframe(kf)
            for back, T, sigma_m, sigma_deg in step.extra:
                if kf - back >= 0:
                    self.graph.add_between(kf - back, kf, T, sigma_m, sigma_deg)
            if not self.segments.tied(kf):
                relocalization.try_join(self.graph, self.segments, self.loops, kf, frame, step)
        self.kf_odometry.append(step.pose)
        self.kf_stamps.append(frame.timestamp)
        self.kf_points.append(map_points(frame))
        if self.live:
            self.timings.update(self.apply_ready() or {})
        while len(self.pending) >= (LIVE_MAX_PENDING if self.live else MAPPING_LAG):
            self._apply_mapping()
        self._submit_mapping(kf, frame, step)
        return FrameRecord(frame.timestamp, frame.seq, kf, True, step.pose, np.eye(4))

    # ------------------------------------------------------------ keyframe mapping (objects, loop closure)

    def _submit_mapping(self, kf: int, frame: Frame, step: Step) -> None:
        """Hand keyframe ``kf``'s stages to the runner; everything they read from the graph is taken now."""
        detections: Handle
        behind = self.live and sum(not idle([jobs]) for jobs in self.pending) >= LIVE_BEHIND
        if frame.detections is None and self.settings.detector.enabled and behind:
            detections, self.detections_skipped = Done((None, {})), self.detections_skipped + 1  # none: not looked
        elif frame.detections is None and self.settings.detector.enabled:
            detections = self.runner.submit(Lane.DETECT, stages.detect, self._get_detector(), frame.rgb)
        else:
            detections = Done((frame.detections or [], {}))
        reposed = self._repose_due()
        body, color_from_body = self.graph.pose(kf), self._color_from_body()
        if self.objects is not None:
            self.object_poses.append(body)
        jobs = {
            "objects": self.runner.submit(
                Lane.MAP, stages.map_objects, self.objects, kf, frame, detections, body, color_from_body, reposed
            )
        }
        loops = self.loops
        if loops is not None:
            assert self.tracking is not None and self.tracking.extractor is not None
            entry = KeyframeEntry(kf, frame.timestamp, frame.seq, step.features)
            poses = self.graph.poses() if loops.settings.proximity else None
            proposed = self._policy_candidates(kf)
            jobs["loops"] = self.runner.submit(
                Lane.MAP, stages.verify_loops, loops, self.tracking.extractor, entry, frame, proposed, poses
            )
        self.pending.append(jobs)

    def _policy_candidates(self, kf: int) -> list[Candidate]:
        """The RL policy's candidates for this keyframe (Sec. 3.8): earlier keyframes where it says we are."""
        if self.proposer is None:
            return []
        t0 = time.perf_counter()
        proposal = self.proposer.observe(kf, self.graph.pose(kf))
        self.timings["policy"] = time.perf_counter() - t0
        if proposal is None:
            return []
        return [Candidate(i, Source.POLICY, proposal.probability) for i in proposal.candidates]

    @property
    def detector_loaded(self) -> bool:
        """True once a keyframe without detections needed the detector (built on first use)."""
        return self._detector is not None

    def _get_detector(self) -> Detector:
        if self._detector is None:
            if self.detector_factory is None:
                raise ValueError("keyframes without detections need a detector (detector.enabled)")
            self._detector = self.detector_factory()
        return self._detector

    def apply_ready(self) -> dict[str, float] | None:
        """Live: apply the mapping of the oldest keyframes whose stages have all finished (none waited for);
        the seconds each stage took, or None when none was applied."""
        step_timings, self.timings = self.timings, {}
        applied = False
        while self.pending and idle([self.pending[0]]):
            self._apply_mapping()
            applied = True
        applied_timings, self.timings = self.timings, step_timings
        return applied_timings if applied else None

    def take_deferred(self) -> bool:
        """Live, no frame coming: wait for the keyframe being made beside the tracking and add it (it would
        otherwise wait for the next frame); True when one was added."""
        taken = self.tracking.frontend.take_deferred() if self.tracking is not None else None
        if taken is not None:
            self._add_keyframe(*taken)
        return taken is not None

    def _apply_mapping(self) -> None:
        """Take the oldest unapplied keyframe's mapping and put it into the map: its detections and landmark
        measurements, the landmarks' new assignment after a re-clustering or re-posing, then its loop closures
        (gated against the graph). A stage that failed is logged and counted (``mapping_errors``): its
        keyframe keeps no objects or loops."""
        if not self.pending:
            return
        jobs = self.pending.popleft()
        objects = self._result(jobs["objects"]) if "objects" in jobs else None
        found = self._result(jobs["loops"]) if "loops" in jobs else None
        if objects is not None:
            self._apply_objects(objects)
        if found is not None and self.loops is not None:
            self.timings.update(found.timings)
            t0 = time.perf_counter()
            for record in self.loops.accept(found.verified):
                if record.accepted and not self.segments.joined(record.match_keyframe, record.query_keyframe):
                    relocalization.join(self.graph, self.segments, record.match_keyframe, record.query_keyframe)
            self.timings["loop_accept"] = time.perf_counter() - t0

    def _result(self, handle: Handle):
        try:
            return handle.result()
        except Exception:  # bad input must not stop the map: the keyframe is mapped without it
            log.exception("mapping a keyframe failed")
            self.mapping_errors += 1
            return None

    def _apply_objects(self, result: KeyframeObjects) -> None:
        self.keyframe_detections[result.keyframe] = result.detections
        self.detections_by_class.update(d.label for d in result.detections)
        self.timings.update(result.timings)
        if self.objects is None:
            return
        if self.landmarks is not None:
            t0 = time.perf_counter()
            self.landmarks.observe(result.keyframe, result.observations)
            if result.reclustered or result.reposed:
                self.landmarks.sync(result.objects, result.retired)
            self.timings["landmarks"] = time.perf_counter() - t0
        self.object_map_version += int(result.reclustered) + int(result.reposed)
        self.objects_view, self.objects_unconfirmed = result.objects, result.unconfirmed

    def settle(self) -> list[dict[str, KeyframeObjects | KeyframeLoops | None]]:
        """Wait for the submitted stages and keep their results (unapplied); a failed stage as None."""
        results = []
        for jobs in self.pending:
            done = {name: self._result(handle) for name, handle in jobs.items()}
            jobs.update({name: Done(value) for name, value in done.items()})
            results.append(done)
        return results

    def flush(self) -> None:
        """Finish the mapping of every keyframe and apply it (later keyframes would)."""
        while self.pending:
            self._apply_mapping()

    def finish(self) -> None:
        """End of a sequence: the whole graph solved, open tracks emitted, objects re-clustered once more."""
        self.take_deferred()
        self.flush()
        self.graph.flush()
        if self.objects is not None and self.records:
            self.objects.finish()
            self.objects_view, self.objects_unconfirmed = list(self.objects.objects), len(self.objects.clusterer.unkept)
            if self.landmarks is not None:
                self.landmarks.sync(self.objects_view, self.objects.take_retired())
            self.object_map_version += 1

    def close(self) -> None:
        """Stop the runner (submitted stages finish first) and the graph's solver."""
        self.runner.close()
        self.graph.close()

    def _color_from_body(self) -> np.ndarray:
        """The colour camera's pose in the keyframe (depth camera) frame: identity when registered."""
        camera = self.tracking.camera if self.tracking is not None else None
        if camera is None or camera.registered or camera.depth_to_color is None:
            return np.eye(4)
        return np.linalg.inv(camera.depth_to_color)

    def _repose_due(self) -> np.ndarray | None:
        """The poses to re-place the object observations with when the graph moved them (``slam.repose``)."""
        if self.objects is None:
            return None
        poses = repose_due(self.graph, self.object_poses, self.settings.objects)
        if poses is not None:
            self.object_poses.revise(poses)
            self.reposes += 1
        return poses
