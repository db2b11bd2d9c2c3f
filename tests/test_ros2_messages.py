"""ROS 2 sources: CDR messages both ways, rejections, rmw_zenoh keys and attachments, pairing, rosbag2 replay."""

from __future__ import annotations

import contextlib
import struct

import cv2
import numpy as np
import pytest

from graph.geometry import pose_from_tum
from perception.frame import CameraModel, Detection, Frame, FrameRejected, Intrinsics, Reason
from sources import DatasetError, open_dataset
from sources.base import Dataset
from sources.ros2.cdr import deserialize, header, make, serialize, typestore
from sources.ros2.encoders import _pose_stamped
from sources.ros2.keys import (
    JAZZY_TYPE_HASHES,
    Attachment,
    RosKey,
    decode_attachment,
    encode_attachment,
    parse_ros_key,
    ros_key,
    type_hash,
)
from sources.ros2.messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DETECTIONS,
    IMAGE,
    MARKER_ARRAY,
    ODOMETRY,
    PATH,
    POSE_STAMPED,
    Stamped,
    decode_camera_info,
    decode_compressed_image,
    decode_detections,
    decode_image,
    decode_odometry,
    encode_camera_info,
    encode_compressed_image,
    encode_detections,
    encode_image,
    encode_marker_array,
    encode_odometry,
    encode_path,
    encode_pose_stamped,
    from_stamp,
    peek_raw_compressed_image,
    peek_raw_image,
    pixels,
    to_stamp,
)
from sources.ros2.pairing import MAX_UNPAIRED_AGE_S, FramePairer, RosTopics
from sources.ros2.rosbag import write_rosbag

MAX = 2048 * 1536
CAMERA = CameraModel(Intrinsics(50.0, 52.0, 31.5, 23.5), 64, 48, 1000.0)
POSE = pose_from_tum(np.array([1.0, -2.0, 0.5, 0.1, 0.2, 0.3, np.sqrt(1 - 0.14)]))
TOPICS = RosTopics("/camera/color/image_raw", "/camera/depth/image_raw", "/camera/color/camera_info", "/odom", "/det")


def rgb_image(h: int = 48, w: int = 64) -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, (h, w, 3), dtype=np.uint8)


def depth_image(h: int = 48, w: int = 64) -> np.ndarray:
    return np.random.default_rng(2).integers(0, 65535, (h, w), dtype=np.uint16)


def rejected(reason: Reason, call, *args) -> FrameRejected:
    with pytest.raises(FrameRejected) as info:
        call(*args)
    assert info.value.reason == reason, info.value
    return info.value


def raw_image(**fields) -> bytes:
    """An Image message with the given fields (a crafted, possibly wrong one)."""
    defaults = {"height": 2, "width": 3, "encoding": "rgb8", "step": 9, "data": np.zeros(18, np.uint8)}
    return serialize(make(IMAGE, **{**defaults, **fields}), IMAGE)


# ---------------------------------------------------------------- stamps, hashes, keys, attachments


def test_stamps_are_exact_to_the_nanosecond():
    assert to_stamp(0.0) == (0, 0)
    assert to_stamp(1.5) == (1, 500_000_000)
    assert to_stamp(0.966666667) == (0, 966_666_667)
    assert to_stamp(2.9999999999) == (3, 0)
    assert to_stamp(1_700_000_000.25) == (1_700_000_000, 250_000_000)
    for t in np.linspace(0.0, 100.0, 301):
        assert abs(from_stamp(*to_stamp(t)) - t) <= 5e-10
    with pytest.raises(ValueError):
        to_stamp(-1.0)


@pytest.mark.parametrize("typename", sorted(JAZZY_TYPE_HASHES))
def test_type_hashes_are_those_jazzy_publishes(typename):
    assert type_hash(typename) == JAZZY_TYPE_HASHES[typename]


def test_every_message_type_has_its_jazzy_hash():
    used = {IMAGE, COMPRESSED_IMAGE, CAMERA_INFO, ODOMETRY, DETECTIONS, PATH, POSE_STAMPED, MARKER_ARRAY}
    assert used == set(JAZZY_TYPE_HASHES)


