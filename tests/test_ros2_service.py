"""ROS 2 over rmw_zenoh, end to end over real zenoh: a robot's camera topics in, the map out as ROS 2 messages.

The "robot" here publishes CDR built with rosbags on the exact keys rmw_zenoh forms
(``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<RIHS01>``) with rmw_zenoh's attachment; no ROS installation.
"""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import zenoh

from service.config import load_settings
from service.node import ServiceNode
from service.protocol import encode_frame
from service.ros2_bridge import Ros2Bridge
from service.ros2_ingest import Incoming, Ros2Ingest, frame_message
from service.ros2_settings import Ros2Settings
from service.zenoh_session import open_session
from sources import open_dataset
from sources.ros2 import keys, messages
from tests.conftest import free_port, make_frame

pytestmark = pytest.mark.integration
FRAMES = 24
SPEC = f"synthetic:room?seed=2&frames={FRAMES}"
TOPICS = {"rgb": "/camera/color/image_raw", "depth": "/camera/depth/image_raw", "info": "/camera/color/camera_info"}
ODOM = "/odom"


def _settings(port: int, **ros2):
    return load_settings(
        None,
        {
            "robot": "ros",
            "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]},
            "detector": {"enabled": False},
            "loops": {"source": "off"},
            "ros2": {
                "enabled": True,
                "rgb_topic": TOPICS["rgb"],
                "depth_topic": TOPICS["depth"],
                "camera_info_topic": TOPICS["info"],
                "odom_topic": ODOM,
                **ros2,
            },
        },
    )


class Robot:
    """Publishes frames as a ROS 2 camera driver on rmw_zenoh would: Image, Image, CameraInfo, Odometry."""

    def __init__(self, session: zenoh.Session, domain: int = 0):
        self.session, self.domain, self.seq = session, domain, 0
        self.attachments = True  # rmw_zenoh's (sequence number, source time, gid); the service needs none
        self.pubs: dict[tuple[str, str], zenoh.Publisher] = {}

    def put(self, topic: str, typename: str, payload: bytes, type_hash: str | None = None) -> None:
        key = keys.ros_key(self.domain, topic, typename, type_hash or keys.type_hash(typename))
        if (topic, key) not in self.pubs:
            self.pubs[(topic, key)] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        self.seq += 1
        attachment = keys.encode_attachment(keys.Attachment(self.seq, time.time_ns(), bytes(range(16))))
        self.pubs[(topic, key)].put(bytes(payload), attachment=attachment if self.attachments else None)

    def frame(self, frame, depth_encoding: str = "16UC1") -> None:
        t, fid = frame.timestamp, "camera_color_optical_frame"
        self.put(TOPICS["info"], messages.CAMERA_INFO, messages.encode_camera_info(t, fid, frame.camera))
        self.put(ODOM, messages.ODOMETRY, messages.encode_odometry(t, "odom", fid, frame.odometry))
        depth = frame.depth if depth_encoding == "16UC1" else frame.depth.astype(np.float32) / 1000.0
        self.put(TOPICS["depth"], messages.IMAGE, messages.encode_image(t, fid, depth, depth_encoding))
        self.put(TOPICS["rgb"], messages.IMAGE, messages.encode_image(t, fid, frame.rgb, "rgb8"))

    def close(self) -> None:
        for pub in self.pubs.values():
            pub.undeclare()


@contextmanager
def _serving(**ros2):
    """A service node with the ROS 2 bridge on 127.0.0.1 (``ros2`` settings over ``_settings``'), and a robot
    session connected to it: (node, bridge, robot, robot's session)."""
    settings = _settings(free_port(), **ros2)
    server = open_session(settings.zenoh, "server")
    node = ServiceNode(settings, server)
    node.start()
    bridge = Ros2Bridge(node)
    bridge.start(server)
    robot_session = open_session(settings.zenoh, "client")
    robot = Robot(robot_session)
    try:
        time.sleep(0.5)  # routes
        yield node, bridge, robot, robot_session
    finally:
        robot.close()
        robot_session.close()
        bridge.stop()
        node.stop()
        server.close()


@pytest.fixture
def ros_service():
    with _serving() as served:
        yield served


