"""The viewer's own thread: it polls a running ``ServiceNode`` and logs what changed to a ``ViewerSink``.

The pipeline never waits for the viewer. The feed reads the node's immutable ``summary`` (replaced after every
frame) and, at most ``viewer.max_rate_hz`` times a second, ``node.trajectories()``; a frame processed between two
updates is simply not shown on its own (the map keeps it). The only lock the feed takes is the core's, for the
trajectories and map points, and it keeps its share of the time under ``1 / LOCK_BUDGET``. A sink that blocks (a
viewer that stops reading) stalls this thread alone. Colour and depth come from a second subscriber on the frames'
key that keeps the last ``TAP_FRAMES`` messages undecoded; at a keyframe the matching one is logged as it came.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from evaluation.trajectory_metrics import evaluate
from graph.trajectory import Trajectory
from perception.frame import CameraModel
from service.config import ViewerSettings
from service.map_summary import MapSummary
from service.protocol import FrameRejected, Inspected, inspect_message, split_message
from service.viewer import ViewerSink, ViewerUpdate
from service.viewer_connect import Outlets, open_outlets

if TYPE_CHECKING:
    import zenoh

    from service.node import ServiceNode

log = logging.getLogger(__name__)

TAP_FRAMES = 16  # raw messages kept to find a keyframe's images (frames in flight: run keeps 8)
LOCK_BUDGET = 20  # wait at least 20 x the time the core lock was held before taking it again
POINTS_PERIOD_S = 2.0
CLOSE_TIMEOUT_S = 10.0


def graph_key(summary: MapSummary) -> tuple[Any, ...]:
    """What moves the optimised trajectory: keyframes and factors added, loops, the window rolling."""
    c = summary.counts
    return (c.get("keyframes"), c.get("factors"), str(c.get("loop_closures")), str(c.get("graph_window")))


def aligned_truth(trajectory: Trajectory, truth: Trajectory | None) -> np.ndarray | None:
    """Ground-truth positions in the trajectory's frame (the SE(3) alignment of the ATE), or None."""
    error = evaluate(trajectory, truth) if truth is not None else None
    if error is None or truth is None:
        return None
    inv = np.linalg.inv(error.alignment)
    return np.asarray(truth.poses[:, :3, 3] @ inv[:3, :3].T + inv[:3, 3])


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
        self._tap: deque[Any] = deque(maxlen=TAP_FRAMES)
        self._subscriber: Any = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="objslam-viewer", daemon=True)
        self._last: MapSummary | None = None
        self._graph: tuple[Any, ...] | None = None
        self._imaged_keyframes = 0
        self._points_due = 0.0
        self._closed = False

    def start(self, session: zenoh.Session | None = None) -> ViewerFeed:
        """Subscribe to the frames' images (with ``viewer.images``) and start the thread."""
        if session is not None and self.settings.images:
            self._subscriber = session.declare_subscriber(f"{self.node.prefix}/rgbd", self._on_frame)
        self._thread.start()
        return self

    def _on_frame(self, sample: Any) -> None:
        self._tap.append(sample.payload)  # kept undecoded: zenoh's callback thread does nothing else

    def _loop(self) -> None:
        period = 1.0 / self.settings.max_rate_hz
        due = time.monotonic()
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            started = time.monotonic()
            try:
                held = self.update()
            except Exception:  # the viewer must never take the service down
                log.exception("viewer update failed")
                held = 1.0
            due = started + max(period, LOCK_BUDGET * held)
        try:  # the final map: objects after the last clustering, map points, the aligned ground truth
            self.update(final=True)
        except Exception:
            log.exception("viewer: the final update failed")
        if self.outlets is not None:
            self.outlets.flush()

    def update(self, final: bool = False) -> float:
        """Log what changed since the last update; the seconds the core lock was held."""
        summary = self.node.summary
        if summary is self._last and not final:
            return 0.0
        frame = self.node.stats.processed
        t0 = time.monotonic()
        trajectory, odometry = self.node.trajectories()
        points = None
        if final or (self._points_due <= t0 and summary is not self._last):
            with self.node.hold_core():
                points = self.node.core.cloud()
            self._points_due = t0 + POINTS_PERIOD_S
        held = time.monotonic() - t0
        newest = trajectory if len(trajectory) else odometry
        when = float(newest.timestamps[-1]) if len(newest) else 0.0
        moved = final or graph_key(summary) != self._graph
        update = ViewerUpdate(
            frame=frame,
            time=when,
            summary=summary,
            pose=newest.poses[-1] if len(newest) else None,
            trajectory=trajectory if moved else None,
            odometry=odometry if moved else None,
            message=self._keyframe_message(summary, when) if len(newest) else None,
            points=points,
            ground_truth=aligned_truth(trajectory, self.ground_truth) if final else None,
        )
        self.sink.log(update)
        self._last, self._graph = summary, graph_key(summary)
        self.updates += 1
        return held

    def _keyframe_message(self, summary: MapSummary, when: float) -> Inspected | None:
        """The newest frame's message, once per keyframe added, when it is still in the tap."""
        keyframes = int(summary.counts.get("keyframes", 0))
        if keyframes <= self._imaged_keyframes:
            return None
        for payload in reversed(list(self._tap)):
            data = payload.to_bytes()
            try:
                header, _ = split_message(data)
                if float(header.get("timestamp", -1.0)) != when:
                    continue
                message = inspect_message(data, self.node.limits)
            except (FrameRejected, TypeError, ValueError):
                continue
            self._imaged_keyframes = keyframes
            self.images += 1
            return message
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
        log.info("viewer: %d updates of %d frames, %d with images", self.updates, frames, self.images)


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
