"""ServiceNode without zenoh traffic: replies never wait for the frame being processed."""

from __future__ import annotations

import threading
import time

from service.config import load_settings
from service.node import ServiceNode
from service.protocol import encode_frame
from tests.conftest import make_frame


class _NoSession:
    """Stands in for a zenoh session: the node is driven through ``submit`` and its worker, no entities."""


def test_status_objects_and_loops_answer_while_the_pipeline_is_busy():
    node = ServiceNode(load_settings(None, {"detector": {"enabled": False}}), _NoSession())
    node._decoder.start()
    node._worker.start()
    try:
        for i in range(3):  # what the subscriber callback does
            node.stats.count_received()
            node.submit(encode_frame(make_frame(t=1.0 + 0.1 * i, seq=i), "rgb8", "u16le"))
        assert node.wait_done(3, timeout=30.0)
        assert node.status()["frames_processed"] == 3 and node.status()["keyframes"] >= 1
        with node._lock:  # the worker holding the pipeline for a long frame
            replies = {}

            def query() -> None:
                t0 = time.perf_counter()
                replies.update(status=node.status(), objects=node.objects_reply(), loops=node.loops_reply())
                replies["seconds"] = time.perf_counter() - t0

            thread = threading.Thread(target=query)
            thread.start()
            thread.join(timeout=5.0)
            assert not thread.is_alive(), "a reply waited for the pipeline lock"
        assert replies["status"]["frames_processed"] == 3 and replies["seconds"] < 1.0
        assert replies["objects"]["objects"] == [] and replies["loops"]["loops"] == []
    finally:
        node._stop.set()
        node._decoder.join(timeout=5)
        node._worker.join(timeout=5)
