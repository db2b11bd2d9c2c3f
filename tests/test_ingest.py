"""The bounded ingest queue: a full queue drops its oldest frame and counts it; shutdown counts the rest."""

from __future__ import annotations

import threading

from service.ingest import IngestQueue
from service.protocol import Inspected, encode_frame, inspect_message
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