def test_ros_key_is_rmw_zenohs():
    key = ros_key(0, "/camera/color/image_raw", IMAGE, JAZZY_TYPE_HASHES[IMAGE])
    assert key == (
        "0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/"
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    )
    assert ros_key(7, "odom", ODOMETRY, None) == "7/odom/nav_msgs::msg::dds_::Odometry_/*"
    assert parse_ros_key(key) == RosKey(0, "/camera/color/image_raw", IMAGE, JAZZY_TYPE_HASHES[IMAGE])
    assert parse_ros_key(ros_key(3, "/a/b", DETECTIONS, "RIHS01_x")).typename == DETECTIONS


@pytest.mark.parametrize("topic", ["", "/", "/camera/*", "a//b", "/cam$", "x/**"])
def test_ros_key_refuses_bad_topics(topic):
    with pytest.raises(ValueError):
        ros_key(0, topic, IMAGE, None)


@pytest.mark.parametrize(
    "key",
    ["", "0/chatter", "x/chatter/std_msgs::msg::dds_::String_/RIHS01_a", "0/chatter/std_msgs/msg/String/RIHS01_a",
     "0/std_msgs::msg::dds_::String_/RIHS01_a", "0/chatter/std_msgs::msg::dds_::String/RIHS01_a",
     "0/chatter/std_msgs::msg::dds_::String_/", "0//chatter/std_msgs::msg::dds_::String_/h"],
)  # fmt: skip
def test_parse_ros_key_refuses_other_keys(key):
    with pytest.raises(ValueError):
        parse_ros_key(key)


def test_attachment_round_trip_and_layout():
    a = Attachment(42, 1_700_000_000_123_456_789, bytes(range(16)))
    data = encode_attachment(a)
    assert data == struct.pack("<qq", 42, 1_700_000_000_123_456_789) + b"\x10" + bytes(range(16))
    assert decode_attachment(data) == a
    assert decode_attachment(data + b"\x00") == a  # a later rmw_zenoh may append fields


@pytest.mark.parametrize(
    "data", [None, b"", b"garbage", bytes(32), bytes(16) + b"\x11" + bytes(17), bytes(16) + b"\xff" * 20]
)
def test_attachment_absent_or_garbage_is_none(data):
    assert decode_attachment(data) is None


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_colour_image_round_trip(encoding):
    rgb = rgb_image()
    raw = encode_image(12.25, "cam", rgb[..., 0] if encoding == "mono8" else rgb, encoding)
    msg = decode_image(raw, MAX)
    expected = np.repeat(rgb[..., :1], 3, axis=2) if encoding == "mono8" else rgb
    assert (msg.stamp, msg.frame_id, msg.encoding) == (12.25, "cam", encoding)
    assert msg.value.dtype == np.uint8 and np.array_equal(msg.value, expected)
    assert msg.value.flags.writeable and msg.value.flags.c_contiguous  # the frame's own pixels, not the message's
    wire = np.asarray(deserialize(raw, IMAGE).data)
    first = {"rgb8": rgb[0, 0], "bgr8": rgb[0, 0, ::-1], "mono8": rgb[0, :3, 0]}[encoding]
    assert wire[:3].tolist() == first.tolist()


def test_depth_image_round_trip_16uc1_and_32fc1():
    depth = depth_image()
    assert np.array_equal(decode_image(encode_image(1.0, "d", depth, "16UC1"), MAX).value, depth)
    metres = depth.astype(np.float32) / 1000
    metres[0, :4] = [np.nan, np.inf, -1.0, 0.0]
    metres[1, 0] = 70.0
    decoded = decode_image(encode_image(1.0, "d", metres, "32FC1"), MAX)
    expected = depth.copy()
    expected[0, :4], expected[1, 0] = 0, 65535
    assert decoded.encoding == "32FC1" and decoded.value.dtype == np.uint16
    assert np.array_equal(decoded.value, expected)


