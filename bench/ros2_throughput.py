"""``objslam bench throughput --ros2``: the ROS 2 ingest path against protocol v1 on the same frames.

Both runs publish the same frames at max rate into ``objslam serve`` (a subprocess behind a zenoh router in this
process) with queues that hold them all, and time first publish to last frame in the graph. Protocol v1 sends
each frame as one message (JPEG colour, 16-bit PNG depth, as ``objslam replay`` does); ROS 2 sends what a camera
driver, an odometry node and a detector on rmw_zenoh send: raw ``sensor_msgs/Image`` colour (rgb8) and depth
(16UC1), ``CameraInfo``, ``nav_msgs/Odometry`` and ``vision_msgs/Detection2DArray``, as CDR on rmw_zenoh keys,
which ``serve --ros2`` pairs by stamp. The frames carry the same odometry and detections both ways (a frame
without detections would run the detector), and both publish reliably, blocking when congested.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import zenoh
from rich.console import Console

from bench.report import load_note, markdown_table, record, show_table
from bench.rig import free_port, query_status, router, start_serve, stop_serve, wait_for_status
from bench.throughput import ROBOT, serve_and_publish
from service.protocol import encode_frame
from sources import open_dataset
from sources.ros2 import keys, messages

TOPICS = {"rgb": "/camera/color/image_raw", "depth": "/camera/depth/image_raw", "info": "/camera/color/camera_info"}
ODOM = "/odom"
DETECTIONS = "/detections"
RATIO_TARGET = 0.9  # ROS 2 throughput within 10 % of protocol v1
ROUNDS = 3  # runs of each path; the table shows the medians
STALL_S = 10.0  # no frame completed for this long: the frames still missing were lost (processed / published)


def ros2_messages(frame) -> list[tuple[str, str, bytes]]:
    """(topic, type, CDR) of one frame as a camera driver, an odometry node and a detector on rmw_zenoh publish it."""
    t, fid = frame.timestamp, "camera_color_optical_frame"
    out = [(TOPICS["info"], messages.CAMERA_INFO, messages.encode_camera_info(t, fid, frame.camera))]
    if frame.odometry is not None:
        out.append((ODOM, messages.ODOMETRY, messages.encode_odometry(t, "odom", fid, frame.odometry)))
    if frame.detections is not None:
        out.append((DETECTIONS, messages.DETECTIONS, messages.encode_detections(t, fid, frame.detections)))
    out.append((TOPICS["depth"], messages.IMAGE, messages.encode_image(t, fid, frame.depth, "16UC1")))
    out.append((TOPICS["rgb"], messages.IMAGE, messages.encode_image(t, fid, frame.rgb, "rgb8")))
    return out


def _serve_ros2(batches: list[list[tuple[str, str, bytes]]]) -> tuple[dict, float]:
    """``serve --ros2`` in a subprocess; publish every frame's messages at once; (final status, seconds)."""
    port = free_port()
    session = router(port)
    n = len(batches)
    topics = {topic: typename for batch in batches for topic, typename, _ in batch}
    env = {
        "OBJSLAM_INGEST__QUEUE_SIZE": str(n + 1),
        "OBJSLAM_ROS2__ENABLED": "true",
        "OBJSLAM_ROS2__RGB_TOPIC": TOPICS["rgb"],
        "OBJSLAM_ROS2__DEPTH_TOPIC": TOPICS["depth"],
        "OBJSLAM_ROS2__CAMERA_INFO_TOPIC": TOPICS["info"],
        "OBJSLAM_ROS2__QUEUE_MESSAGES": str(len(topics) * n + 8),
        "OBJSLAM_ROS2__QUEUE_BYTES": str(sum(len(p) for batch in batches for _, _, p in batch) + 2**20),
    }
    if ODOM in topics:
        env["OBJSLAM_ROS2__ODOM_TOPIC"] = ODOM
    if DETECTIONS in topics:
        env["OBJSLAM_ROS2__DETECTIONS_TOPIC"] = DETECTIONS
    serve, log = start_serve(f"tcp/127.0.0.1:{port}", ROBOT, env)
    key = f"objslam/{ROBOT}/status"
    try:
        wait_for_status(session, key, serve, log)
        pubs = {
            topic: session.declare_publisher(
                keys.ros_key(0, topic, typename, keys.type_hash(typename)),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            for topic, typename in topics.items()
        }
        time.sleep(0.5)  # the service's subscribers are known
        start = time.monotonic()
        for seq, batch in enumerate(batches, start=1):
            for topic, _, payload in batch:
                attachment = keys.encode_attachment(keys.Attachment(seq, time.time_ns(), bytes(16)))
                pubs[topic].put(payload, attachment=attachment)
        status, elapsed = _until_done(session, key, n, start)
    finally:
        stop_serve(serve)
        session.close()
        log.unlink(missing_ok=True)
    return status, elapsed


def _until_done(session: zenoh.Session, key: str, n: int, start: float) -> tuple[dict, float]:
    """The status once every frame was processed, rejected or lost in pairing, and the seconds from ``start``
    to then; when nothing completes for ``STALL_S``, to the last frame completed (the others were lost)."""
    done, at = -1, time.monotonic()
    while True:
        status = query_status(session, key)
        if status is not None:
            ros2 = status.get("ros2", {})
            lost = max(ros2.get("unpaired_color", 0), ros2.get("unpaired_depth", 0))
            now = status["frames_processed"] + status["frames_rejected_total"] + lost
            if now != done:
                done, at = now, time.monotonic()
            if done >= n:
                return status, at - start
        if status is not None and time.monotonic() - at > STALL_S:
            return status, at - start
        time.sleep(0.02)


def _runs(v1: list[bytes], ros: list[list[tuple[str, str, bytes]]]) -> tuple[list[dict], list[dict], list[float]]:
    """``ROUNDS`` runs of each path, alternating which goes first (a shared machine's load drifts): the runs'
    results (status and frames/s) of protocol v1 and of ROS 2, and the load averages seen."""
    results: dict[str, list[dict]] = {"v1": [], "ros2": []}
    load = [os.getloadavg()[0]]
    for round_ in range(ROUNDS):
        for path in ("v1", "ros2") if round_ % 2 == 0 else ("ros2", "v1"):
            if path == "v1":
                status, _, seconds = serve_and_publish(v1, None)
            else:
                status, seconds = _serve_ros2(ros)
            results[path].append({"status": status, "fps": status["frames_processed"] / seconds})
            load.append(os.getloadavg()[0])
    return results["v1"], results["ros2"], load


def _median_run(runs: list[dict]) -> dict:
    return sorted(runs, key=lambda r: r["fps"])[len(runs) // 2]


def run_ros2_throughput(console: Console, dataset: str, frames: int, write: Path | None) -> dict:
    """Measure both paths on the same frames, print the table and record it (block ``throughput_ros2``)."""
    data = open_dataset(dataset)
    frames = min(frames, len(data))
    loaded = [data.frame(i) for i in range(frames)]
    v1 = [encode_frame(f) for f in loaded]
    ros = [ros2_messages(f) for f in loaded]
    v1_runs, ros_runs, load = _runs(v1, ros)
    v1_run, ros_run = _median_run(v1_runs), _median_run(ros_runs)
    ratio = ros_run["fps"] / v1_run["fps"]
    mb = sum(len(p) for batch in ros for _, _, p in batch) / frames / 1e6
    header = [
        "path",
        "processed / published",
        "wire MB per frame",
        f"throughput (frames/s, median of {ROUNDS})",
        "runs (frames/s)",
        "decode p50 (ms)",
    ]
    rows = [
        _row("protocol v1 (JPEG + PNG16)", v1_runs, frames, sum(map(len, v1)) / frames / 1e6),
        _row(
            "ROS 2 on rmw_zenoh keys (raw Image rgb8 + 16UC1, CameraInfo, Odometry, Detection2DArray)",
            ros_runs,
            frames,
            mb,
        ),
        ["**ROS 2 / protocol v1**", "", "", f"**{ratio:.2f}** (target >= {RATIO_TARGET})", "", ""],
    ]
    show_table(console, "ROS 2 ingest throughput against protocol v1", header, rows)
    counters = {k: v for k, v in ros_run["status"].get("ros2", {}).items() if isinstance(v, int)}
    notes = (
        "Max rate into queues that hold every frame; throughput = frames / (first publish to last frame in the "
        f"graph), the median of {ROUNDS} runs of each path taken in turns. Both paths' frames carry the same "
        "odometry and detections, and both publishers are reliable and block when congested. The ROS 2 path "
        "checks the CDR and pairs colour and depth by stamp on its own thread, then hands the pair to the same "
        "validation as protocol v1 (as raw rgb8 / u16le, so `decode` there is a copy). Counters of the median "
        f"ROS 2 run: {counters}." + load_note(sum(load) / len(load))
    )
    path = record(
        "throughput_ros2",
        "ROS 2 ingest throughput",
        f"objslam bench throughput --ros2 --frames {frames} --dataset '{dataset}'",
        markdown_table(header, rows),
        notes,
        write,
    )
    console.print(f"recorded in {path}")
    return {"v1_fps": v1_run["fps"], "ros2_fps": ros_run["fps"], "ratio": ratio}


def _row(name: str, runs: list[dict], frames: int, mb: float) -> list[str]:
    median = _median_run(runs)
    return [
        name,
        f"{min(r['status']['frames_processed'] for r in runs)} / {frames}",
        f"{mb:.2f}",
        f"{median['fps']:.1f}",
        ", ".join(f"{r['fps']:.1f}" for r in runs),
        f"{median['status']['latency']['decode']['p50_ms']:.1f}",
    ]
