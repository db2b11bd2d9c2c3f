"""The bounded ingest queue: a full queue drops its oldest frame and counts it; shutdown counts the rest."""

from __future__ import annotations

import threading

from service.ingest import IngestQueue


def test_a_full_queue_drops_the_oldest_frames_and_counts_them():
    q = IngestQueue(3)
    assert [q.put(bytes([i])) for i in range(5)] == [False, False, False, True, True]
    assert q.dropped == 2 and len(q) == q.depth == 3
    assert [q.get(timeout=0.1).payload for _ in range(3)] == [b"\x02", b"\x03", b"\x04"]
    assert q.get(timeout=0.01) is None and q.dropped == 2


def test_discard_and_count_dropped_account_for_every_frame_at_shutdown():
    q = IngestQueue(10)
    for i in range(4):
        q.put(bytes([i]))
    taken = q.get(timeout=0.1)  # a consumer took one and will not finish it
    assert taken.payload == b"\x00" and q.discard() == 3 and len(q) == 0
    assert q.count_dropped(1) == 1 and q.dropped == 4


def test_a_waiting_consumer_wakes_for_a_frame_put_by_another_thread():
    q = IngestQueue(2)
    got = []
    consumer = threading.Thread(target=lambda: got.append(q.get(timeout=5.0)))
    consumer.start()
    q.put(b"frame")
    consumer.join(timeout=5.0)
    assert not consumer.is_alive() and got[0].payload == b"frame"
