"""ServiceNode: replies never wait for the frame being processed; the events it publishes over zenoh."""

from __future__ import annotations

import json
import threading
import time

import pytest

from service.config import load_settings
from service.map_summary import loop_events
from service.node import ServiceNode
from service.protocol import encode_frame
from service.replay import frame_publisher
from service.zenoh_session import open_session
from sources import open_dataset
from tests.conftest import make_frame


def test_status_objects_and_loops_answer_while_the_pipeline_is_busy():
    settings = load_settings(None, {"detector": {"enabled": False}})
    session = open_session(settings.zenoh, "server", embedded=True)  # no entities: driven through ``submit``
    node = ServiceNode(settings, session)
    node.start_threads()
    try:
        for i in range(3):  # what the subscriber callback does
            node.stats.count_received()
            node.submit(encode_frame(make_frame(t=1.0 + 0.1 * i, seq=i), "rgb8", "u16le"))
        assert node.wait_done(3, timeout=30.0)
        assert node.status()["frames_processed"] == 3 and node.status()["keyframes"] >= 1
        assert len(json.loads(node.replies.body("trajectory"))["poses"]) == 3  # computed once, then cached
        with node.hold_core():  # the worker holding the core for a long frame
            replies = {}

            def query() -> None:
                replies.update(status=node.status(), objects=node.objects_reply(), loops=node.loops_reply())
                replies["trajectory"] = json.loads(node.replies.body("trajectory"))

            thread = threading.Thread(target=query)
            thread.start()
            thread.join(timeout=5.0)
            assert not thread.is_alive(), "a reply waited for the core's lock"
        assert replies["status"]["frames_processed"] == 3
        assert replies["objects"]["objects"] == [] and replies["loops"]["loops"] == []
        assert len(replies["trajectory"]["poses"]) == 3
        assert replies["status"]["service_id"] == str(session.zid())
    finally:
        assert node.stop_threads(timeout=5)
        session.close()


def test_loop_events_name_each_accepted_loop_once_and_each_retraction():
    first = [{"factor": 5, "accepted": True}, {"accepted": False, "reason": "too_few_inliers"}]
    events, published = loop_events(first, set())
    assert events == [{"type": "loop_closure", "accepted": 1, "latest": [first[0]]}] and published == {5}
    assert loop_events(first, published) == ([], {5})  # nothing new
    later = [
        {"factor": 5, "accepted": False, "reason": "retracted_inconsistent"},
        first[1],
        {"factor": 9, "accepted": True},
        {"factor": 7, "accepted": True},
    ]
    assert loop_events(later, published) == (
        [
            {"type": "loop_closure", "accepted": 2, "latest": [later[3], later[2]]},
            {"type": "loop_retracted", "accepted": 2, "retracted": [later[0]]},
        ],
        {7, 9},
    )


@pytest.mark.integration
def test_events_over_zenoh_report_object_maps_and_every_accepted_loop_closure():
    settings = load_settings(None, {"detector": {"enabled": False}, "robot": "etest"})
    session = open_session(settings.zenoh, "server", embedded=True)
    events: list[dict] = []
    node = ServiceNode(settings, session)
    try:
        session.declare_subscriber(f"{node.prefix}/events", lambda s: events.append(json.loads(s.payload.to_bytes())))
        node.start()
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        data = open_dataset("synthetic:room?seed=0&frames=160&fps=10&width=320&height=240")
        for i in range(len(data)):
            pub.put(encode_frame(data.frame(i)))
            assert node.wait_done(i + 1, timeout=60.0)
        loops = node.loops_reply()["loops"]
        deadline = time.monotonic() + 10.0
        accepted = sorted(r["factor"] for r in loops if r["accepted"])
        while time.monotonic() < deadline and sum(len(e.get("latest", [])) for e in events) < len(accepted):
            time.sleep(0.05)
    finally:
        node.stop()
        session.close()
    announced = [r["factor"] for e in events if e["type"] == "loop_closure" for r in e["latest"]]
    assert len(accepted) > 1 and sorted(announced) == accepted  # each accepted loop exactly once
    maps = [e for e in events if e["type"] == "objects"]

    def clustered(objects: list[dict]) -> list[dict]:  # landmark estimates move with every graph update
        return [{k: v for k, v in o.items() if k != "landmark"} for o in objects]

    assert maps and len(maps[-1]["objects"]) > 3
    assert clustered(maps[-1]["objects"]) == clustered(node.objects_reply()["objects"])  # the last re-clustering


@pytest.mark.integration
def test_save_writes_the_outputs_of_a_running_service_on_request(tmp_path):
    data = open_dataset("synthetic:room?seed=0&frames=30&fps=10&width=320&height=240")
    for state_dir in (tmp_path / "state", None):
        settings = load_settings(None, {"detector": {"enabled": False}, "robot": "stest", "state_dir": state_dir})
        session = open_session(settings.zenoh, "server", embedded=True)
        node = ServiceNode(settings, session)
        try:
            node.start()
            pub = frame_publisher(session, f"{node.prefix}/rgbd")
            for i in range(len(data)):
                pub.put(encode_frame(data.frame(i)))
            assert node.wait_done(len(data), timeout=60.0)
            replies = list(session.get(f"{node.prefix}/save", timeout=60.0))
            assert len(replies) == 1
            if state_dir is None:
                assert replies[0].ok is None and "no state directory" in replies[0].err.payload.to_string()
                continue
            reply = json.loads(replies[0].ok.payload.to_bytes())
            assert reply["frames_processed"] == len(data) and reply["keyframes"] == node.status()["keyframes"]
            assert {"trajectory.tum", "odometry.tum", "objects.json", "loops.json", "report.md", "map.png"} <= set(
                reply["files"]
            )
            rows = [r for r in (state_dir / "trajectory.tum").read_text().splitlines() if r and r[0] != "#"]
            assert len(rows) == len(data)
            assert json.loads((state_dir / "objects.json").read_text()) == node.objects_reply()["objects"]
            assert node.status()["frames_processed"] == len(data)  # the service carries on
        finally:
            node.stop()
            session.close()


@pytest.mark.integration
def test_overload_drops_the_oldest_frames_counts_them_and_status_keeps_answering():
    settings = load_settings(None, {"detector": {"enabled": False}, "robot": "otest", "ingest": {"queue_size": 4}})
    session = open_session(settings.zenoh, "server", embedded=True)
    data = open_dataset("synthetic:room?seed=0&frames=120&fps=30&width=320&height=240")
    payloads = [encode_frame(data.frame(i)) for i in range(len(data))]
    node = ServiceNode(settings, session)
    try:
        node.start()
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        answered = 0
        for i, payload in enumerate(payloads):  # far faster than the pipeline processes
            pub.put(payload)
            if i % 20 == 0:
                answered += len([r for r in session.get(f"{node.prefix}/status", timeout=5.0) if r.ok is not None])
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and not (node.stats.received == len(data) and node.completed == len(data)):
            time.sleep(0.05)
        status = node.status()
        trajectory = node.trajectory_reply()["poses"]
    finally:
        node.stop()
        session.close()
    assert answered == len(payloads) // 20  # every status query answered during the overload
    assert status["frames_received"] == len(data) and status["frames_dropped"] > 0 and status["frames_processed"] > 1
    assert status["frames_processed"] + status["frames_rejected_total"] + status["frames_dropped"] == len(data)
    assert len(trajectory) == status["frames_processed"] and trajectory[-1][0] == data.frame(len(data) - 1).timestamp
