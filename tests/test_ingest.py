"""The bounded ingest queue: a full queue drops its oldest frame and counts it; shutdown counts the rest."""

from __future__ import annotations

import threading
import time

from service.config import load_settings
from service.ingest import IngestQueue
from service.node import ServiceNode
from service.protocol import Inspected, encode_frame, inspect_message
from service.replay import frame_publisher
from service.zenoh_session import open_session
from sources import open_dataset
from tests.conftest import make_frame


def _message(i: int) -> Inspected:
    return inspect_message(encode_frame(make_frame(t=float(i), seq=i)))


def test_a_full_queue_drops_the_oldest_frames_and_counts_them():
    q = IngestQueue(3)
    assert [q.put(_message(i)) for i in range(5)] == [False, False, False, True, True]
    assert q.dropped == 2 and len(q) == q.depth == 3
    assert [q.get(timeout=0.1).message.seq for _ in range(3)] == [2, 3, 4]
    assert q.get(timeout=0.01) is None and q.dropped == 2


def test_discard_and_count_dropped_account_for_every_frame_at_shutdown():
    q = IngestQueue(10)
    for i in range(4):
        q.put(_message(i))
    taken = q.get(timeout=0.1)  # a consumer took one and will not finish it
    assert taken.message.seq == 0 and q.discard() == 3 and len(q) == 0
    assert q.count_dropped(1) == 1 and q.dropped == 4


def test_a_waiting_consumer_wakes_for_a_frame_put_by_another_thread():
    q = IngestQueue(2)
    got = []
    consumer = threading.Thread(target=lambda: got.append(q.get(timeout=5.0)))
    consumer.start()
    q.put(_message(7))
    consumer.join(timeout=5.0)
    assert not consumer.is_alive() and got[0].message.seq == 7


def test_live_ingest_takes_the_newest_frame_and_counts_the_older_ones_as_stale():
    q = IngestQueue(10)
    for i in range(5):
        q.put(_message(i))
    assert q.get_newest(timeout=0.1).message.seq == 4
    assert (q.dropped, q.stale, len(q)) == (4, 4, 0)
    q.put(_message(5))
    assert q.get_newest(timeout=0.1).message.seq == 5 and q.stale == 4  # nothing older: nothing stale


def test_a_live_service_tracks_the_freshest_frames_of_a_burst_and_accounts_for_every_frame():
    settings = load_settings(None, {"detector": {"enabled": False}, "robot": "livetest", "ingest": {"live": True}})
    session = open_session(settings.zenoh, "server", embedded=True)
    data = open_dataset("synthetic:room?seed=0&frames=300&fps=30&width=320&height=240")
    payloads = [encode_frame(data.frame(i)) for i in range(60)]
    node = ServiceNode(settings, session)
    try:
        node.start()
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        for payload in payloads:  # a burst far faster than the pipeline: live keeps only the freshest
            pub.put(payload)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and not (node.stats.received == 60 and node.completed == 60):
            time.sleep(0.05)
        status = node.status()
        trajectory = node.trajectory_reply()["poses"]
    finally:
        node.stop()
        session.close()
    dropped = status["frames_dropped_by_reason"]
    assert status["frames_received"] == 60 and dropped["stale"] > 0 and dropped["queue"] == 0
    assert status["frames_processed"] + status["frames_rejected_total"] + status["frames_dropped"] == 60
    assert dropped["stale"] + dropped["queue"] == status["frames_dropped"]
    assert trajectory[-1][0] == data.frame(59).timestamp  # the newest frame was tracked, not a queued old one
    assert status["mapping"]["live"] and status["mapping"]["pending_keyframes"] <= 8


def test_a_live_service_settles_its_map_at_the_batch_optimum_when_the_stream_pauses():
    overrides = {"detector": {"enabled": False}, "robot": "settle", "ingest": {"live": True, "polish_after_s": 0.3}}
    settings = load_settings(None, overrides)
    session = open_session(settings.zenoh, "server", embedded=True)
    data = open_dataset("synthetic:room?seed=1&frames=300&fps=30&width=320&height=240")
    node = ServiceNode(settings, session)
    try:
        node.start()
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        for i in range(40):
            pub.put(encode_frame(data.frame(i)))
            time.sleep(0.05)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and node.status()["graph_window"]["whole_graph_solves"] == 0:
            time.sleep(0.05)
        status = node.status()
        with node._lock:
            graph = node.core.graph
            optimum, _ = graph.local.optimum()
            off = float(abs(graph.poses() - optimum).max())
            again = graph.polish()
    finally:
        node.stop()
        session.close()
    assert status["frames_processed"] > 0 and status["mapping"]["pending_keyframes"] == 0
    assert status["graph_window"]["whole_graph_solves"] == 1  # once for the pause, not once per idle tick
    assert off < 1e-6 and not again  # at the batch optimum, with nothing left to do
