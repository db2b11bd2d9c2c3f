"""``objslam replay BAG_DIR --rgb-topic ...``: a rosbag2 recording published as a ROS 2 robot would, on rmw_zenoh keys.

Each message goes out as it is stored (CDR), on ``<domain>/<topic>/<type>/<RIHS01 hash>`` with rmw_zenoh's
attachment (sequence number, source time, publisher gid), paced by the recording's log times (or a frame rate
of the colour topic, or as fast as possible), so ``serve --ros2`` sees what a robot on rmw_zenoh would send.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from pathlib import Path

import zenoh

from service.replay import ReplayResult, wait_for_subscriber
from sources.ros2 import keys
from sources.ros2.pairing import RosTopics
from sources.ros2.rosbag import read_messages

log = logging.getLogger(__name__)


def replay_rosbag(
    session: zenoh.Session,
    bag: Path,
    topics: RosTopics,
    domain_id: int = 0,
    rate_hz: float | None = None,
    max_rate: bool = False,
    max_frames: int | None = None,
    wait_s: float = 5.0,
) -> ReplayResult:
    """Publish the recording's messages on our topics; returns the colour messages sent and the time taken."""
    publishers: dict[tuple[str, str], tuple[zenoh.Publisher, bytes]] = {}
    sequence: dict[tuple[str, str], int] = {}
    start, t0, frames = time.monotonic(), None, 0
    try:
        for topic, typename, log_ns, raw in read_messages(bag, topics):
            is_color = topic == topics.rgb
            if is_color and max_frames is not None and frames >= max_frames:
                break
            pub, gid = _publisher(session, publishers, domain_id, topic, typename, wait_s)
            t0 = log_ns if t0 is None else t0
            if is_color:
                _pace(start, frames, (log_ns - t0) * 1e-9, rate_hz, max_rate)
                frames += 1
            n = sequence[(topic, typename)] = sequence.get((topic, typename), 0) + 1
            pub.put(raw, attachment=keys.encode_attachment(keys.Attachment(n, time.time_ns(), gid)))
    finally:
        for pub, _ in publishers.values():
            with contextlib.suppress(zenoh.ZError):
                pub.undeclare()
    return ReplayResult(frames, time.monotonic() - start)


def _publisher(
    session: zenoh.Session,
    publishers: dict[tuple[str, str], tuple[zenoh.Publisher, bytes]],
    domain_id: int,
    topic: str,
    typename: str,
    wait_s: float,
) -> tuple[zenoh.Publisher, bytes]:
    """The publisher of ``topic`` (declared on first use, reliable and blocking, like a ROS 2 reliable one)."""
    found = publishers.get((topic, typename))
    if found is None:
        key = keys.ros_key(domain_id, topic, typename, keys.type_hash(typename))
        pub = session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
        )
        if not wait_for_subscriber(pub, wait_s):
            log.warning("no subscriber on %s yet; publishing anyway", key)
        found = publishers[(topic, typename)] = (pub, os.urandom(16))
    return found


def _pace(start: float, index: int, offset_s: float, rate_hz: float | None, max_rate: bool) -> None:
    if max_rate:
        return
    due = start + (index / rate_hz if rate_hz else offset_s)
    delay = due - time.monotonic()
    if delay > 0:
        time.sleep(delay)
