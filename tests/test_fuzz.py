"""Fuzz over real zenoh: 10,000 mutated, random and good frames into a running ServiceNode (SPEC 8).

The node listens on its own zenoh peer session; a second session publishes the storm of
``tests/fuzz_frames.py`` and queries ``status`` and ``trajectory`` over zenoh. Publishing keeps at most
``WINDOW`` frames in flight (below the queue capacity), so no frame is dropped and every frame's fate is known.
"""

from __future__ import annotations

import json
import time
from collections import Counter

import numpy as np
import pytest
import zenoh

from service.config import load_settings
from service.node import ServiceNode
from service.protocol import Reason
from service.replay import frame_publisher
from service.zenoh_session import open_session
from tests.conftest import free_port
from tests.fuzz_frames import PROCESSED, Storm, pack

pytestmark = pytest.mark.integration
SEED = 20240611
STORM = 10_000
WINDOW = 32  # frames published but not yet processed or rejected; the queue holds 64
GOOD_SHARE = 0.2


@pytest.fixture
def service():
    port = free_port()
    settings = load_settings(
        None,
        {
            "robot": "fuzz",
            "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"], "multicast_scouting": False},
            "detector": {"enabled": False},  # good frames carry detections; never load the ONNX model
            "odometry": {"visual": False},  # the stream carries odometry: a frame without is no_odometry
        },
    )
    server = open_session(settings.zenoh, "server")
    node = ServiceNode(settings, server)
    node.start()
    client = open_session(settings.zenoh, "client")  # a second peer, connected to the node's endpoint
    yield node, client
    client.close()
    node.stop()
    server.close()


def _get(session: zenoh.Session, key: str) -> dict:
    for reply in session.get(key, timeout=5.0):
        assert reply.ok is not None, reply.err.payload.to_string()
        return json.loads(reply.ok.payload.to_bytes())
    raise AssertionError(f"no reply on {key}")


def _completed(node: ServiceNode) -> int:
    s = node.stats
    return s.processed + sum(s.rejected.values()) + sum(s.errors.values()) + node.queue.dropped


def _publish_paced(node: ServiceNode, pub: zenoh.Publisher, payload: bytes, sent: int) -> None:
    deadline = time.monotonic() + 30.0
    while sent - _completed(node) >= WINDOW:
        assert time.monotonic() < deadline, "the service stopped consuming frames"
        time.sleep(0.0005)
    pub.put(payload)


def _drain(node: ServiceNode, sent: int) -> None:
    deadline = time.monotonic() + 60.0
    while _completed(node) < sent or node.stats.received < sent:
        assert time.monotonic() < deadline, f"{_completed(node)} of {sent} frames accounted for"
        time.sleep(0.01)


