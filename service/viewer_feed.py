"""The viewer's own thread: it polls a running ``ServiceNode`` and logs what changed to a ``ViewerSink``.

The pipeline never waits for the viewer. The feed reads the node's immutable ``summary`` (replaced after every
frame) and, at most ``viewer.max_rate_hz`` times a second, copies what is new in the core (``CoreTracks``): the
records of the frames processed since its last copy and, only when the graph moved, the keyframe poses. It never
waits for the core lock: when the worker holds it, the feed tries again ``RETRY_S`` later. Its time (its own CPU
time and the time it held the lock) is kept under ``1 / CPU_BUDGET`` of the wall time, so at max rate it updates
less often; a frame processed between two updates is not shown on its own (the map keeps it). A sink that blocks
(a viewer that stops reading) stalls this thread alone. Colour and depth come from a second subscriber on the
frames' key that keeps the last ``TAP_FRAMES`` messages undecoded; a keyframe's own message is found there by
its timestamp and logged as it came, with the keyframe's detection boxes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from evaluation.trajectory_metrics import evaluate
from graph.trajectory import Trajectory
from perception.frame import CameraModel, Detection
from service.config import ViewerSettings
from service.map_summary import MapSummary
from service.protocol import FrameRejected, Inspected, inspect_message, split_message
from service.viewer import ViewerSink, ViewerUpdate
from service.viewer_connect import Outlets, open_outlets

if TYPE_CHECKING:
    import zenoh

    from service.node import ServiceNode
    from slam.core import SlamCore

log = logging.getLogger(__name__)

TAP_FRAMES = 16  # raw messages kept to find a keyframe's images (frames in flight: run keeps 8)
CPU_BUDGET = 25  # the feed's CPU time and lock holding: at most 1/25 of the wall time
RETRY_S = 0.01  # the core lock was busy: try again after this long
POINTS_PERIOD_S = 2.0
CLOSE_TIMEOUT_S = 10.0
KEYFRAMES_KEPT = 4  # keyframes waiting for their image or their detection boxes


def aligned_truth(trajectory: Trajectory, truth: Trajectory | None) -> np.ndarray | None:
    """Ground-truth positions in the trajectory's frame (the SE(3) alignment of the ATE), or None."""
    error = evaluate(trajectory, truth) if truth is not None else None
    if error is None or truth is None:
        return None
    inv = np.linalg.inv(error.alignment)
    return np.asarray(truth.poses[:, :3, 3] @ inv[:3, :3].T + inv[:3, 3])


@dataclass
class Keyframe:
    """A keyframe the feed shows: its index and time, and where on the timelines its image was logged."""

    index: int
    timestamp: float
    logged_at: tuple[int, float] | None = None  # (frame, sensor time) of the update that logged its image
    boxes: list[Detection] | None = None  # the boxes logged with its image
    final: bool = False  # the boxes logged are the core's (nothing to log later)


class CoreTracks:
    """The frames' poses as the feed last copied them from the core: the records of new frames only, the keyframe
    poses (and which keyframes are tied to the map) only when the graph moved. ``take`` runs under the core lock
    and copies references; ``trajectories`` composes the poses afterwards, without it."""

    def __init__(self) -> None:
        self.seen = 0  # records copied
        self.graph_key: tuple[Any, ...] | None = None
        self.kf_poses = np.zeros((0, 4, 4))
        self.tied = np.zeros(0, bool)
        self._new: list[Any] = []
        self._new_keyframes: list[Keyframe] = []
        self._keyframes_seen = 0
        self._columns: dict[str, list[np.ndarray]] = {k: [] for k in ("t", "kf", "rel", "odom", "posed")}

    def take(self, core: SlamCore) -> bool:
        """Copy what changed in ``core`` (its lock held); True when the graph moved since the last copy."""
        self._new = core.records[self.seen :]
        self.seen += len(self._new)
        stamps = core.kf_stamps  # live, a keyframe made beside the tracking has no keyframe record of its own
        self._new_keyframes = [Keyframe(k, float(stamps[k])) for k in range(self._keyframes_seen, len(stamps))]
        self._keyframes_seen = len(stamps)
        graph = core.graph
        key = (graph.updates, graph.num_keyframes, graph.start, graph.global_solves)
        if key == self.graph_key:
            return False
        self.graph_key, self.kf_poses = key, graph.poses()
        segments = core.segments
        every = not segments.unjoined()
        self.tied = np.array([every or segments.tied(k) for k in range(len(self.kf_poses))], bool)
        return True

    def new_keyframes(self) -> list[Keyframe]:
        """The keyframes among the frames copied by the last ``take``."""
        return self._new_keyframes

    def trajectories(self) -> tuple[Trajectory, Trajectory]:
        """(optimised poses of the frames tied to the map, odometry of every posed frame), as ``node.trajectories``."""
        if self._new:
            new, self._new = self._new, []
            for name, values in (
                ("t", [r.timestamp for r in new]),
                ("kf", [r.keyframe for r in new]),
                ("rel", [r.from_keyframe for r in new]),
                ("odom", [r.odometry for r in new]),
                ("posed", [r.posed for r in new]),
            ):
                self._columns[name].append(np.asarray(values))
        c = {k: self._join(k) for k in self._columns}
        if not len(c["t"]):
            empty = Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
            return empty, empty
        posed = c["posed"].astype(bool)
        known = c["kf"] < len(self.kf_poses)
        tied = posed & known
        tied[tied] = self.tied[c["kf"][tied]]
        optimised = Trajectory(c["t"][tied], self.kf_poses[c["kf"][tied]] @ c["rel"][tied])
        return optimised, Trajectory(c["t"][posed], c["odom"][posed])

    def _join(self, name: str) -> np.ndarray:
        parts = self._columns[name]
        if len(parts) > 1:
            self._columns[name] = parts = [np.concatenate(parts)]
        return parts[0] if parts else np.zeros(0)


