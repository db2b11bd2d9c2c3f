"""``objslam bench throughput --ros2``: the ROS 2 ingest path against protocol v1 on the same frames.

Both runs publish the same frames at max rate into ``objslam serve`` (a subprocess behind a zenoh router in this
process) with queues that hold them all, and time first publish to last frame in the graph. Protocol v1 sends
each frame as one message (JPEG colour, 16-bit PNG depth, as ``objslam replay`` does); ROS 2 sends what a camera
driver on rmw_zenoh sends: raw ``sensor_msgs/Image`` colour (rgb8) and depth (16UC1), ``CameraInfo`` and
``nav_msgs/Odometry``, as CDR on rmw_zenoh keys, which ``serve --ros2`` pairs by stamp.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from rich.console import Console

from bench.report import load_note, markdown_table, record, show_table
from bench.rig import free_port, query_status, router, start_serve, stop_serve, wait_for_status
from bench.throughput import ROBOT, _serve_and_publish
from service.protocol import encode_frame
from sources import open_dataset
from sources.ros2 import keys, messages

TOPICS = {"rgb": "/camera/color/image_raw", "depth": "/camera/depth/image_raw", "info": "/camera/color/camera_info"}
ODOM = "/odom"
RATIO_TARGET = 0.9  # ROS 2 throughput within 10 % of protocol v1
DEADLINE_S = 60.0  # frames not in the graph by then were lost (the table shows processed / published)


def ros2_messages(frame) -> list[tuple[str, str, bytes]]:
    """(topic, type, CDR) of one frame as a camera driver and an odometry node on rmw_zenoh publish it."""
    t, fid = frame.timestamp, "camera_color_optical_frame"
    out = [
        (TOPICS["info"], messages.CAMERA_INFO, messages.encode_camera_info(t, fid, frame.camera)),
        (TOPICS["depth"], messages.IMAGE, messages.encode_image(t, fid, frame.depth, "16UC1")),
        (TOPICS["rgb"], messages.IMAGE, messages.encode_image(t, fid, frame.rgb, "rgb8")),
    ]
    if frame.odometry is not None:
        out.insert(1, (ODOM, messages.ODOMETRY, messages.encode_odometry(t, "odom", fid, frame.odometry)))
    return out


def _serve_ros2(batches: list[list[tuple[str, str, bytes]]]) -> tuple[dict, float]:
    """``serve --ros2`` in a subprocess; publish every frame's messages at once; (final status, seconds)."""
    port = free_port()
    session = router(port)
    n = len(batches)
    env = {
        "OBJSLAM_INGEST__QUEUE_SIZE": str(n + 1),
        "OBJSLAM_ROS2__ENABLED": "true",
        "OBJSLAM_ROS2__RGB_TOPIC": TOPICS["rgb"],
        "OBJSLAM_ROS2__DEPTH_TOPIC": TOPICS["depth"],
        "OBJSLAM_ROS2__CAMERA_INFO_TOPIC": TOPICS["info"],
        "OBJSLAM_ROS2__ODOM_TOPIC": ODOM,
        "OBJSLAM_ROS2__QUEUE_MESSAGES": str(5 * n + 8),
    }
    serve, log = start_serve(f"tcp/127.0.0.1:{port}", ROBOT, env)
    key = f"objslam/{ROBOT}/status"
    try:
        wait_for_status(session, key, serve, log)
        pubs = {}
        for topic, typename, _ in batches[0]:
            pubs[topic] = session.declare_publisher(keys.ros_key(0, topic, typename, keys.type_hash(typename)))
        time.sleep(0.5)  # the service's subscribers are known
        start = time.monotonic()
        for seq, batch in enumerate(batches, start=1):
            for topic, _, payload in batch:
                attachment = keys.encode_attachment(keys.Attachment(seq, time.time_ns(), bytes(16)))
                pubs[topic].put(payload, attachment=attachment)
        status, deadline = query_status(session, key), start + DEADLINE_S
        while status is None or status["frames_processed"] + status["frames_rejected_total"] < n:
            if time.monotonic() > deadline and status is not None:  # frames lost on the way: what arrived
                break
            time.sleep(0.02)
            status = query_status(session, key)
        elapsed = time.monotonic() - start
    finally:
        stop_serve(serve)
        session.close()
        log.unlink(missing_ok=True)
    return status, elapsed


def run_ros2_throughput(console: Console, dataset: str, frames: int, write: Path | None) -> dict:
    """Measure both paths on the same frames, print the table and record it (block ``throughput_ros2``)."""
    data = open_dataset(dataset)
    frames = min(frames, len(data))
    loaded = [data.frame(i) for i in range(frames)]
    v1 = [encode_frame(f) for f in loaded]
    ros = [ros2_messages(f) for f in loaded]
    load = [os.getloadavg()[0]]
    v1_status, _, v1_s = _serve_and_publish(v1, None)
    load.append(os.getloadavg()[0])
    ros_status, ros_s = _serve_ros2(ros)
    load.append(os.getloadavg()[0])
    v1_fps, ros_fps = v1_status["frames_processed"] / v1_s, ros_status["frames_processed"] / ros_s
    ratio = ros_fps / v1_fps
    mb = sum(len(p) for batch in ros for _, _, p in batch) / frames / 1e6
    header = ["path", "processed / published", "wire MB per frame", "throughput (frames/s)", "decode p50 (ms)"]
    rows = [
        [
            "protocol v1 (JPEG + PNG16)",
            f"{v1_status['frames_processed']} / {frames}",
            f"{sum(map(len, v1)) / frames / 1e6:.2f}",
            f"{v1_fps:.1f}",
            f"{v1_status['latency']['decode']['p50_ms']:.1f}",
        ],
        [
            "ROS 2 on rmw_zenoh keys (raw Image rgb8 + 16UC1, CameraInfo, Odometry)",
            f"{ros_status['frames_processed']} / {frames}",
            f"{mb:.2f}",
            f"{ros_fps:.1f}",
            f"{ros_status['latency']['decode']['p50_ms']:.1f}",
        ],
        ["**ROS 2 / protocol v1**", "", "", f"**{ratio:.2f}** (target >= {RATIO_TARGET})", ""],
    ]
    show_table(console, "ROS 2 ingest throughput against protocol v1", header, rows)
    notes = (
        "Max rate into queues that hold every frame; throughput = frames / (first publish to last frame in the "
        "graph). The ROS 2 path decodes CDR and pairs colour and depth by stamp on its own thread, then hands the "
        "pair to the same validation as protocol v1 (as raw rgb8 / u16le, so `decode` there is a copy). "
        f"Pairing counters of the ROS 2 run: {ros_status.get('ros2', {})}." + load_note(sum(load) / len(load))
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
    return {"v1_fps": v1_fps, "ros2_fps": ros_fps, "ratio": ratio}