def test_image_row_padding_and_big_endian_are_honoured():
    depth = depth_image(4, 5)
    padded = np.zeros((4, 16), np.uint8)
    padded[:, :10] = depth.astype(">u2").view(np.uint8).reshape(4, 10)
    raw = raw_image(height=4, width=5, encoding="16UC1", is_bigendian=1, step=16, data=padded.reshape(-1))
    assert np.array_equal(decode_image(raw, MAX).value, depth)


def test_raw_images_convert_without_copies_where_the_wire_is_already_rgb8_or_u16le():
    rgb, depth = rgb_image(), depth_image()
    for image, encoding in ((rgb, "rgb8"), (depth, "16UC1")):
        held = peek_raw_image(encode_image(1.0, "c", image, encoding), MAX)
        assert held.value.shape == image.shape[:2] and held.value.nbytes == len(held.value.raw)
        view = pixels(held.value, MAX, copy=False)
        assert np.array_equal(view, image) and np.shares_memory(view, np.frombuffer(held.value.raw, np.uint8))
        owned = pixels(held.value, MAX)
        assert np.array_equal(owned, image) and owned.flags.writeable and not np.shares_memory(owned, view)
    padded = np.zeros((48, 200), np.uint8)
    padded[:, :192] = rgb.reshape(48, 192)
    held = peek_raw_image(raw_image(height=48, width=64, encoding="rgb8", step=200, data=padded.reshape(-1)), MAX)
    assert np.array_equal(pixels(held.value, MAX, copy=False), rgb)  # rows cut from their padding
    jpeg = peek_raw_compressed_image(encode_compressed_image(1.0, "c", rgb, "png"), MAX)
    assert jpeg.value.shape == (48, 64) and np.array_equal(pixels(jpeg.value, MAX, copy=False), rgb)


def test_compressed_image_round_trip():
    rgb = rgb_image()
    png = decode_compressed_image(encode_compressed_image(3.0, "cam", rgb, "png"), MAX)
    assert png.encoding == "png" and np.array_equal(png.value, rgb)
    smooth = np.repeat(np.linspace(0, 255, 64, dtype=np.uint8)[None, :, None], 48, axis=0).repeat(3, axis=2)
    jpeg = decode_compressed_image(encode_compressed_image(3.0, "cam", smooth, "jpeg"), MAX)
    assert jpeg.encoding == "jpeg" and np.abs(jpeg.value.astype(int) - smooth).max() <= 3


def test_camera_info_round_trip():
    msg = decode_camera_info(encode_camera_info(5.5, "cam", CAMERA))
    assert (msg.stamp, msg.frame_id, msg.value) == (5.5, "cam", CAMERA)


def test_odometry_round_trip():
    msg = decode_odometry(encode_odometry(2.0, "odom", "cam", POSE))
    assert msg.frame_id == "odom" and np.abs(msg.value - POSE).max() < 1e-12


def test_detections_round_trip_skip_empty_results_and_clip():
    dets = [Detection("cup", 0.9, (5.0, 6.0, 20.5, 30.0)), Detection("chair", 1.0, (-10.0, 40.0, 30.0, 60.0))]
    msg = decode_detections(encode_detections(4.0, "cam", dets), 64, 48)
    assert [d.label for d in msg.value] == ["cup", "chair"] and msg.value[0].score == 0.9
    assert np.allclose(msg.value[0].box, dets[0].box, atol=1e-9)
    assert np.allclose(msg.value[1].box, (0.0, 40.0, 30.0, 48.0))
    array = deserialize(encode_detections(4.0, "cam", dets), DETECTIONS)
    array.detections[0].results = []
    array.detections[1].bbox.center.theta = np.pi / 2  # rotated a quarter turn: 40 x 20 becomes 20 x 40
    out = decode_detections(serialize(array, DETECTIONS), 64, 48).value
    assert [d.label for d in out] == ["chair"] and np.allclose(out[0].box, (0.0, 30.0, 20.0, 48.0))