def test_ten_thousand_bad_frames_are_each_counted_by_reason_and_good_frames_keep_flowing(service):
    node, client = service
    prefix = node.prefix
    pub = frame_publisher(client, f"{prefix}/rgbd")
    storm = Storm(SEED)
    bad_classes = [name for name in storm.classes if name != "good"]
    expected: Counter[str] = Counter()
    by_class: Counter[str] = Counter()
    sent = 0

    def send(name: str) -> None:
        nonlocal sent
        payload, outcome = storm.classes[name]()
        _publish_paced(node, pub, payload, sent)
        sent += 1
        expected[outcome] += 1
        by_class[name] += 1

    for _ in range(10):  # the first frames decide the front end: frames carry odometry
        send("good")
    for i in range(STORM):
        send("good" if storm.rng.random() < GOOD_SHARE else bad_classes[int(storm.rng.integers(len(bad_classes)))])
        if i % 2000 == 1999:  # status keeps answering over zenoh in the middle of the storm
            mid = _get(client, f"{prefix}/status")
            assert 0 < mid["frames_received"] <= sent and mid["errors"] == {}
    _drain(node, sent)

    status = _get(client, f"{prefix}/status")
    print(
        f"\nfuzz: {sent} frames, by class {dict(sorted(by_class.items()))}\nstatus: processed "
        f"{status['frames_processed']}, rejected {status['frames_rejected']}, dropped {status['frames_dropped']}"
    )
    assert node.working
    assert status["frames_received"] == sent >= STORM
    assert status["errors"] == {}
    assert status["frames_received"] == (
        status["frames_processed"]
        + status["frames_rejected_total"]
        + status["frames_dropped"]
        + sum(status["errors"].values())
    )
    assert status["frames_dropped"] == 0  # paced below the queue capacity
    assert status["frames_processed"] == expected.pop(PROCESSED)
    assert status["frames_rejected"] == dict(expected)
    # the storm exercised every reason but the rate limit (tests/test_hostile.py floods for that one)
    assert set(expected) == {reason.value for reason in Reason} - {Reason.RATE_LIMITED.value}
    poses = _get(client, f"{prefix}/trajectory")["poses"]
    assert len(poses) == status["frames_processed"]

    # after the storm: good frames are still processed and extend the trajectory
    after = [storm.classes["good"]() for _ in range(30)]
    for payload, _ in after:
        _publish_paced(node, pub, payload, sent)
        sent += 1
    _drain(node, sent)
    final = _get(client, f"{prefix}/status")
    assert final["frames_processed"] == status["frames_processed"] + 30
    rows = np.array(_get(client, f"{prefix}/trajectory")["poses"])
    assert len(rows) == len(poses) + 30
    np.testing.assert_allclose(rows[-30:, 0], [storm.t - 0.05 * k for k in range(29, -1, -1)], atol=1e-6)
    pub.undeclare()


def _send_good(node: ServiceNode, pub: zenoh.Publisher, storm: Storm, n: int, sent: int) -> int:
    """Publish ``n`` good frames of ``storm`` and wait until they are accounted for; frames sent so far."""
    for _ in range(n):
        _publish_paced(node, pub, storm.good()[0], sent)
        sent += 1
    _drain(node, sent)
    return sent


def test_an_odometry_jump_is_rejected_with_its_reason_and_mapping_continues(service):
    node, client = service
    pub = frame_publisher(client, f"{node.prefix}/rgbd")
    storm = Storm(SEED)
    sent = _send_good(node, pub, storm, 12, 0)
    header, body = storm.valid()
    header["odometry"] = [8000.0, -6000.0, 3000.0, 0.5, 0.5, 0.5, 0.5]  # a 10 km jump
    _publish_paced(node, pub, pack(header, body), sent)
    sent = _send_good(node, pub, storm, 0, sent + 1)
    before = _get(client, f"{node.prefix}/status")
    _send_good(node, pub, storm, 30, sent)
    after = _get(client, f"{node.prefix}/status")
    assert before["frames_rejected"] == {"odometry_jump": 1} and before["errors"] == {}
    assert after["frames_processed"] == before["frames_processed"] + 30 == 42 and after["errors"] == {}
    assert after["keyframes"] >= before["keyframes"] + 2
    pub.undeclare()


class _FailingOnce:
    """iSAM2 whose next update throws (then the graph rebuilds its solver, and this wrapper is gone)."""

    def __init__(self, isam):
        self._isam = isam

    def update(self, *args):
        raise RuntimeError("injected solver failure")

    def __getattr__(self, name):
        return getattr(self._isam, name)


def test_a_solver_failure_does_not_stop_mapping(service):
    node, client = service
    pub = frame_publisher(client, f"{node.prefix}/rgbd")
    storm = Storm(SEED)
    sent = _send_good(node, pub, storm, 12, 0)
    before = _get(client, f"{node.prefix}/status")
    window = node.core.graph.local  # the iSAM2 window: the next keyframe's update fails
    window.isam = _FailingOnce(window.isam)
    _send_good(node, pub, storm, 30, sent)
    after = _get(client, f"{node.prefix}/status")
    assert before["errors"] == {} and after["errors"] == {"solver": 1}
    assert after["frames_processed"] == before["frames_processed"] + 29
    assert after["keyframes"] >= before["keyframes"] + 2
    pub.undeclare()
