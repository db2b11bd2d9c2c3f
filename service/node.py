"""The service node: zenoh subscriber and queryables wired to the ingest queue and the SLAM core.

The subscriber callback inspects each message (``ingest.Gate``: no pixel decoded) and queues the valid ones; a
decoder thread decodes their images (releasing the GIL), handing at most two frames to the worker thread,
which runs the SLAM core. After each frame the worker publishes an immutable ``MapSummary``; the queryables
answer from it through a per-version reply cache (``service.replies``), never waiting for the frame being
processed. With a state directory the node resumes from its map store and checkpoints it every N keyframes
and on ``stop`` (``service.map_persistence``).
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from graph.pose_graph import SolverError
from graph.trajectory import Trajectory
from perception.frame import Frame
from service.config import Settings
from service.events import MapEvents
from service.ingest import Gate, IngestQueue, decode_counted
from service.intake import Intake, MappingLag
from service.labels import LabelVocabulary
from service.map_persistence import Persistence, service_state
from service.map_summary import MapSummary, summarize
from service.node_queries import NodeQueries
from service.outputs import run_summary, write_outputs
from service.protocol import VERSION, FrameRejected, Reason
from service.save_requests import SaveRequests
from service.scheduler import ThreadedRunner
from service.stats import ServiceStats
from slam.build import build_core
from slam.core import LIVE_MAX_PENDING, MAPPING_LAG
from slam.parts import core_parts
from slam.runner import idle
from slam.snapshot import restore_core

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.001


class ServiceNode(NodeQueries):
    """One robot's mapping service on a zenoh session, under ``<key_prefix>/<robot>/``."""

    def __init__(self, settings: Settings, session: zenoh.Session):
        self.settings = settings
        self.session = session
        self.prefix = settings.key_prefix
        self.queue = IngestQueue(settings.ingest.queue_size)
        self.stats = ServiceStats()
        self.core = build_core(settings, ThreadedRunner())  # keyframe stages on the scheduler's threads
        self.limits = settings.ingest  # the decoder's bounds are fields of the ingest section
        self._lock = threading.Lock()  # guards the SLAM core between the worker and the trajectory queryable
        self._summary_lock = threading.Lock()  # guards only the swap of ``_summary`` (and its version)
        self._summary, self._summary_version = MapSummary(), 0
        self._stop = threading.Event()
        self._frame_done = threading.Condition()  # notified after each frame is processed, rejected or failed
        self.intake = Intake(settings.ingest, self.queue, self._stop, self._completed_one)  # in order or live
        self.mapping_lag = MappingLag()
        self.service_id = str(session.zid())
        self.saves = SaveRequests(settings, self.service_id, self.write_outputs)
        self.labels = LabelVocabulary(self.limits.labels, self.limits.extra_labels, self.limits.max_detections)
        self.gate = Gate(self.limits, self.stats)
        self.replies = self._replies(self.limits)
        self._last_frame_at = time.monotonic()  # when the worker last took a frame
        self._saved_completed = 0  # frames completed (processed, rejected, failed, dropped) in the newest snapshot
        self.events = MapEvents()
        self.status_sections: dict[str, Callable[[], Any]] = {}  # more parts of ``status`` (the ROS 2 bridge's)
        self._started = time.time()
        self._entities: list[Any] = []
        self._decoder = threading.Thread(target=self._decode_loop, name="objslam-decoder", daemon=True)
        self._worker = threading.Thread(target=self._work, name="objslam-worker", daemon=True)
        self.persistence: Persistence | None = None
        if settings.state_dir is not None:
            ps = settings.persistence
            self.persistence = Persistence(settings.state_dir, settings.robot, ps.every_keyframes, ps.keep)
            if self.persistence.resume(self._restore, service_state):
                self.core.begin_session(ps.session_gap_s)
        self.core.live = settings.ingest.live
        self._publish_summary()

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Declare the subscriber, queryables and events publisher, and start the worker."""
        # Four Python threads (zenoh callbacks, decoder, worker, mapping) share the GIL and a query waits for it
        # in steps of the switch interval: 1 ms rather than Python's 5 ms (`objslam bench overload`: status p99
        # 83-104 ms at 1 ms, 101 at 5 ms; 0.5 ms answered faster but processed fewer frames).
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        s, p = self.session, self.prefix
        self._entities.append(s.declare_subscriber(f"{p}/rgbd", self._on_frame))  # first: ``stop`` relies on it
        for name in self.replies.cached:
            self._entities.append(s.declare_queryable(f"{p}/{name}", self.replies.callback(name)))
        self._entities.append(s.declare_queryable(f"{p}/save", self.saves.enqueue))
        self.events.publisher = s.declare_publisher(f"{p}/events")
        self._entities.append(self.events.publisher)
        self.start_threads()
        log.info("serving %s (protocol v%d)", p, VERSION)

    def start_threads(self) -> None:
        """Start the decoder and the worker (``start`` does, after declaring the zenoh entities)."""
        self._decoder.start()
        self._worker.start()

    def stop_threads(self, timeout: float = 10.0) -> bool:
        """Stop the decoder and the worker after the current frame; True when both stopped in time."""
        self._stop.set()
        for thread in (self._decoder, self._worker):
            if thread.is_alive():
                thread.join(timeout=timeout)
        return not self.working

    @property
    def working(self) -> bool:
        """The worker thread is running."""
        return self._worker.is_alive()

    def hold_core(self) -> threading.Lock:
        """The lock the worker holds while the core processes a frame (``with node.hold_core(): ...``)."""
        return self._lock

    def stop(self) -> None:
        """Stop taking frames, stop the worker after the current frame, count the frames still queued as dropped,
        write a last snapshot, and undeclare the other zenoh entities."""
        if self._entities:  # the frame subscriber (declared first): nothing arrives after this
            self._undeclare(self._entities.pop(0))
        if not self.stop_threads():
            log.error("the worker did not stop within 10 s: no final snapshot, the last periodic one stands")
        else:
            self._discard_queued()
            self.snapshot(final=True)
            self.core.close()
        for entity in reversed(self._entities):
            self._undeclare(entity)
        self._entities.clear()

    @staticmethod
    def _undeclare(entity: Any) -> None:
        try:
            entity.undeclare()
        except zenoh.ZError as exc:  # already closed session
            log.debug("undeclare failed: %s", exc)

    def _discard_queued(self) -> None:
        """Frames received and still queued when the decoder and worker stopped: counted as dropped, so that
        after a restart every received frame is processed, rejected, failed or dropped."""
        left = self.intake.discard()
        if left:
            log.info("stopping with %d queued frames unprocessed: counted in frames_dropped", left)
        self.saves.refuse_all("the service is stopping (with a state directory it writes its outputs)")

    @property
    def completed(self) -> int:
        """Frames processed, rejected, failed or dropped: every received frame ends in one of these."""
        return self.stats.completed() + self.queue.dropped

    def wait_done(self, frames: int, timeout: float) -> bool:
        """Wait until ``frames`` frames have been received and each processed, rejected or dropped."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.stats.received >= frames and self.completed >= frames:
                return True
            time.sleep(0.005)
        return False

    def wait_completed(self, frames: int, timeout: float) -> bool:
        """Block until at least ``frames`` frames are completed (``run``'s back-pressure on frames in flight)."""
        with self._frame_done:
            return self._frame_done.wait_for(lambda: self.completed >= frames, timeout)

    # ------------------------------------------------------------ ingest

    def _on_frame(self, sample: zenoh.Sample) -> None:
        self.stats.count_received()
        if len(sample.payload) > self.limits.max_payload_bytes:  # refused before it is copied
            self.stats.count_rejected(Reason.TOO_LARGE.value)
            self._completed_one()
            return
        self.submit(sample.payload.to_bytes())

    def submit(self, payload: bytes) -> None:
        """Inspect a raw message and enqueue it when valid (what the subscriber callback does); never blocks.

        Everything that needs no pixel decoded is checked here, before queuing, so a flood of garbage or of
        decompression bombs is refused at once and never displaces a good frame from the queue."""
        received = time.monotonic()
        message = self.gate.admit(payload)
        if message is None:
            self._completed_one()
            return
        if self.queue.put(message, received):
            log.debug("ingest queue full: dropped the oldest frame")

    def _decode_loop(self) -> None:
        """Decoder thread: raw messages from the ingest queue, validated and decoded, to the worker."""
        while not self._stop.is_set():
            item = self.intake.take(timeout=0.1)
            if item is None:
                continue
            frame = decode_counted(item.message, self.stats)
            if frame is None:
                self._completed_one()
                continue
            self.intake.hand_over(self.labels.apply(frame), item.received)

    def _work(self) -> None:
        """Worker thread: decoded frames through the SLAM core, one at a time; ``save`` requests between them."""
        while not self._stop.is_set():
            self.saves.answer()
            taken = self.intake.next(timeout=0.1)
            if taken is None:
                if self.core.live and (self._catch_up(idle=True) or self._polish()):  # no frame: map what is ready
                    self._publish_summary()
                continue
            frame, received = taken
            self._last_frame_at = time.monotonic()
            try:
                self._process(frame, received)
            except Exception:  # the worker must survive anything a frame can trigger
                log.exception("unexpected error while processing a frame")
                self.stats.count_error("internal")
            finally:
                self._completed_one()

    def _polish(self) -> bool:
        """Live, no frame for ``ingest.polish_after_s`` and every keyframe mapped: the graph moved towards its
        batch optimum (``Graph.polish``: once per change of the graph, never waiting for the child), the map a
        paused robot or an ended stream leaves. True when the estimate moved."""
        after = self.limits.polish_after_s
        if not after or self.core.pending or time.monotonic() - self._last_frame_at < after:
            return False
        with self._lock:
            return self.core.graph.polish()

    def _completed_one(self) -> None:
        with self._frame_done:
            self._frame_done.notify_all()

    def _process(self, frame: Frame, received: float) -> None:
        t1 = time.monotonic()
        try:
            with self._lock:
                result = self.core.step(frame)
            t2 = time.monotonic()
            stage_times, added = result.timings, result.added
        except FrameRejected as exc:
            self.stats.count_rejected(exc.reason.value)
            log.debug("rejected frame: %s", exc)
            return
        except SolverError:
            self.stats.count_error("solver")
            return
        self.stats.time("graph", t2 - t1)
        for stage, seconds in stage_times.items():
            self.stats.time(stage, seconds)
        self.stats.time("ingest_to_graph", t2 - received)
        self.stats.count_processed()
        self.mapping_lag.frame(frame.timestamp, received, added)
        self._catch_up()
        self._publish_summary()
        self.events.publish(self.summary)
        self.snapshot()

    def _catch_up(self, idle: bool = False) -> bool:
        """Live: keyframe mapping finished since the frame's step goes into the map now, after its pose (a
        failure is a mapping error, not the frame's); ``idle`` (no frame coming): a keyframe being made beside
        the tracking is waited for and added too. Then the mapping lag of the keyframes mapped. True when the
        map changed."""
        timings, took = None, False
        if self.core.live:
            try:
                with self._lock:
                    took = idle and self.core.take_deferred()
                    timings = self.core.apply_ready()
            except Exception:
                log.exception("applying a keyframe's mapping failed")
                self.core.mapping_errors, took = self.core.mapping_errors + 1, True
            for stage, seconds in (timings or {}).items():
                self.stats.time(stage, seconds)
        for lag in self.mapping_lag.applied(len(self.core.kf_odometry) - len(self.core.pending), time.monotonic()):
            self.stats.time("mapping_lag", lag)
        return timings is not None or took

    # ------------------------------------------------------------ persistence

    def snapshot(self, final: bool = False) -> bool:
        """Checkpoint the map store when N keyframes were added since the last checkpoint (or, ``final``,
        anything changed). Called by the worker between frames, or after it stopped: no other thread changes
        the core, so only taking its parts needs the lock (iSAM2 updates a cache that queries read); encoding
        the new rows runs without it, writing them on the store's writer thread (``final``: waited for). A
        failed write is counted (``persistence.failed_writes``)."""
        p = self.persistence
        if p is None:
            return False
        keyframes, frames, completed = self.core.graph.num_keyframes, self.stats.processed, self.completed
        changed = p.changed(keyframes, frames) or completed != self._saved_completed  # rejected, dropped frames too
        lag = LIVE_MAX_PENDING if self.core.live else MAPPING_LAG  # live: never wait for mapping below that
        if not (p.due(keyframes, idle(self.core.pending), lag) or (final and changed)):
            return False
        t0 = time.perf_counter()
        with self._lock:
            small, logs = self._parts()
        if not p.save(small, logs, keyframes, frames, time.perf_counter() - t0, wait=final):
            return False
        self._saved_completed = completed
        self.stats.time("snapshot", time.perf_counter() - t0)
        return True

    def _parts(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """The core's parts (``slam.parts``) with the counters: small part, live logs. Queued frames are not in
        the core's state, so the saved ``received`` counts only the frames the state accounts for."""
        stats = self.stats.counters()
        stats["received"] = (
            stats["processed"] + sum(stats["rejected"].values()) + sum(stats["errors"].values()) + self.queue.dropped
        )
        parts = core_parts(self.core)
        small = {
            "pipeline": parts.small,
            "stats": stats,
            "frames_dropped": self.queue.dropped,
            "frames_stale": self.queue.stale,
            "settings": self.settings.map_sections(),
        }
        return small, parts.logs

    def _restore(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint's (or an old snapshot's) state, built whole before anything is replaced."""
        saved, current = state["settings"], self.settings.map_sections()
        changed = sorted(k for k in saved.keys() | current.keys() if saved.get(k) != current.get(k))
        if changed:
            log.warning(
                "resuming a map made with other settings of %s; the current ones apply from now on", ", ".join(changed)
            )
        core = restore_core(self.settings, state["pipeline"], ThreadedRunner())
        self.core.close()
        self.core = core
        self.stats.restore_counters(state["stats"])
        self.queue.dropped, self.queue.stale = state["frames_dropped"], state.get("frames_stale", 0)
        self._saved_completed = self.completed
        accepted = {r.factor for r in core.loop_records() if r.accepted and r.factor is not None}
        self.events.resume(core.object_map_version, accepted)

    def _publish_summary(self) -> None:
        """Take the map's counts, objects and loop records for the queryables (worker thread, between frames)."""
        summary = summarize(self.core, self._summary)
        with self._summary_lock:
            self._summary = summary
            self._summary_version += 1

    @property
    def summary(self) -> MapSummary:
        with self._summary_lock:
            return self._summary

    def write_outputs(self, out: Path) -> dict[str, Any]:
        """The outputs of SPEC section 4 of the map as it stands, into ``out``; returns the summary."""
        traj, odom = self.trajectories()
        status = self.status()
        summary = run_summary(f"serve {self.prefix}", status["frames_received"], status["uptime_s"], status)
        with self._lock:  # iSAM2's estimate cache: not beside the worker (this may run on another thread)
            cloud = self.core.cloud()
        return write_outputs(
            out, traj, odom, summary, None, self.objects_reply()["objects"], self.loops_reply()["loops"], cloud
        )

    def finish(self) -> None:
        """End of a replayed sequence: final object clustering."""
        with self._lock:
            self.core.finish()
        self._publish_summary()

    def trajectories(self) -> tuple[Trajectory, Trajectory]:
        """(optimised poses of the frames tied to the map, odometry of every frame), taken consistently."""
        with self._lock:
            return self.core.trajectory(tied_only=True), self.core.odometry_trajectory()