def test_path_and_pose_stamped_carry_poses_with_their_times():
    path = deserialize(encode_path(9.0, "map", [(1.0, np.eye(4)), (2.5, POSE)]), PATH)
    assert [p.header.stamp.sec for p in path.poses] == [1, 2] and path.poses[1].header.stamp.nanosec == 500_000_000
    pose = deserialize(encode_pose_stamped(9.0, "map", POSE), POSE_STAMPED).pose
    q = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
    assert np.allclose(pose_from_tum(np.array([pose.position.x, pose.position.y, pose.position.z, *q])), POSE)


@pytest.mark.parametrize("frame_id", ["", "m", "map", "odom_frame"])
def test_path_bytes_are_those_of_rosbags_serializer(frame_id):
    """``encode_path`` writes the CDR itself (fast): the very bytes rosbags gives, whatever the padding."""
    rng = np.random.default_rng(len(frame_id))
    poses = []
    for i in range(5):
        q = rng.normal(size=4)
        poses.append((1.5 + i * 0.1234567, pose_from_tum(np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)]))))
    for few in (poses[:0], poses[:1], poses):
        reference = make(PATH, header=header(9.25, frame_id), poses=[_pose_stamped(t, frame_id, T) for t, T in few])
        assert encode_path(9.25, frame_id, few) == serialize(reference, PATH)


def test_marker_array_shows_objects_labels_and_loops():
    rotation = pose_from_tum(np.array([0, 0, 0, 0.0, 0.0, np.sin(0.3), np.cos(0.3)]))[:3, :3]
    axes = (rotation * [0.3, 0.2, 0.1]).T  # rows: principal directions times radii
    objects = [{"id": 4, "label": "chair", "mean": [1.0, 2.0, 0.5], "axes": axes.tolist(), "n_observations": 7}]
    loops = [(np.zeros(3), np.ones(3)), (np.eye(4), POSE)]
    markers = deserialize(encode_marker_array(3.0, "map", objects, loops), MARKER_ARRAY).markers
    assert [(m.ns, m.type, m.action) for m in markers] == [
        ("", 2, 3),
        ("objects", 2, 0),
        ("labels", 9, 0),
        ("loops", 5, 0),
    ]
    sphere = markers[1]
    assert sphere.id == 4 and np.allclose([sphere.scale.x, sphere.scale.y, sphere.scale.z], [0.6, 0.4, 0.2])
    o = sphere.pose.orientation
    pose = pose_from_tum(
        np.array([sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z, o.x, o.y, o.z, o.w])
    )
    assert np.allclose(pose[:3, 3], [1.0, 2.0, 0.5]) and np.allclose(pose[:3, :3], rotation)
    assert sphere.color.a == 0.5 and markers[2].text == "chair #4 (7)"
    assert len(markers[3].points) == 4 and markers[3].points[3].x == POSE[0, 3]
    again = deserialize(encode_marker_array(3.0, "map", objects, []), MARKER_ARRAY).markers
    assert len(again) == 3 and again[1].color == sphere.color  # colours are a stable function of the label


# ---------------------------------------------------------------- rejections


def test_bytes_that_are_not_the_message_are_bad_header():
    for decode in (
        lambda r: decode_image(r, MAX),
        lambda r: decode_compressed_image(r, MAX),
        decode_camera_info,
        decode_odometry,
    ):
        rejected(Reason.BAD_HEADER, decode, b"\x00\x01\x00\x00\xff")
    rejected(Reason.BAD_HEADER, decode_detections, b"not cdr at all", 64, 48)


def test_image_rejections():
    rejected(Reason.BAD_FIELD, decode_image, raw_image(encoding="yuv422"), MAX)
    rejected(Reason.SIZE_MISMATCH, decode_image, raw_image(step=8), MAX)  # step < width x 3
    rejected(Reason.SIZE_MISMATCH, decode_image, raw_image(data=np.zeros(17, np.uint8)), MAX)
    rejected(Reason.BAD_IMAGE, decode_image, raw_image(height=0, data=np.zeros(0, np.uint8)), MAX)
    too_large = rejected(Reason.TOO_LARGE, decode_image, raw_image(height=30000, width=30000, step=90000), MAX)
    assert "30000x30000" in too_large.detail