def _frames():
    ds = open_dataset(SPEC)
    return [replace(ds.frame(i), detections=None) for i in range(len(ds))]


def _wait(node: ServiceNode, frames: int, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = node.status()
        if status["frames_processed"] + status["frames_rejected_total"] >= frames and status["queue_depth"] == 0:
            return status
        time.sleep(0.05)
    return node.status()


def _reference_trajectory(frames) -> np.ndarray:
    """The same frames through protocol v1 (raw rgb8 / u16le) on an embedded session."""
    settings = _settings(free_port(), enabled=False)
    session = open_session(settings.zenoh, "server", embedded=True)
    node = ServiceNode(settings, session)
    node.start_threads()
    try:
        for frame in frames:
            node.stats.count_received()
            node.submit(encode_frame(frame, "rgb8", "u16le"))
            assert node.wait_done(node.stats.received, timeout=30.0)
        return np.array(node.trajectory_reply()["poses"])
    finally:
        node.stop_threads()
        session.close()


def test_a_ros2_camera_stream_maps_with_the_trajectory_of_protocol_v1(ros_service):
    node, _, robot, _ = ros_service
    frames = _frames()
    for frame in frames:
        robot.frame(frame)
        time.sleep(0.03)
    status = _wait(node, FRAMES)
    assert status["frames_processed"] == FRAMES, status
    assert status["frames_rejected"] == {} and status["ros2"]["unpaired_color"] == 0
    poses = np.array(node.trajectory_reply()["poses"])
    np.testing.assert_allclose(poses, _reference_trajectory(frames), atol=1e-6)


def test_32fc1_depth_in_metres_maps_like_16uc1_and_no_attachment_is_needed(ros_service):
    node, _, robot, _ = ros_service
    robot.attachments = False
    frames = _frames()[:8]
    for frame in frames:
        robot.frame(frame, depth_encoding="32FC1")
        time.sleep(0.03)
    status = _wait(node, len(frames))
    assert status["frames_processed"] == len(frames), status


def test_bad_messages_are_rejected_with_their_reasons_and_counted(ros_service):
    node, _, robot, _ = ros_service
    frames = _frames()[:6]
    f0 = frames[0]
    robot.frame(f0)  # a good pair first: the camera is known
    robot.put(TOPICS["rgb"], messages.IMAGE, messages.encode_image(f0.timestamp + 0.1, "c", f0.rgb[:, :, 0], "mono8"))
    robot.put(TOPICS["depth"], messages.IMAGE, messages.encode_image(f0.timestamp + 0.1, "c", f0.depth[:100], "16UC1"))
    robot.put(TOPICS["rgb"], messages.IMAGE, b"\x00\x01\x00\x00garbage")  # not CDR of an Image
    distorted = messages.encode_camera_info(f0.timestamp + 0.2, "c", f0.camera)
    info: Any = messages.typestore().deserialize_cdr(distorted, messages.CAMERA_INFO)
    info.d = np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    robot.put(TOPICS["info"], messages.CAMERA_INFO, messages.typestore().serialize_cdr(info, messages.CAMERA_INFO))
    # each topic has its own callback: let the pairs above form before a colour 5 s later makes them stale
    time.sleep(0.5)
    robot.put(TOPICS["rgb"], messages.IMAGE, messages.encode_image(f0.timestamp + 5.0, "c", f0.rgb, "rgb8"))  # unpaired
    time.sleep(1.0)
    status = node.status()
    assert status["frames_processed"] == 1
    rejected = status["frames_rejected"]
    assert rejected.get("size_mismatch", 0) >= 1, rejected
    assert rejected.get("bad_header", 0) == 1 and rejected.get("bad_intrinsics", 0) == 1, rejected


def test_another_type_hash_is_accepted_and_warned_once(ros_service, caplog):
    node, _, robot, _ = ros_service
    frame = _frames()[0]
    other = "RIHS01_" + "0" * 64
    t, fid = frame.timestamp, "c"
    with caplog.at_level("WARNING", logger="service.ros2_ingest"):
        robot.put(TOPICS["info"], messages.CAMERA_INFO, messages.encode_camera_info(t, fid, frame.camera), other)
        robot.put(ODOM, messages.ODOMETRY, messages.encode_odometry(t, "odom", fid, frame.odometry))
        robot.put(TOPICS["depth"], messages.IMAGE, messages.encode_image(t, fid, frame.depth, "16UC1"), other)
        robot.put(TOPICS["rgb"], messages.IMAGE, messages.encode_image(t, fid, frame.rgb, "rgb8"), other)
        status = _wait(node, 1)
    assert status["frames_processed"] == 1
    assert sum("type hash" in r.message for r in caplog.records) == 2  # Image and CameraInfo, once each


def test_the_map_comes_back_as_ros2_messages_with_jazzy_type_hashes(ros_service):
    node, _, robot, robot_session = ros_service
    received: dict[str, list[tuple[str, bytes]]] = {"path": [], "objects": [], "pose": []}

    def listener(name: str):
        return lambda s: received[name].append((str(s.key_expr), s.payload.to_bytes()))

    subs = [robot_session.declare_subscriber(f"0/objslam/{name}/**", listener(name)) for name in received]
    time.sleep(0.3)
    frames = _frames()
    for frame in frames:
        robot.frame(frame)
        time.sleep(0.03)
    _wait(node, FRAMES)
    store = messages.typestore()
    keyframes, deadline = node.status()["keyframes"], time.monotonic() + 5.0
    while time.monotonic() < deadline:  # the path goes out at most every 0.5 s: until it has every keyframe
        time.sleep(0.1)
        path: Any = store.deserialize_cdr(received["path"][-1][1], messages.PATH) if received["path"] else None
        if path is not None and len(path.poses) == keyframes:
            break
    time.sleep(0.3)  # the pose of the last frame too (every 0.2 s)
    for name, typename in (
        ("path", messages.PATH),
        ("pose", messages.POSE_STAMPED),
        ("objects", messages.MARKER_ARRAY),
    ):
        assert received[name], name
        key, payload = received[name][-1]
        parsed = keys.parse_ros_key(key)
        assert parsed.typename == typename and parsed.type_hash == keys.JAZZY_TYPE_HASHES[typename]
        store.deserialize_cdr(payload, typename)
    path = store.deserialize_cdr(received["path"][-1][1], messages.PATH)
    assert path.header.frame_id == "map" and len(path.poses) == node.status()["keyframes"]
    last = np.array(node.trajectory_reply()["poses"][-1][1:4])
    stamped: Any = store.deserialize_cdr(received["pose"][-1][1], messages.POSE_STAMPED)
    pose = stamped.pose.position
    np.testing.assert_allclose([pose.x, pose.y, pose.z], last, atol=1e-9)
    tokens = robot_session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
    names = [str(r.ok.key_expr) for r in tokens if r.ok is not None]
    assert any("/MP/" in n and "%objslam%path" in n for n in names), names
    for sub in subs:
        sub.undeclare()
    assert json.dumps(node.status()["ros2"]["results"])  # reported in status


def test_a_rosbag2_recording_maps_with_run_like_its_frames_and_replays_into_serve(tmp_path, ros_service):
    from service.ros2_replay import replay_rosbag
    from service.run import run_dataset
    from sources.ros2.pairing import RosTopics
    from sources.ros2.rosbag import write_rosbag

    ds = open_dataset("synthetic:room?seed=2&frames=16")
    topics = RosTopics(TOPICS["rgb"], TOPICS["depth"], TOPICS["info"], ODOM)
    bag = write_rosbag(ds, tmp_path / "bag", topics, storage="mcap")
    settings = load_settings(
        None, {"detector": {"enabled": False}, "loops": {"source": "off"}, "objects": {"enabled": False}}
    )
    from_bag = run_dataset(open_dataset(str(bag), ros_topics=topics), tmp_path / "a", settings, progress=False)
    from_frames = run_dataset(ds, tmp_path / "b", settings, progress=False)
    assert from_bag["frames_processed"] == from_frames["frames_processed"] == len(ds)
    a, b = (np.loadtxt(tmp_path / d / "trajectory.tum") for d in ("a", "b"))
    np.testing.assert_allclose(a, b, atol=1e-6)

    node, _, _, robot_session = ros_service
    result = replay_rosbag(robot_session, bag, topics, rate_hz=30.0)
    assert result.frames == len(ds)
    status = _wait(node, len(ds))
    missing = (status["frames_processed"], status["frames_rejected"], status.get("ros2"))
    assert status["frames_processed"] == len(ds), missing


def test_serve_with_ros2_flags_maps_a_recording_replayed_by_the_cli(tmp_path, router):
    """The commands a user types: `objslam serve --ros2 --rgb-topic ...` and `objslam replay BAG --rgb-topic ...`."""
    import os
    import subprocess
    import sys

    from sources.ros2.pairing import RosTopics
    from sources.ros2.rosbag import write_rosbag

    session, endpoint = router
    frames = 12
    topics = RosTopics(TOPICS["rgb"], TOPICS["depth"], TOPICS["info"], ODOM)
    bag = write_rosbag(open_dataset(f"synthetic:room?seed=5&frames={frames}"), tmp_path / "bag", topics)
    flags = ["--rgb-topic", TOPICS["rgb"], "--depth-topic", TOPICS["depth"], "--camera-info-topic", TOPICS["info"]]
    common = ["--mode", "client", "--connect", endpoint, "--robot", "rosbot"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "service"]
    serve = subprocess.Popen(
        [*cmd, "serve", *common, "--lc-source", "off", "--ros2", *flags, "--odom-topic", ODOM],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        status = None
        for _ in range(300):  # until the service answers
            status = _status(session, "objslam/rosbot/status")
            if status is not None:
                break
            time.sleep(0.2)
        assert status is not None and status["ros2"]["topics"]["color"] == TOPICS["rgb"]
        replay = subprocess.run(
            [*cmd, "replay", str(bag), *common, *flags, "--odom-topic", ODOM, "--rate", "15"],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert replay.returncode == 0, replay.stderr
        deadline = time.monotonic() + 120.0  # generous: on a loaded machine 12 frames took over 30 s to map
        while time.monotonic() < deadline:
            status = _status(session, "objslam/rosbot/status")
            if status and status["frames_processed"] >= frames:
                break
            time.sleep(0.1)
        assert status is not None and status["frames_processed"] == frames, status
        assert status["ros2"]["results"]["published"]["path"] >= 1
    finally:
        serve.terminate()
        serve.communicate(timeout=30)


def _status(session: zenoh.Session, key: str) -> dict | None:
    for reply in session.get(key, timeout=1.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def test_provided_detections_on_their_topic_reach_the_object_map():
    with _serving(detections_topic="/detections") as (node, _, robot, _):
        ds = open_dataset("synthetic:room?seed=2&frames=12")
        for i in range(len(ds)):
            frame = ds.frame(i)
            dets = messages.encode_detections(frame.timestamp, "c", frame.detections or [])
            robot.put("/detections", messages.DETECTIONS, dets)
            robot.frame(frame)
            time.sleep(0.03)
        status = _wait(node, len(ds))
        assert status["frames_processed"] == len(ds), status
        node.finish()
        by_class = node.status()["keyframe_detections_by_class"]
        truth = {d.label for i in range(len(ds)) for d in ds.frame(i).detections or []}
        assert by_class and set(by_class) <= truth


# ---------------------------------------------------------------- the ingest without zenoh


def _ingest(**settings) -> tuple[Ros2Ingest, list[bytes], list[str]]:
    """A ``Ros2Ingest`` (not started) whose frames and rejections are collected."""
    topics = {"rgb_topic": TOPICS["rgb"], "depth_topic": TOPICS["depth"], "camera_info_topic": TOPICS["info"]}
    frames: list[bytes] = []
    rejected: list[str] = []
    ingest = Ros2Ingest(Ros2Settings(**{**topics, **settings}), 2048 * 1536, frames.append, rejected.append)
    return ingest, frames, rejected


def _incoming(kind: str, typename: str, payload: bytes) -> Incoming:
    topic = {"color": TOPICS["rgb"], "depth": TOPICS["depth"], "camera_info": TOPICS["info"], "odom": ODOM}[kind]
    return Incoming(kind, keys.ros_key(0, topic, typename, keys.type_hash(typename)), payload)


def test_a_pair_becomes_the_protocol_v1_message_of_its_frame_bytes_for_bytes():
    frame = make_frame(t=3.5, seq=0)
    frame = replace(frame, frame_id="c")
    ingest, payloads, _ = _ingest(odom_topic=ODOM)
    assert frame.odometry is not None
    for kind, typename, payload in (
        ("camera_info", messages.CAMERA_INFO, messages.encode_camera_info(3.5, "c", frame.camera)),
        ("odom", messages.ODOMETRY, messages.encode_odometry(3.5, "odom", "c", frame.odometry)),
        ("depth", messages.IMAGE, messages.encode_image(3.5, "c", frame.depth, "16UC1")),
        ("color", messages.IMAGE, messages.encode_image(3.5, "c", frame.rgb, "rgb8")),
    ):
        ingest.handle(_incoming(kind, typename, payload))
    assert len(payloads) == 1  # odometry came: the pair did not wait
    assert payloads[0] == encode_frame(replace(frame, detections=None), "rgb8", "u16le")
    assert frame_message(frame) == encode_frame(frame, "rgb8", "u16le")  # detections too


def test_the_same_camera_info_is_decoded_once_and_a_distorted_one_still_refused():
    ingest, _, rejected = _ingest()
    frame = make_frame()
    good = messages.encode_camera_info(1.0, "c", frame.camera)
    info: Any = messages.typestore().deserialize_cdr(good, messages.CAMERA_INFO)
    info.d = np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    distorted = bytes(messages.typestore().serialize_cdr(info, messages.CAMERA_INFO))
    ingest.handle(_incoming("camera_info", messages.CAMERA_INFO, good))
    camera = ingest.pairer.camera
    ingest.handle(_incoming("camera_info", messages.CAMERA_INFO, messages.encode_camera_info(2.0, "c", frame.camera)))
    assert camera is not None and ingest.pairer.camera is camera  # only the stamp differs: not decoded again
    for _ in range(2):
        ingest.handle(_incoming("camera_info", messages.CAMERA_INFO, distorted))
    assert rejected == ["bad_intrinsics", "bad_intrinsics"] and ingest.pairer.camera is camera


def test_the_raw_queue_is_bounded_by_bytes_dropping_the_oldest():
    ingest, _, _ = _ingest(queue_bytes=2**20)
    for i in range(5):
        ingest.put(Incoming("color", f"k{i}", bytes(300_000)))
    assert ingest.counts["dropped_messages"] == 2 and [item.key for item in ingest._queue] == ["k2", "k3", "k4"]


def test_a_flood_with_all_depth_before_its_colour_maps_every_frame_like_protocol_v1():
    """40 frames published at once, each topic in a burst: depth runs 40 frames ahead of colour (the pairer
    used to hold 30 unpaired messages); every pair still forms, in order, with its odometry."""
    ds = open_dataset("synthetic:room?seed=2&frames=40")
    frames = [replace(ds.frame(i), detections=None) for i in range(len(ds))]
    with _serving() as (node, _, robot, _):
        for frame in frames:
            robot.put(
                TOPICS["info"], messages.CAMERA_INFO, messages.encode_camera_info(frame.timestamp, "c", frame.camera)
            )
        for frame in frames:
            assert frame.odometry is not None
            robot.put(ODOM, messages.ODOMETRY, messages.encode_odometry(frame.timestamp, "odom", "c", frame.odometry))
        for frame in frames:
            robot.put(
                TOPICS["depth"], messages.IMAGE, messages.encode_image(frame.timestamp, "c", frame.depth, "16UC1")
            )
        for frame in frames:
            robot.put(TOPICS["rgb"], messages.IMAGE, messages.encode_image(frame.timestamp, "c", frame.rgb, "rgb8"))
        status = _wait(node, len(frames))
        assert status["frames_processed"] == len(frames), status
        assert status["ros2"]["unpaired_depth"] == 0 and "released_before_side" not in status["ros2"]
        poses = np.array(node.trajectory_reply()["poses"])
    np.testing.assert_allclose(poses, _reference_trajectory(frames), atol=1e-6)
