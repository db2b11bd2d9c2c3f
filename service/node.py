"""The service node: zenoh subscriber and queryables wired to the ingest queue and the pipeline.

Zenoh callbacks only enqueue bytes or serialise a reply; decoding and graph work run on one worker thread.
With a state directory the node resumes from its newest good snapshot and writes one every N keyframes
(on the worker thread, between frames) and on ``stop``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from typing import Any

import zenoh

from graph.geometry import pose_to_tum
from graph.pose_graph import SolverError
from service.config import Settings
from service.ingest import IngestQueue
from service.persistence import Persistence
from service.pipeline import Pipeline
from service.protocol import VERSION, FrameRejected, Limits, decode_frame
from service.sources.base import Trajectory
from service.stats import ServiceStats

log = logging.getLogger(__name__)


class ServiceNode:
    """One robot's mapping service on a zenoh session, under ``<key_prefix>/<robot>/``."""

    def __init__(self, settings: Settings, session: zenoh.Session):
        self.settings = settings
        self.session = session
        self.prefix = settings.key_prefix
        self.queue = IngestQueue(settings.ingest.queue_size)
        self.stats = ServiceStats()
        self.pipeline = Pipeline(settings)
        self.limits = Limits(settings.ingest.max_payload_bytes, settings.ingest.max_image_pixels)
        self._lock = threading.Lock()  # guards the pipeline between the worker and queryables
        self._stop = threading.Event()
        self._busy = False
        self._last_version = self._last_loops = 0
        self._started = time.time()
        self._entities: list[Any] = []
        self._worker = threading.Thread(target=self._work, name="objslam-worker", daemon=True)
        self.persistence: Persistence | None = None
        if settings.state_dir is not None:
            ps = settings.persistence
            self.persistence = Persistence(settings.state_dir, settings.robot, ps.every_keyframes, ps.keep)
            self.persistence.resume(self._restore)

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Declare the subscriber, queryables and events publisher, and start the worker."""
        s, p = self.session, self.prefix
        self._entities.append(s.declare_subscriber(f"{p}/rgbd", self._on_frame))
        for name, handler in (("status", self.status), ("trajectory", self.trajectory_reply),
                              ("objects", self.objects_reply), ("loops", self.loops_reply)):
            self._entities.append(s.declare_queryable(f"{p}/{name}", self._replier(name, handler)))
        self.events = s.declare_publisher(f"{p}/events")
        self._entities.append(self.events)
        self._worker.start()
        log.info("serving %s (protocol v%d)", p, VERSION)

    def stop(self) -> None:
        """Stop the worker after the current frame, write a last snapshot, and undeclare zenoh entities."""
        self._stop.set()
        if self._worker.is_alive():
            self._worker.join(timeout=10)
        if len(self.queue):
            log.info("stopping with %d queued frames unprocessed", len(self.queue))
        if self._worker.is_alive():
            log.error("the worker did not stop within 10 s: no final snapshot, the last periodic one stands")
        else:
            self.snapshot(final=True)
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # already closed session
                log.debug("undeclare failed: %s", exc)
        self._entities.clear()

    def wait_done(self, frames: int, timeout: float) -> bool:
        """Wait until ``frames`` frames have been received and each processed, rejected or dropped."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            s = self.stats
            if s.received >= frames and len(self.queue) == 0 and not self._busy \
                    and s.processed + sum(s.rejected.values()) + self.queue.dropped + sum(s.errors.values()) >= frames:
                return True
            time.sleep(0.005)
        return False

    # ------------------------------------------------------------ ingest

    def _on_frame(self, sample: zenoh.Sample) -> None:
        self.stats.count_received()
        self.submit(sample.payload.to_bytes())

    def submit(self, payload: bytes) -> None:
        """Enqueue a raw message (what the subscriber callback does); never blocks."""
        if self.queue.put(payload):
            log.debug("ingest queue full: dropped the oldest frame")

    def _work(self) -> None:
        while not self._stop.is_set():
            item = self.queue.get(timeout=0.1)
            if item is None:
                continue
            self._busy = True
            try:
                self._process(item.payload, item.received)
            except Exception:  # the worker must survive anything a frame can trigger
                log.exception("unexpected error while processing a frame")
                self.stats.count_error("internal")
            finally:
                self._busy = False

    def _process(self, payload: bytes, received: float) -> None:
        t0 = time.monotonic()
        try:
            frame = decode_frame(payload, self.limits)
            t1 = time.monotonic()
            self.stats.time("decode", t1 - t0)
            with self._lock:
                self.pipeline.timings.clear()
                self.pipeline.process(frame)
                stage_times = dict(self.pipeline.timings)
            t2 = time.monotonic()
        except FrameRejected as exc:
            self.stats.count_rejected(exc.reason.value)
            log.debug("rejected frame: %s", exc)
            return
        except SolverError:
            self.stats.count_error("solver")
            return
        self.stats.time("graph", t2 - t1)
        self._publish_changes()
        for stage, seconds in stage_times.items():
            self.stats.time(stage, seconds)
        self.stats.time("ingest_to_graph", t2 - received)
        self.stats.count_processed()
        self.snapshot()

    # ------------------------------------------------------------ persistence

    def snapshot(self, final: bool = False) -> bool:
        """Write a snapshot when N keyframes were added since the last one (or, ``final``, anything changed).

        Called by the worker between frames, or after it stopped: no other thread changes the pipeline, so
        only taking its plain state needs the lock (iSAM2 updates a cache that queries read); pickling and
        writing run without it. A failed write is logged and counted (``persistence.failed_writes``).
        """
        p = self.persistence
        if p is None:
            return False
        keyframes, frames = self.pipeline.graph.num_keyframes, self.stats.processed
        if not (p.due(keyframes) or (final and p.changed(keyframes, frames))):
            return False
        t0 = time.perf_counter()
        with self._lock:
            state = self._state()
        payload = p.capture(keyframes, frames, state)
        capture_s = time.perf_counter() - t0
        if p.save(payload, keyframes, frames, capture_s) is None:
            return False
        self.stats.time("snapshot", time.perf_counter() - t0)
        return True

    def _state(self) -> dict[str, Any]:
        """The pipeline and the frame counters. Frames still queued are not in the pipeline's state, so the
        saved ``received`` counts only the frames the state accounts for."""
        stats = self.stats.counters()
        stats["received"] = stats["processed"] + sum(stats["rejected"].values()) + sum(stats["errors"].values()) \
            + self.queue.dropped
        return {"pipeline": self.pipeline.state(), "stats": stats, "frames_dropped": self.queue.dropped,
                "settings": _map_settings(self.settings)}

    def _restore(self, state: dict[str, Any]) -> None:
        """Continue from a snapshot's state (built completely before anything is replaced)."""
        saved, current = state["settings"], _map_settings(self.settings)
        changed = sorted(k for k in saved.keys() | current.keys() if saved.get(k) != current.get(k))
        if changed:
            log.warning("resuming a map made with other settings of %s; the current ones apply from now on",
                        ", ".join(changed))
        pipeline = Pipeline.from_state(self.settings, state["pipeline"])
        self.pipeline = pipeline
        self.stats.restore_counters(state["stats"])
        self.queue.dropped = state["frames_dropped"]
        self._last_version = pipeline.object_map_version
        self._last_loops = pipeline.loops.n_accepted if pipeline.loops is not None else 0

    def _publish_changes(self) -> None:
        """``events``: the object map after each re-clustering, and each newly accepted loop closure."""
        version = self.pipeline.object_map_version
        loops = self.pipeline.loops.n_accepted if self.pipeline.loops is not None else 0
        events = []
        if version != self._last_version:
            events.append({"type": "objects", "objects": self.pipeline.object_list()})
        if loops != self._last_loops:
            events.append({"type": "loop_closure", "accepted": loops,
                           "latest": [r for r in self.pipeline.loop_records() if r["accepted"]][-1:]})
        self._last_version, self._last_loops = version, loops
        for event in events:
            try:
                self.events.put(json.dumps(event).encode())
            except zenoh.ZError as exc:
                log.warning("could not publish event: %s", exc)

    # ------------------------------------------------------------ queries

    def _replier(self, name: str, handler):
        def reply(query: zenoh.Query) -> None:
            try:
                body = json.dumps(handler())
                query.reply(f"{self.prefix}/{name}", body.encode(), encoding=zenoh.Encoding.APPLICATION_JSON)
            except Exception as exc:  # a failing query must not take the service down
                log.exception("query %s failed", name)
                query.reply_err(json.dumps({"error": str(exc)}).encode())

        return reply

    def status(self) -> dict[str, Any]:
        """The ``status`` reply (schema in docs/protocol.md)."""
        snap = self.stats.snapshot()
        with self._lock:
            graph = self.pipeline.graph
            objects = self.pipeline.object_list()
            snap.update(keyframes=graph.num_keyframes, poses=graph.num_keyframes, factors=graph.num_factors,
                        tracking_lost=self.pipeline.tracking_lost, loop_closures=self._loop_counts(),
                        keyframe_detections_by_class=dict(self.pipeline.detections_by_class),
                        objects=len(objects), objects_by_class=dict(Counter(o["label"] for o in objects)))
        snap.update(
            robot=self.settings.robot,
            protocol_version=VERSION,
            frames_dropped=self.queue.dropped,
            queue_depth=len(self.queue),
            queue_capacity=self.queue.capacity,
            landmarks=0,
            uptime_s=round(time.time() - self._started, 3),
            persistence=self.persistence.status() if self.persistence is not None else None,
        )
        return snap

    def trajectory_reply(self) -> dict[str, Any]:
        """Optimised poses of every processed frame: ``{"frame": "world", "poses": [[t, tx..qw], ...]}``."""
        traj, _ = self.trajectories()
        rows = [[float(t), *map(float, pose_to_tum(T))] for t, T in zip(traj.timestamps, traj.poses)]
        return {"robot": self.settings.robot, "format": "t tx ty tz qx qy qz qw", "poses": rows}

    def finish(self) -> None:
        """End of a replayed sequence: final object clustering."""
        with self._lock:
            self.pipeline.finish()

    def trajectories(self) -> tuple[Trajectory, Trajectory]:
        """(optimised, odometry) trajectories of every processed frame, taken consistently."""
        with self._lock:
            return self.pipeline.trajectory(), self.pipeline.odometry_trajectory()

    def objects_reply(self) -> dict[str, Any]:
        """Objects as ellipsoids (SPEC section 4 fields)."""
        with self._lock:
            return {"robot": self.settings.robot, "objects": self.pipeline.object_list()}

    def loops_reply(self) -> dict[str, Any]:
        """Every loop-closure candidate with its verdict (SPEC section 4 fields)."""
        with self._lock:
            return {"robot": self.settings.robot, "loops": self.pipeline.loop_records()}

    def _loop_counts(self) -> dict[str, int]:
        loops = self.pipeline.loops
        if loops is None:
            return {"accepted": 0, "rejected": 0}
        return {"accepted": loops.n_accepted, "rejected": loops.n_rejected}


def _map_settings(settings: Settings) -> dict[str, Any]:
    """The settings sections that shape the map (not endpoints, queue or state dir), to compare on resume."""
    return settings.model_dump(mode="json", include={"keyframes", "odometry", "loops", "detector", "objects",
                                                     "graph", "camera"})