def test_compressed_bomb_is_refused_before_decoding(monkeypatch):
    png = bytearray(cv2.imencode(".png", np.zeros((2, 2, 3), np.uint8))[1].tobytes())
    png[16:24] = struct.pack(">II", 30000, 30000)  # the IHDR now declares 30000 x 30000
    raw = serialize(make(COMPRESSED_IMAGE, format="png", data=np.frombuffer(bytes(png), np.uint8)), COMPRESSED_IMAGE)
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("a bomb must not be decoded"))
    rejected(Reason.TOO_LARGE, decode_compressed_image, raw, MAX)


def test_compressed_format_and_data_rejections():
    garbage = serialize(make(COMPRESSED_IMAGE, format="jpeg", data=np.arange(50, dtype=np.uint8)), COMPRESSED_IMAGE)
    rejected(Reason.BAD_IMAGE, decode_compressed_image, garbage, MAX)
    for fmt in ("tiff", "16UC1; compressedDepth png"):
        raw = serialize(make(COMPRESSED_IMAGE, format=fmt, data=np.zeros(4, np.uint8)), COMPRESSED_IMAGE)
        rejected(Reason.BAD_FIELD, decode_compressed_image, raw, MAX)


def test_camera_info_rejections():
    info = deserialize(encode_camera_info(1.0, "cam", CAMERA), CAMERA_INFO)
    info.d = np.array([0.1, -0.02, 0.0, 0.0, 0.0])
    error = rejected(Reason.BAD_INTRINSICS, decode_camera_info, serialize(info, CAMERA_INFO))
    assert "distorted images are not supported (distortion_model plumb_bob, d=[0.1, -0.02" in error.detail
    info.d = np.zeros(5)
    info.k = info.k.copy()  # deserialised arrays are read-only views of the message
    info.k[0] = 0.0
    rejected(Reason.BAD_INTRINSICS, decode_camera_info, serialize(info, CAMERA_INFO))
    info.k[0] = np.nan
    rejected(Reason.BAD_INTRINSICS, decode_camera_info, serialize(info, CAMERA_INFO))


@pytest.mark.parametrize("field,value", [("x", np.nan), ("w", 0.5), ("z", 1e7)])
def test_odometry_rejections(field, value):
    odom = deserialize(encode_odometry(1.0, "odom", "cam", np.eye(4)), ODOMETRY)
    target = odom.pose.pose.orientation if field == "w" else odom.pose.pose.position
    setattr(target, field, value)
    rejected(Reason.BAD_POSE, decode_odometry, serialize(odom, ODOMETRY))


def test_detection_rejections():
    dets = [Detection("cup", 0.9, (5.0, 6.0, 20.0, 30.0))]
    for change in ("score", "nan", "outside", "label"):
        array = deserialize(encode_detections(1.0, "cam", dets), DETECTIONS)
        det = array.detections[0]
        if change == "score":
            det.results[0].hypothesis.score = 1.5
        elif change == "nan":
            det.bbox.size_x = np.nan
        elif change == "outside":
            det.bbox.center.position.x = 500.0
        else:
            det.results[0].hypothesis.class_id = ""
        rejected(Reason.BAD_DETECTIONS, decode_detections, serialize(array, DETECTIONS), 64, 48)


