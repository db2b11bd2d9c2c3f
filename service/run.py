"""``objslam run`` and ``objslam serve``: the service on an embedded or networked zenoh session."""

from __future__ import annotations

import logging
import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.config import Settings
from service.node import ServiceNode
from service.outputs import EXIT_OUTPUTS_FAILED, OutputsError, check_output_dir, run_summary, write_outputs
from service.replay import Replayer, frame_publisher
from service.viewer_cli import run_rrd, viewer_wanted
from service.zenoh_session import open_session
from sources import Dataset, open_dataset

if TYPE_CHECKING:
    from service.viewer_feed import ViewerFeed

log = logging.getLogger(__name__)


def run_dataset(
    spec: str | Dataset,
    out: Path,
    settings: Settings,
    max_frames: int | None = None,
    camera_overrides: dict[str, float] | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Replay ``spec`` into a service on one embedded zenoh session and write the outputs into ``out``.

    The same ServiceNode as ``serve`` receives the frames through a zenoh subscriber. Zenoh delivers to the
    subscriber asynchronously, so the ingest queue's length does not show the frames still in flight; the
    replay instead keeps at most ``window`` frames published and not yet completed (processed, rejected or
    dropped), below the queue's capacity, so no frame is dropped.
    """
    check_output_dir(out, "out")  # before any work: a run must not end in a failure to write its results
    dataset = open_dataset(spec, camera_overrides, settings.camera.model_dump()) if isinstance(spec, str) else spec
    settings = settings.model_copy(update={"state_dir": None})  # a run starts a new map and keeps no snapshots
    session = open_session(settings.zenoh, "server", embedded=True)
    node = ServiceNode(settings, session)
    viewer: ViewerFeed | None = None
    try:
        node.start()
        rrd = run_rrd(settings, out)  # OUT/map.rrd by default
        if viewer_wanted(settings.viewer, rrd):
            from service.viewer_feed import open_viewer  # rerun only when wanted

            viewer = open_viewer(node, session, settings.viewer, rrd, dataset.camera, dataset.ground_truth)
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        window = max(1, min(8, node.queue.capacity // 2))
        published = 0

        def back_pressure() -> None:
            nonlocal published
            if not node.wait_completed(published + 1 - window, 60.0):
                log.warning("the service completed no frame for 60 s; publishing anyway")
            published += 1

        replayer = Replayer(
            dataset, pub.put, max_rate=True, max_frames=max_frames, before_publish=back_pressure, progress=progress
        )
        started = time.monotonic()
        result = replayer.run()
        if not node.wait_done(result.frames, timeout=120.0):
            log.warning("not every replayed frame reached the pipeline within 120 s")
        elapsed = time.monotonic() - started
        pub.undeclare()
        node.finish()
        if viewer is not None:
            viewer.close()
        status = node.status()
        summary = run_summary(dataset.name, result.frames, elapsed, status)
        traj, odom = node.trajectories()
        objects = node.objects_reply()["objects"]
        return write_outputs(
            out, traj, odom, summary, dataset.ground_truth, objects, node.loops_reply()["loops"], node.core.cloud()
        )
    finally:
        if viewer is not None:
            viewer.close()
        node.stop()
        session.close()


def serve(settings: Settings, stop: threading.Event | None = None) -> int:
    """Run the service until SIGINT / SIGTERM (or ``stop``); returns the exit code.

    With a state dir: resume from its newest good snapshot, write snapshots while running, and on
    shutdown a last snapshot and the outputs (SPEC section 4). Exit code 0, or ``EXIT_OUTPUTS_FAILED`` when
    some output files could not be written (each named in a log line; the others are written).
    """
    stop = stop or threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = open_session(settings.zenoh, "server", max_message_bytes=settings.ingest.max_payload_bytes)
    try:
        node = ServiceNode(settings, session)
    except BaseException:
        session.close()
        raise
    viewer: ViewerFeed | None = None
    if viewer_wanted(settings.viewer, settings.viewer.rrd):  # before the node answers: rerun's import takes the GIL
        from service.viewer_feed import open_viewer  # rerun only when wanted

        try:
            viewer = open_viewer(node, session, settings.viewer, settings.viewer.rrd)
        except BaseException:
            node.stop()
            session.close()
            raise
    bridge = None
    if settings.ros2.enabled:  # ROS 2 topics on rmw_zenoh keys (rosbags imported only then), in status from its
        from service.ros2_bridge import Ros2Bridge  # first answer: built before the node answers

        bridge = Ros2Bridge(node)
        bridge.start(session)  # before the node answers: a client that waits for status then publishes loses no frame
    node.start()
    log.info("objslam serve: robot %s on %s, listening %s", settings.robot, node.prefix, settings.zenoh.listen)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        if viewer is not None:
            viewer.close()
        if bridge is not None:
            bridge.stop()
        code = _shut_down(node, settings.state_dir)
        session.close()
        log.info("objslam serve: stopped")
    return code


def _shut_down(node: ServiceNode, state_dir: Path | None) -> int:
    """Stop the node (last snapshot) and write the outputs into the state dir: as many files as can be written."""
    try:
        node.stop()
    except Exception as exc:  # the outputs are still worth writing from the map in memory
        log.error("stopping the service failed: %s", " ".join(str(exc).split()))
    if state_dir is None:
        return 0
    try:
        node.write_outputs(Path(state_dir))
    except OutputsError as exc:
        log.error("%s", exc)
        return EXIT_OUTPUTS_FAILED
    return 0
