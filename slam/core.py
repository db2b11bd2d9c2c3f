"""The per-frame pipeline: temporal checks, odometry front end, keyframes, pose graph, loop closure.

No zenoh, no disk: the service node feeds it decoded frames; ``state()`` / ``from_state()`` give and take
its whole state as plain data, which service.persistence writes to disk.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from pydantic import BaseModel

from graph.object_landmarks import LandmarkConfig, ObjectLandmarks
from graph.trajectory import Trajectory
from graph.window import WindowedGraph
from loops.closer import KeyframeEntry, LoopCloser, LoopConfig, Verified
from perception.clustering import ObjectEllipsoid
from perception.frame import CameraModel, Detection, Frame, FrameRejected, Reason
from perception.frontend import ExternalOdometry, KeyframePolicy, Step, VisualOdometry
from perception.object_map import ObjectMapper, object_json
from perception.odometry import FeatureExtractor, OdometryConfig, RelativePoseEstimator
from perception.registration import backproject, depth_in_color
from rl.proposer import PolicyProposer
from service.config import Settings

log = logging.getLogger(__name__)


@dataclass
class FrameRecord:
    """Where a processed frame sits in the graph: its keyframe and its odometry pose relative to it."""

    timestamp: float
    seq: int
    keyframe: int
    is_keyframe: bool
    odometry: np.ndarray
    from_keyframe: np.ndarray


MAPPING_LAG = 3
"""A keyframe's mapping (objects, loop verification) is applied when the keyframe this many later is added:
the mapping thread has that many keyframe intervals before tracking waits for it. `bench throughput` at 30
frames/s with 14-18 % of the CPU stolen by the host: ingest-to-graph p95 67 and 321 ms with 3, 745 and 1594
ms with 2; with 1 the worker waited at p95 80-107 ms per step even on a quieter machine."""


@dataclass
class KeyframeObjects:
    """What mapping one keyframe's objects produced, to be applied to the graph (plain data)."""

    keyframe: int
    detections: list[Detection]
    observations: list[tuple[int, np.ndarray, float]] = field(default_factory=list)  # (track, body-frame p, extent)
    reclustered: bool = False
    reposed: bool = False
    objects: list[ObjectEllipsoid] = field(default_factory=list)  # the object map after this keyframe
    timings: dict[str, float] = field(default_factory=dict)