def test_truncated_messages_raise_only_frame_rejected():
    messages = [
        (lambda r: decode_image(r, MAX), encode_image(1.0, "c", rgb_image(4, 5), "rgb8")),
        (lambda r: decode_compressed_image(r, MAX), encode_compressed_image(1.0, "c", rgb_image(4, 5), "png")),
        (decode_camera_info, encode_camera_info(1.0, "c", CAMERA)),
        (decode_odometry, encode_odometry(1.0, "o", "c", POSE)),
        (lambda r: decode_detections(r, 64, 48), encode_detections(1.0, "c", [Detection("cup", 0.5, (1, 2, 9, 9))])),
    ]
    rng = np.random.default_rng(0)
    for decode, raw in messages:
        for cut in range(0, len(raw), max(1, len(raw) // 40)):
            for data in (raw[:cut], raw[:cut] + rng.integers(0, 256, 8, dtype=np.uint8).tobytes()):
                with contextlib.suppress(FrameRejected):
                    decode(data)


# ---------------------------------------------------------------- pairing


def color(t: float, w: int = 64, h: int = 48) -> Stamped:
    return Stamped(t, "cam", np.zeros((h, w, 3), np.uint8), "rgb8")


def depth(t: float, w: int = 64, h: int = 48) -> Stamped:
    return Stamped(t, "cam", np.zeros((h, w), np.uint16), "16UC1")


def with_camera(**kwargs) -> FramePairer:
    pairer = FramePairer(**kwargs)
    pairer.camera_info(Stamped(0.0, "cam", CAMERA))
    return pairer


def test_exact_and_jittered_stamps_pair_in_order():
    pairer = with_camera()
    frames = []
    for i, jitter in enumerate([0.0, 0.004, -0.015, 0.019]):
        frames += pairer.color(color(i / 30))
        frames += pairer.depth(depth(i / 30 + jitter))
    assert [f.timestamp for f in frames] == [i / 30 for i in range(4)] and [f.seq for f in frames] == [0, 1, 2, 3]
    assert frames[0].camera == CAMERA and frames[0].odometry is None and frames[0].detections is None
    assert pairer.counters() == {"unpaired_color": 0, "unpaired_depth": 0, "no_camera_info": 0}


def test_depth_first_pairs_too():
    pairer = with_camera()
    assert pairer.depth(depth(1.0)) == []
    assert [f.timestamp for f in pairer.color(color(1.01))] == [1.01]


def test_unpaired_colour_is_counted():
    pairer = with_camera()
    pairer.color(color(1.0))  # its depth never comes
    pairer.color(color(1.1))
    frames = pairer.depth(depth(1.1))
    assert [f.timestamp for f in frames] == [1.1]
    assert pairer.counters()["unpaired_color"] == 1
    assert pairer.depth(depth(0.9)) == [] and pairer.counters()["unpaired_depth"] == 1  # late: older than the last pair


def test_unpaired_messages_are_bounded_by_stream_time():
    pairer = with_camera()
    for i in range(100):  # 4 Hz for 24.75 s, no depth: kept while within 10 s of the newest
        pairer.color(color(i * 0.25))
    assert MAX_UNPAIRED_AGE_S == 10.0
    assert pairer.counters()["unpaired_color"] == 59  # stamps 0 .. 14.5 s given up, 14.75 .. 24.75 s kept
    assert pairer.held_bytes == 41 * 64 * 48 * 3


def test_unpaired_messages_are_bounded_by_bytes_oldest_first():
    image = 64 * 48 * 3
    pairer = with_camera(max_bytes=10 * image)
    for i in range(30):
        pairer.color(color(i / 30))
    assert pairer.counters()["unpaired_color"] == 20 and pairer.held_bytes == 10 * image
    frames = pairer.depth(depth(29 / 30)) + pairer.depth(depth(19 / 30))  # the newest kept, the oldest dropped
    assert [f.timestamp for f in frames] == [29 / 30] and pairer.counters()["unpaired_depth"] == 1


def flood(n: int, seed: int, lead: float) -> list[tuple[str, float]]:
    """The messages of ``n`` frames at 30 Hz as a flood delivers them: each topic in order, but colour falling
    behind depth by up to ``lead`` frames and catching up, odometry now behind, now ahead (ties at random)."""
    rng = np.random.default_rng(seed)
    i = np.arange(n)
    shift = {
        "color": np.minimum(np.minimum(0.6 * i, 0.6 * (n - 1 - i)), lead),  # slopes < 1: colour stays in order
        "depth": 0.0 * i,
        "odom": 10 * np.sin(2 * np.pi * i / n),
    }
    keyed = [(k + shift[kind][k] + rng.uniform(0, 0.3), kind, k) for kind in shift for k in i]
    return [(kind, k / 30 + (0.004 if kind == "depth" else 0.0)) for _, kind, k in sorted(keyed)]


def feed(pairer: FramePairer, order: list[tuple[str, float]]) -> list[Frame]:
    frames = []
    for kind, t in order:
        if kind == "odom":
            pairer.odometry(Stamped(t, "odom", pose_from_tum(np.array([t, 0, 0, 0, 0, 0, 1.0]))))
            frames += [p.frame() for p in pairer.ready_pairs()]
        else:
            frames += pairer.color(color(t)) if kind == "color" else pairer.depth(depth(t))
    return frames + pairer.flush()


@pytest.mark.parametrize(("seed", "lead"), [(0, 40), (1, 120)])
def test_an_out_of_order_flood_pairs_every_frame_in_order_with_its_odometry(seed, lead):
    n = 400
    order = flood(n, seed, lead)
    kinds = np.array([{"color": 1, "depth": -1}[k] for k, _ in order if k != "odom"])
    assert -np.cumsum(kinds).min() >= lead - 1  # depth that far ahead: beyond the 30 messages once held (and 3 s)
    frames = feed(with_camera(hold_s=2.0, waits_for=["odom"]), order)
    assert [f.seq for f in frames] == list(range(n))
    np.testing.assert_allclose([f.timestamp for f in frames], np.arange(n) / 30)
    assert all(f.odometry is not None and f.odometry[0, 3] == f.timestamp for f in frames)


def test_a_lost_depth_does_not_hold_later_frames():
    pairer = with_camera()
    pairer.color(color(1.0))  # its depth is lost
    pairer.color(color(1.1))
    assert pairer.depth(depth(1.05)) == []  # depth has passed 1.0 (+ tolerance): colour 1.0 waits for nothing
    assert [f.timestamp for f in pairer.depth(depth(1.1))] == [1.1]
    assert pairer.counters()["unpaired_color"] == 1 and pairer.counters()["unpaired_depth"] == 1


def test_waiting_for_odometry_releases_as_soon_as_it_comes_or_after_the_hold():
    pairer = with_camera(hold_s=0.5, waits_for=["odom"])
    pairer.color(color(1.0))
    assert pairer.depth(depth(1.0)) == [] and pairer.ready_pairs() == []
    pairer.odometry(Stamped(1.0, "odom", POSE))
    (pair,) = pairer.ready_pairs()
    assert pair.timestamp == 1.0 and pair.odometry is not None and np.array_equal(pair.odometry, POSE)
    pairer.color(color(1.1))
    assert pairer.depth(depth(1.1)) == [] and pairer.color(color(1.5)) == []  # no odometry yet, 0.4 s later
    (frame,) = pairer.color(color(1.6))  # 0.5 s later: without it
    assert frame.timestamp == 1.1 and frame.odometry is None


def test_pairs_without_camera_info_are_counted():
    pairer = FramePairer()
    pairer.color(color(1.0))
    assert pairer.depth(depth(1.0)) == []
    assert pairer.counters()["no_camera_info"] == 1


def test_size_mismatch_is_counted():
    pairer = with_camera()
    pairer.color(color(1.0, w=32))
    assert pairer.depth(depth(1.0, w=32)) == []
    pairer.color(color(2.0))
    assert pairer.depth(depth(2.0, h=24)) == []
    assert pairer.counters()["size_mismatch"] == 2


def test_odometry_and_detections_join_by_stamp():
    pairer = with_camera()
    pairer.odometry(Stamped(0.99, "odom", POSE))
    pairer.odometry(Stamped(1.005, "odom", np.eye(4)))
    pairer.detections(Stamped(1.0, "cam", [Detection("cup", 0.5, (1.0, 1.0, 9.0, 9.0))]))
    pairer.color(color(1.0))
    (frame,) = pairer.depth(depth(1.0))
    assert frame.odometry is not None and frame.detections is not None
    assert np.array_equal(frame.odometry, np.eye(4)) and frame.detections[0].label == "cup"
    pairer.color(color(2.0))
    (frame,) = pairer.depth(depth(2.0))
    assert frame.odometry is None and frame.detections is None


def test_hold_lets_late_detections_join():
    pairer = with_camera(hold_s=0.1)
    pairer.color(color(1.0))
    assert pairer.depth(depth(1.0)) == []
    pairer.detections(Stamped(1.0, "cam", [Detection("cup", 0.5, (1.0, 1.0, 9.0, 9.0))]))
    assert pairer.color(color(1.05)) == []  # not yet 0.1 s later
    (frame,) = pairer.color(color(1.2))
    assert frame.timestamp == 1.0 and frame.detections is not None
    assert pairer.depth(depth(1.2)) == []
    assert [f.timestamp for f in pairer.flush()] == [1.2]


# ---------------------------------------------------------------- rosbag2


class Frames(Dataset):
    """Frames in memory, as a dataset."""

    def __init__(self, frames: list[Frame]):
        self.name, self.camera, self.frames = "frames", frames[0].camera, frames

    def __len__(self) -> int:
        return len(self.frames)

    def frame(self, index: int) -> Frame:
        return self.frames[index]


@pytest.fixture(scope="module")
def scene() -> Frames:
    source = open_dataset("synthetic:room?seed=0&frames=20")
    return Frames([source.frame(i) for i in range(len(source))])


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag_replays_the_scene(scene, tmp_path, storage):
    bag = write_rosbag(scene, tmp_path / "bag", TOPICS, storage=storage)
    replay = open_dataset(str(bag), ros_topics=TOPICS)
    assert len(replay) == len(scene) and replay.camera == scene.camera
    assert np.abs(replay.timestamps - [f.timestamp for f in scene.frames]).max() < 1e-9
    for i, original in enumerate(scene.frames):
        frame = replay.frame(i)
        assert abs(frame.timestamp - original.timestamp) <= 1e-9 and frame.index == i
        assert np.array_equal(frame.rgb, original.rgb) and np.array_equal(frame.depth, original.depth)
        assert np.abs(frame.odometry - original.odometry).max() < 1e-9
        assert frame.detections is not None and original.detections is not None
        assert [d.label for d in frame.detections] == [d.label for d in original.detections]
        assert np.allclose([d.box for d in frame.detections], [d.box for d in original.detections], atol=1e-9)


def test_rosbag_with_compressed_colour_and_float_depth(scene, tmp_path):
    topics = RosTopics("/rgb/compressed", "/depth", "/info", compressed=True)
    few = Frames(scene.frames[:4])
    bag = write_rosbag(few, tmp_path / "bag", topics, depth_encoding="32FC1", color_format="png")
    replay = open_dataset(f"{bag}?stride=2", ros_topics=topics)
    assert len(replay) == 2
    frame, original = replay.frame(1), few.frames[2]
    assert np.array_equal(frame.rgb, original.rgb) and np.array_equal(frame.depth, original.depth)
    assert frame.odometry is None and frame.detections is None


def test_rosbag_needs_its_topics(scene, tmp_path):
    bag = write_rosbag(Frames(scene.frames[:2]), tmp_path / "bag", TOPICS, storage="sqlite3")
    with pytest.raises(DatasetError, match="--rgb-topic, --depth-topic and --camera-info-topic"):
        open_dataset(str(bag))
    with pytest.raises(DatasetError, match="no topic /nope"):
        open_dataset(str(bag), ros_topics=RosTopics("/nope", TOPICS.depth, TOPICS.camera_info))
    with pytest.raises(DatasetError, match="carries sensor_msgs/msg/Image"):
        open_dataset(str(bag), ros_topics=RosTopics(TOPICS.rgb, TOPICS.depth, TOPICS.camera_info, compressed=True))


def test_typestore_knows_vision_msgs():
    assert DETECTIONS in typestore().types