class ViewerFeed:
    """Feeds ``sink`` from ``node`` on the thread ``objslam-viewer`` until ``close``."""

    def __init__(
        self,
        node: ServiceNode,
        sink: ViewerSink,
        settings: ViewerSettings,
        outlets: Outlets | None = None,
        ground_truth: Trajectory | None = None,
    ):
        self.node, self.sink, self.settings, self.outlets = node, sink, settings, outlets
        self.ground_truth = ground_truth
        self.updates = 0  # updates logged
        self.images = 0  # keyframe images logged
        self.busy = 0  # tries that found the core lock held by the worker
        self.held = 0.0  # seconds the last update held the core lock
        self.cpu = 0.0  # the feed thread's CPU seconds
        self.tracks = CoreTracks()
        self._tap: deque[list[Any]] = deque(maxlen=TAP_FRAMES)  # [payload, its timestamp once read]
        self._subscriber: Any = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="objslam-viewer", daemon=True)
        self._last: MapSummary | None = None
        self._keyframes: list[Keyframe] = []  # the newest ones, to show or showing
        self._points_due = 0.0
        self._closed = False

    def start(self, session: zenoh.Session | None = None) -> ViewerFeed:
        """Subscribe to the frames' images (with ``viewer.images``) and start the thread."""
        if session is not None and self.settings.images:
            self._subscriber = session.declare_subscriber(f"{self.node.prefix}/rgbd", self._on_frame)
        self._thread.start()
        return self

    def _on_frame(self, sample: Any) -> None:
        self._tap.append([sample.payload, None])  # kept undecoded: zenoh's callback thread does nothing else

    def _loop(self) -> None:
        period = 1.0 / self.settings.max_rate_hz
        due = time.monotonic()
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            started, cpu = time.monotonic(), time.thread_time()
            try:
                taken = self.update()
                cost = time.thread_time() - cpu + self.held
            except Exception:  # the viewer must never take the service down
                log.exception("viewer update failed")
                taken, cost = True, 1.0
            due = started + (max(period, CPU_BUDGET * cost) if taken else RETRY_S)
        self.cpu = time.thread_time()
        try:  # the final map: objects after the last clustering, map points, the aligned ground truth
            self.update(final=True)
        except Exception:
            log.exception("viewer: the final update failed")
        if self.outlets is not None:
            self.outlets.flush()

    def update(self, final: bool = False) -> bool:
        """Log what changed since the last update; False when the worker held the core lock (nothing logged).
        ``final`` waits for the lock."""
        summary = self.node.summary
        if summary is self._last and not final:
            return True
        lock = self.node.hold_core()
        if not lock.acquire(blocking=final):
            self.busy += 1
            return False
        t0 = time.perf_counter()
        try:  # references only: the poses are composed and the images found after the lock is released
            core = self.node.core
            moved = self.tracks.take(core) or final
            self._keyframes = (self._keyframes + self.tracks.new_keyframes())[-KEYFRAMES_KEPT:]
            boxes = {k.index: core.keyframe_detections.get(k.index) for k in self._keyframes}
            points = core.cloud() if final or self._points_due <= time.monotonic() else None
        finally:
            lock.release()
        self.held = time.perf_counter() - t0
        if points is not None:  # every POINTS_PERIOD_S, or less often when a copy of them holds the lock long
            self._points_due = time.monotonic() + max(POINTS_PERIOD_S, CPU_BUDGET * self.held)
        trajectory, odometry = self.tracks.trajectories()
        newest = trajectory if len(trajectory) else odometry
        when = float(newest.timestamps[-1]) if len(newest) else 0.0
        frame = self.node.stats.processed
        late = self._late_boxes(boxes)
        message, detections = self._keyframe_message(boxes, frame, when)
        update = ViewerUpdate(
            frame=frame,
            time=when,
            summary=summary,
            pose=newest.poses[-1] if len(newest) else None,
            trajectory=trajectory if moved else None,
            odometry=odometry if moved else None,
            message=message,
            detections=detections,
            late_boxes=late,
            points=points,
            ground_truth=aligned_truth(trajectory, self.ground_truth) if final else None,
        )
        self.sink.log(update)
        self._last = summary
        self.updates += 1
        return True

    def _keyframe_message(
        self, boxes: dict[int, list[Detection] | None], frame: int, when: float
    ) -> tuple[Inspected | None, list[Detection] | None]:
        """The message of the newest keyframe not shown yet, when it is still in the tap, and its boxes: the
        core's detections of it, else (the core's not ready yet: logged later) the ones the frame carried."""
        shown = max((i for i, k in enumerate(self._keyframes) if k.logged_at is not None), default=-1)
        for i in range(len(self._keyframes) - 1, shown, -1):
            keyframe = self._keyframes[i]
            message = self._tapped(keyframe.timestamp)
            if message is None:
                continue
            keyframe.logged_at = (frame, when)
            del self._keyframes[:i]  # older ones are skipped: drop frames to the viewer, never to the map
            self.images += 1
            core_boxes = boxes.get(keyframe.index)
            keyframe.boxes = core_boxes if core_boxes is not None else message.detections or []
            keyframe.final = core_boxes is not None
            return message, keyframe.boxes
        return None, None

    def _late_boxes(self, boxes: dict[int, list[Detection] | None]) -> tuple[int, float, list[Detection]] | None:
        """The core's boxes of the keyframe shown last, when they came after its image and differ from the
        frame's own: to be logged at the image's time."""
        for keyframe in reversed(self._keyframes):
            if keyframe.logged_at is None or keyframe.final:
                continue
            found = boxes.get(keyframe.index)
            if found is None:
                return None
            keyframe.final = True
            return (*keyframe.logged_at, found) if found != keyframe.boxes else None
        return None

    def _tapped(self, timestamp: float) -> Inspected | None:
        """The tapped message of the frame at ``timestamp``, inspected (its images still encoded); each message's
        header is read once."""
        for entry in reversed(list(self._tap)):
            payload, stamp = entry
            data = None
            if stamp is None:
                data = payload.to_bytes()
                try:
                    stamp = float(split_message(data)[0].get("timestamp", -1.0))
                except (FrameRejected, TypeError, ValueError):
                    stamp = -1.0
                entry[1] = stamp
            if stamp == timestamp:
                try:
                    return inspect_message(data if data is not None else payload.to_bytes(), self.node.limits)
                except (FrameRejected, TypeError, ValueError):
                    return None
        return None

    def close(self, timeout: float | None = None) -> None:
        """Stop polling; the thread logs the final map and flushes the recording. A sink still blocked after
        ``timeout`` seconds (``CLOSE_TIMEOUT_S``) is left behind, the web viewer stopped all the same."""
        if self._closed:
            return
        self._closed = True
        if self._subscriber is not None:
            self._subscriber.undeclare()
        self._stop.set()
        self._thread.join(timeout=CLOSE_TIMEOUT_S if timeout is None else timeout)
        if self._thread.is_alive():
            log.warning("viewer: the sink is blocked; the recording may lack the final map")
        if self.outlets is not None:
            self.outlets.stop_web()
        frames = self.node.stats.processed
        log.info(
            "viewer: %d updates of %d frames, %d with images; %.2f s CPU until closed, the core busy at %d tries",
            self.updates,
            frames,
            self.images,
            self.cpu,
            self.busy,
        )


def open_viewer(
    node: ServiceNode,
    session: zenoh.Session | None,
    settings: ViewerSettings,
    rrd: Path | None,
    camera: CameraModel | None = None,
    ground_truth: Trajectory | None = None,
) -> ViewerFeed | None:
    """A feed from ``node`` to the recording ``rrd`` and the viewers ``settings`` ask for; None for none."""
    outlets = open_outlets(settings, rrd, node.settings.robot)
    if outlets is None:
        return None
    log.info("viewer: %s", ", ".join(outlets.names))
    return ViewerFeed(node, ViewerSink(outlets.recording, camera), settings, outlets, ground_truth).start(session)