class InlineExecutor(Executor):
    """Runs each task at once in the caller's thread (tests, benchmarks: the same results as the thread)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:  # handed to whoever takes the result, as a thread pool would
            future.set_exception(exc)
        return future


def map_points(frame: Frame, step: int = 32, max_depth_m: float = 4.0) -> np.ndarray:
    """A sparse grid of the frame's depth points (camera frame, float32) for the map's occupancy."""
    pts, _, _ = backproject(frame.depth_m(), frame.camera.depth, step)
    return pts[pts[:, 2] <= max_depth_m].astype(np.float32)


def load_proposer(path, radius: int, candidates: int) -> PolicyProposer:
    """The RL loop-closure proposer for a policy file (``loops.policy``)."""
    from rl.policy import OnnxPolicy  # onnxruntime session only when a policy is configured

    if path is None:
        raise ValueError("loops.source policy/both needs loops.policy (a FILE.onnx from train-lc --from-map)")
    return PolicyProposer(OnnxPolicy(path), radius=radius, max_candidates=candidates)


def from_settings(cls, *sections: BaseModel):
    """A component's frozen config dataclass from the same-named fields of configuration sections.

    Where two sections share a field name the earlier section wins (keyframes.min_inliers over odometry's).
    """
    names = {f.name for f in fields(cls)}
    values: dict = {}
    for section in sections:
        for k, v in section.model_dump().items():
            if k in names:
                values.setdefault(k, v)
    return cls(**values)


class Pipeline:
    """Turns validated frames into keyframes and factors (SPEC 6.4, 6.8).

    Per frame: (1) reject stale or duplicate timestamps and unusable depth; (2) the front end gives the
    odometry pose and decides keyframes: the frames' own odometry when the stream carries it (decided by
    the first frame), else RGB-D visual odometry; (3) a keyframe adds its odometry factor to iSAM2;
    (4) loop-closure candidates of the keyframe are verified and accepted ones become robust factors;
    (5) every frame is recorded relative to its keyframe, so the full trajectory follows the graph.

    The mapping of a keyframe (object detection when the frame has none, on a detector thread; NPDA, tracks,
    clustering; loop candidates and their geometric verification) runs on a mapping thread while the next
    frames are tracked; its landmark measurements and loop factors enter the graph when the keyframe ``MAPPING_LAG``
    later is added (or on ``flush``). That point is fixed and the jobs read only what they were given, so
    the result is the same with the thread (``background=True``, the service) or with each job run at once.
    """

    def __init__(self, settings: Settings, background: bool = False):
        self.settings = settings
        # One mapping thread, jobs in submission order: a keyframe's objects, then its loop verification. More
        # mapping threads measured worse: they compete with ingest and queries for the GIL and the two cores
        # (status p99 under overload 125-140 ms with three, 93 ms with one). The detector has a thread of its
        # own: onnxruntime releases the GIL, so detecting keyframe k+1 overlaps associating keyframe k
        # (keyframe mapping on 7-Scenes 12.2 keyframes/s instead of 9.7-10.9, `bench stages`).
        self._mapping: Executor = (
            ThreadPoolExecutor(1, thread_name_prefix="objslam-mapping") if background else InlineExecutor()
        )
        self._detecting: Executor = (
            ThreadPoolExecutor(1, thread_name_prefix="objslam-detector") if background else self._mapping
        )
        self._pending: deque[dict[str, Future]] = deque()  # per keyframe, oldest first: its unapplied mapping jobs
        self._objects_view: list = []  # the objects as of the last applied mapping (read by object_list)
        self.mapping_errors = 0
        self.graph = WindowedGraph(settings.graph)
        self.policy = from_settings(KeyframePolicy, settings.keyframes, settings.odometry)
        self.odometry_config = from_settings(OdometryConfig, settings.odometry)
        self.frontend: ExternalOdometry | VisualOdometry | None = None
        self._camera: CameraModel | None = None
        self.loops: LoopCloser | None = None
        self._extractor: FeatureExtractor | None = None
        self.records: list[FrameRecord] = []
        self._kf_odometry: list[np.ndarray] = []
        self._kf_points: list[np.ndarray] = []  # sparse depth samples per keyframe, camera frame, float32
        self.proposer: PolicyProposer | None = None
        self.tracking_lost = 0
        self.timings: dict[str, float] = {}
        self._detector = None
        self.keyframe_detections: dict[int, list] = {}
        self.detections_by_class: Counter[str] = Counter()
        self.objects = ObjectMapper() if settings.objects.enabled else None
        self.object_map_version = 0
        self.landmarks = (
            ObjectLandmarks(self.graph, from_settings(LandmarkConfig, settings.objects))
            if settings.objects.enabled and settings.objects.landmarks
            else None
        )
        self._object_poses: list[np.ndarray] = []  # per keyframe: the pose its object observations were placed with
        self.reposes = 0

    @property
    def last_timestamp(self) -> float:
        return self.records[-1].timestamp if self.records else -math.inf

    def process(self, frame: Frame) -> FrameRecord:
        """Add one frame; raises FrameRejected (counted by the caller) when it cannot be used."""
        self._check(frame)
        if self.frontend is None:
            self._start(frame)
        t0 = time.perf_counter()
        step = self.frontend.track(frame)
        self.timings["frontend"] = time.perf_counter() - t0
        self.tracking_lost += int(step.lost)
        if step.keyframe:
            record = self._add_keyframe(frame, step)
        else:
            kf = len(self._kf_odometry) - 1
            record = FrameRecord(
                frame.timestamp, frame.seq, kf, False, step.pose, np.linalg.inv(self._kf_odometry[kf]) @ step.pose
            )
        self.records.append(record)
        return record

    def _start(self, frame: Frame) -> None:
        """Choose the front end from the first frame and set up loop closure for its camera."""
        if frame.odometry is None:
            log.info("frames carry no odometry: using RGB-D visual odometry")
        self._setup(frame.camera, external=frame.odometry is not None)

    def _setup(self, camera: CameraModel, external: bool) -> None:
        self._camera = camera
        if external:
            self.frontend = ExternalOdometry(self.policy)
        else:
            self.frontend = VisualOdometry(camera, self.policy, self.odometry_config)
        lc = self.settings.loops
        if lc.source != "off":
            self.loops = LoopCloser(
                self.graph, RelativePoseEstimator(camera, self.odometry_config), from_settings(LoopConfig, lc)
            )
            self._extractor = FeatureExtractor(camera, self.odometry_config)
        if lc.source in ("policy", "both"):
            self.proposer = load_proposer(lc.policy, lc.policy_radius, lc.policy_candidates)

    def _check(self, frame: Frame) -> None:
        if frame.timestamp == self.last_timestamp:
            raise FrameRejected(Reason.DUPLICATE_TIMESTAMP, f"timestamp {frame.timestamp} already processed")
        if frame.timestamp < self.last_timestamp:
            raise FrameRejected(Reason.OUT_OF_ORDER, f"timestamp {frame.timestamp} < {self.last_timestamp}")
        if not np.any(frame.depth):
            raise FrameRejected(Reason.EMPTY_DEPTH, "depth image has no valid pixel")
        if isinstance(self.frontend, ExternalOdometry) and frame.odometry is None:
            raise FrameRejected(Reason.NO_ODOMETRY, "this stream carries odometry but the frame has none")
        if (
            isinstance(self.frontend, ExternalOdometry)
            and self.records
            and self.policy.implausible(
                self.records[-1].odometry, frame.odometry, frame.timestamp - self.last_timestamp
            )
        ):
            raise FrameRejected(Reason.ODOMETRY_JUMP, "odometry jumped implausibly far since the last frame")

    def _add_keyframe(self, frame: Frame, step: Step) -> FrameRecord:
        if not self._kf_odometry:
            kf = self.graph.add_first(step.pose)
        else:
            kf = self.graph.add_keyframe(step.factor, step.sigma_m, step.sigma_deg)
            for back, T, sigma_m, sigma_deg in step.extra:
                if kf - back >= 0:
                    self.graph.add_between(kf - back, kf, T, sigma_m, sigma_deg)
        self._kf_odometry.append(step.pose)
        self._kf_points.append(map_points(frame))
        while len(self._pending) >= MAPPING_LAG:
            self._apply_mapping()
        self._submit_mapping(kf, frame, step)
        return FrameRecord(frame.timestamp, frame.seq, kf, True, step.pose, np.eye(4))

    def _policy_candidates(self, kf: int) -> list[tuple[int, str, float]]:
        """The RL policy's candidates for this keyframe (Sec. 3.8): earlier keyframes where it says we are."""
        if self.proposer is None:
            return []
        t0 = time.perf_counter()
        proposal = self.proposer.observe(kf, self.graph.pose(kf))
        self.timings["policy"] = time.perf_counter() - t0
        if proposal is None:
            return []
        return [(i, "policy", proposal.probability) for i in proposal.candidates]

    def cloud(self) -> np.ndarray:
        """Sparse map points (N, 3) in the trajectory frame: every keyframe's samples at its current estimate."""
        if not self._kf_points:
            return np.zeros((0, 3), np.float32)
        poses = self.graph.poses()
        parts = [
            pts @ poses[k][:3, :3].T.astype(np.float32) + poses[k][:3, 3].astype(np.float32)
            for k, pts in enumerate(self._kf_points[: len(poses)])
        ]
        return np.concatenate(parts)

    # ------------------------------------------------------------ keyframe mapping (objects, loop closure)

    def _submit_mapping(self, kf: int, frame: Frame, step: Step) -> None:
        """Start mapping keyframe ``kf`` beside the tracking of the next frames.

        Objects: detection (SPEC 6.1), then re-posing when due, NPDA and clustering. Loop closure: features,
        candidates and their geometric verification. Everything they read from the graph is taken now.
        """
        detections: Future
        if frame.detections is None and self.settings.detector.enabled:
            detections = self._detecting.submit(self._detect, frame.rgb)
        else:
            detections = Future()
            detections.set_result((frame.detections or [], {}))
        reposed = self._repose_due()
        body, color_from_body = self.graph.pose(kf), self._color_from_body()
        if self.objects is not None:
            self._object_poses.append(body)
        jobs: dict[str, Future] = {}
        jobs["objects"] = self._mapping.submit(self._map_objects, kf, frame, detections, body, color_from_body, reposed)
        if self.loops is not None:
            entry = KeyframeEntry(kf, frame.timestamp, frame.seq, step.features)
            poses = self.graph.poses() if self.loops.config.proximity else None
            jobs["loops"] = self._mapping.submit(self._verify_loops, entry, frame, self._policy_candidates(kf), poses)
        self._pending.append(jobs)

    def _detect(self, rgb: np.ndarray) -> tuple[list[Detection], dict[str, float]]:
        t0 = time.perf_counter()
        detections = self._get_detector().detect(rgb)
        return detections, {"detector": time.perf_counter() - t0}

    def _map_objects(
        self,
        kf: int,
        frame: Frame,
        detections: Future,
        body: np.ndarray,
        color_from_body: np.ndarray,
        reposed: np.ndarray | None,
    ) -> KeyframeObjects:
        """Associate the keyframe's detections, extend tracks and re-cluster objects (Sec. 2.4, SPEC 6.2-6.7).

        On the mapping thread; touches nothing but the object mapper. ``reposed``: new poses of the earlier
        keyframes to recompute the feature vectors from first (Sec. 2.4.7). Boxes are colour pixels, so
        depth is registered to colour and the colour camera's pose is used.
        """
        found, timings = detections.result()
        result = KeyframeObjects(kf, found, timings=dict(timings))
        if self.objects is None:
            return result
        if reposed is not None:
            t0 = time.perf_counter()
            self.objects.repose(reposed @ color_from_body)
            result.reposed = True
            result.timings["repose"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        camera = frame.camera
        depth = depth_in_color(frame.depth_m(), camera, scale=2)
        result.reclustered = self.objects.add_keyframe(kf, found, depth, camera.color.matrix(), body @ color_from_body)
        to_body = np.linalg.inv(color_from_body)
        result.observations = [
            (t, to_body[:3, :3] @ p + to_body[:3, 3], extent) for t, p, extent in self.objects.last_observations
        ]
        result.objects = list(self.objects.objects)  # the mapper may be on a later keyframe when this is applied
        result.timings["objects"] = time.perf_counter() - t0
        return result

    def _verify_loops(
        self, entry: KeyframeEntry, frame: Frame, proposed: list[tuple[int, str, float]], poses: np.ndarray | None
    ) -> tuple[list[Verified], dict[str, float]]:
        """Loop-closure candidates of a keyframe, verified geometrically (on the mapping thread, no graph)."""
        t0 = time.perf_counter()
        if entry.features is None:
            entry = replace(entry, features=self._extractor.extract(frame))
        verified = self.loops.verify(entry, frame.rgb, proposed, poses)
        return verified, {"loop_closure": time.perf_counter() - t0}

    def _apply_mapping(self) -> None:
        """Wait for the oldest unapplied keyframe's mapping and put it into the map: its detections and
        landmark measurements, the landmarks' new assignment after a re-clustering or re-posing, then its loop
        closures (gated against the graph). A job that failed is logged and counted (``mapping_errors``):
        its keyframe keeps no objects or loops."""
        if not self._pending:
            return
        pending = self._pending.popleft()
        objects, loops = (self._result(pending[name]) if name in pending else None for name in ("objects", "loops"))
        if objects is not None:
            self._apply_objects(objects)
        if loops is not None:
            verified, timings = loops
            self.timings.update(timings)
            t0 = time.perf_counter()
            self.loops.accept(verified)
            self.timings["loop_accept"] = time.perf_counter() - t0

    def _result(self, future: Future):
        try:
            return future.result()
        except Exception:  # bad input must not stop the pipeline: the keyframe is mapped without it
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
                self.landmarks.sync(result.objects)
            self.timings["landmarks"] = time.perf_counter() - t0
        self.object_map_version += int(result.reclustered) + int(result.reposed)
        self._objects_view = result.objects

    def flush(self) -> None:
        """Finish the mapping of every keyframe and apply it (later keyframes would)."""
        while self._pending:
            self._apply_mapping()

    def close(self) -> None:
        """Stop the mapping thread (submitted jobs are finished first)."""
        self._detecting.shutdown(wait=True)
        self._mapping.shutdown(wait=True)
        self.graph.close()

    def _color_from_body(self) -> np.ndarray:
        """The colour camera's pose in the keyframe (depth camera) frame: identity when registered."""
        camera = self._camera
        if camera is None or camera.registered or camera.depth_to_color is None:
            return np.eye(4)
        return np.linalg.inv(camera.depth_to_color)

    def _repose_due(self) -> np.ndarray | None:
        """Sec. 2.4.7: after an optimisation, the feature vectors are recomputed from the updated poses and the
        objects re-clustered. Due when some keyframe holding object observations has moved by more than
        ``repose_m`` or turned by more than ``repose_deg`` since its observations were placed (smaller
        corrections are below the objects' own noise and re-clustering every keyframe would cost ~50 ms
        each); then the poses to re-place them with, else None.
        """
        if self.objects is None or not self._object_poses:
            return None
        n = len(self._object_poses)
        # at most ~110 keyframes checked (every n/100-th and the last 10): an optimisation that matters moves
        # many keyframes together, and a full estimate per keyframe would grow with the map
        idx = np.unique(np.r_[np.arange(0, n, max(1, n // 100)), np.arange(max(0, n - 10), n)])
        now, used = np.stack([self.graph.pose(int(k)) for k in idx]), np.stack([self._object_poses[k] for k in idx])
        moved = np.linalg.norm(now[:, :3, 3] - used[:, :3, 3], axis=1).max()
        cos = (np.einsum("nij,nij->n", now[:, :3, :3], used[:, :3, :3]) - 1.0) / 2.0
        turned = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max()
        cfg = self.settings.objects
        if moved <= cfg.repose_m and turned <= cfg.repose_deg:
            return None
        now = self.graph.poses()[:n]
        self._object_poses = list(now)
        self.reposes += 1
        return now

    def finish(self) -> None:
        """End of a sequence (``run``): the whole graph solved, the open tracks emitted, the objects re-clustered
        once more."""
        self.flush()
        self.graph.flush()
        if self.objects is not None and self.records:
            self.objects.finish()
            self._objects_view = list(self.objects.objects)
            if self.landmarks is not None:
                self.landmarks.sync(self._objects_view)
            self.object_map_version += 1

    def object_list(self) -> list[dict]:
        """Current objects in the frame of the trajectory (``objects.json`` entries)."""
        if self.objects is None:
            return []
        landmarks = self.landmarks.positions() if self.landmarks is not None else {}
        return [object_json(o, landmarks.get(o.id)) for o in self._objects_view]

    def _get_detector(self):
        if self._detector is None:
            from perception.detector import Detector, DetectorConfig

            self._detector = Detector(from_settings(DetectorConfig, self.settings.detector))
        return self._detector

    def trajectory(self) -> Trajectory:
        """Optimised poses of every processed frame (keyframe estimate composed with its offset)."""
        if not self.records:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        kf_poses = self.graph.poses()
        poses = np.stack([kf_poses[r.keyframe] @ r.from_keyframe for r in self.records])
        return Trajectory(np.array([r.timestamp for r in self.records]), poses)

    def odometry_trajectory(self) -> Trajectory:
        """The front-end (odometry) poses of every processed frame."""
        if not self.records:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([r.timestamp for r in self.records]), np.stack([r.odometry for r in self.records]))

    def loop_records(self) -> list[dict]:
        return list(self.loops.records) if self.loops is not None else []

    # ------------------------------------------------------------ plain state

    def state(self) -> dict[str, Any]:
        """Everything needed to continue exactly where this pipeline is, as plain data and arrays.

        The graph as recorded factors and updates, frame records, the front end's keyframe, loop closure's
        keyframes and records, tracks and objects. Not included: cv2 and gtsam objects and the detector,
        which ``from_state`` recreates. The result shares arrays with the pipeline: serialise it before the
        next ``process``.
        """
        r = self.records
        pending = []  # finished (the jobs read nothing later frames change), unapplied; a failed job as None
        for jobs in self._pending:
            results = {}
            for name, future in jobs.items():
                results[name] = self._result(future)
                jobs[name] = Future()
                jobs[name].set_result(results[name])
            pending.append(results)
        return {
            "pending_mapping": pending,
            "objects_view": self._objects_view,
            "mapping_errors": self.mapping_errors,
            "camera": self._camera,
            "external_odometry": isinstance(self.frontend, ExternalOdometry),
            "frontend": None if self.frontend is None else self.frontend.state(),
            "graph": self.graph.state(),
            "records": {
                "timestamp": np.array([x.timestamp for x in r]),
                "seq": np.array([x.seq for x in r], np.int64),
                "keyframe": np.array([x.keyframe for x in r], np.int64),
                "is_keyframe": np.array([x.is_keyframe for x in r], bool),
                "odometry": np.array([x.odometry for x in r]).reshape(-1, 4, 4),
                "from_keyframe": np.array([x.from_keyframe for x in r]).reshape(-1, 4, 4),
            },
            "kf_odometry": np.array(self._kf_odometry).reshape(-1, 4, 4),
            "kf_points": self._kf_points,
            "tracking_lost": self.tracking_lost,
            "keyframe_detections": self.keyframe_detections,
            "detections_by_class": dict(self.detections_by_class),
            "objects": None if self.objects is None else self.objects.state(),
            "object_map_version": self.object_map_version,
            "landmarks": None if self.landmarks is None else self.landmarks.state(),
            "object_poses": np.array(self._object_poses).reshape(-1, 4, 4),
            "reposes": self.reposes,
            "loops": None if self.loops is None else self.loops.state(),
            "proposer": None if self.proposer is None else self.proposer.state(),
        }

    @classmethod
    def from_state(cls, settings: Settings, state: dict[str, Any], background: bool = False) -> Pipeline:
        """A pipeline that continues from ``state`` (of ``state()``) exactly as the saved one would have."""
        p = cls(settings, background)
        p.graph = WindowedGraph.from_state(state["graph"], settings.graph)
        if state["camera"] is not None:
            p._setup(state["camera"], state["external_odometry"])
            p.frontend.restore(state["frontend"])
            if p.loops is not None and state["loops"] is not None:
                p.loops.restore(state["loops"])
            if p.proposer is not None and state.get("proposer") is not None:
                p.proposer.restore(state["proposer"])
        r = state["records"]
        p.records = [
            FrameRecord(float(t), int(s), int(k), bool(kf), odo, off)
            for t, s, k, kf, odo, off in zip(
                r["timestamp"], r["seq"], r["keyframe"], r["is_keyframe"], r["odometry"], r["from_keyframe"]
            )
        ]
        p._kf_odometry = list(state["kf_odometry"])
        p._kf_points = list(state.get("kf_points", []))
        p.tracking_lost = state["tracking_lost"]
        p.keyframe_detections = state["keyframe_detections"]
        p.detections_by_class = Counter(state["detections_by_class"])
        if p.objects is not None and state["objects"] is not None:
            p.objects.restore(state["objects"])
        p.object_map_version = state["object_map_version"]
        if p.landmarks is not None:
            p.landmarks.graph = p.graph
            if state.get("landmarks") is not None:
                p.landmarks.restore(state["landmarks"])
        p._object_poses = list(state.get("object_poses", p.graph.poses()[: len(p.keyframe_detections)]))
        p.reposes = state.get("reposes", 0)
        p.mapping_errors = state.get("mapping_errors", 0)
        if p.objects is not None:
            p._objects_view = list(state.get("objects_view", p.objects.objects))
        for results in state.get("pending_mapping", []):
            p._pending.append({})
            for name, result in results.items():
                p._pending[-1][name] = Future()
                p._pending[-1][name].set_result(result)
        return p
