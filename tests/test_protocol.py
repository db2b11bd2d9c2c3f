"""Protocol v1: round trip and rejection of each kind of bad input with its reason."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from perception.frame import CameraModel, Intrinsics
from service.protocol import PREAMBLE, FrameRejected, Limits, Reason, decode_frame, encode_frame, split_message
from tests.conftest import make_frame


def _rewrite_header(payload: bytes, edit) -> bytes:
    header, body = split_message(payload)
    edit(header)
    head = json.dumps(header).encode()
    return PREAMBLE.pack(b"OSLM", 1, 0, len(head)) + head + body


def _reason(payload: bytes, limits: Limits | None = None) -> Reason:
    with pytest.raises(FrameRejected) as info:
        decode_frame(payload, Limits() if limits is None else limits)
    return info.value.reason


@pytest.mark.parametrize("color,depth", [("png", "png16"), ("rgb8", "u16le"), ("jpeg", "png16")])
def test_round_trip_preserves_every_field(color, depth):
    f = make_frame(t=12.5, seq=7)
    g = decode_frame(encode_frame(f, color, depth))
    assert (g.timestamp, g.seq, g.frame_id) == (12.5, 7, "test/7")
    assert g.camera == f.camera
    np.testing.assert_array_equal(g.depth, f.depth)  # depth is lossless in both encodings
    if color == "jpeg":
        assert np.abs(g.rgb.astype(int) - f.rgb.astype(int)).mean() < 6
    else:
        np.testing.assert_array_equal(g.rgb, f.rgb)
    np.testing.assert_allclose(g.odometry, f.odometry, atol=1e-12)
    assert g.detections == f.detections


def test_unregistered_camera_round_trips():
    f = make_frame()
    extr = np.eye(4)
    extr[:3, 3] = [0.025, 0.0, 0.0]
    f.camera = CameraModel(f.camera.color, f.camera.width, f.camera.height, 1000.0, Intrinsics(58, 58, 32, 24), extr)
    g = decode_frame(encode_frame(f, "png"))
    assert g.camera.depth_intrinsics == Intrinsics(58, 58, 32, 24)
    np.testing.assert_allclose(g.camera.depth_to_color, extr)
    # compared by value, 4 x 4 transform included (the live view compares each keyframe's camera with the last)
    assert g.camera == f.camera and hash(g.camera) == hash(f.camera) and g.camera != make_frame().camera
    moved = extr.copy()
    moved[0, 3] = 0.05
    assert g.camera != CameraModel(
        f.camera.color, f.camera.width, f.camera.height, 1000.0, Intrinsics(58, 58, 32, 24), moved
    )


def test_frame_without_odometry_or_detections_decodes_to_none():
    f = make_frame()
    f.odometry, f.detections = None, None
    g = decode_frame(encode_frame(f, "png"))
    assert g.odometry is None and g.detections is None


def test_truncated_payloads_are_rejected_as_truncated_or_size_mismatch():
    payload = encode_frame(make_frame(), "png")
    assert _reason(payload[:5]) is Reason.TRUNCATED
    assert _reason(payload[: PREAMBLE.size + 10]) is Reason.TRUNCATED
    assert _reason(payload[:-1]) is Reason.SIZE_MISMATCH
    assert _reason(payload + b"\0") is Reason.SIZE_MISMATCH


def test_bad_magic_and_unknown_version_are_rejected():
    payload = encode_frame(make_frame(), "png")
    assert _reason(b"XXXX" + payload[4:]) is Reason.BAD_MAGIC
    assert _reason(payload[:4] + struct.pack("<H", 2) + payload[6:]) is Reason.UNSUPPORTED_VERSION
    assert _reason(_rewrite_header(payload, lambda h: h.update(version=3))) is Reason.UNSUPPORTED_VERSION


def test_header_that_is_not_json_is_rejected():
    payload = encode_frame(make_frame(), "png")
    hlen = struct.unpack_from("<I", payload, 8)[0]
    broken = payload[: PREAMBLE.size] + b"{" * hlen + payload[PREAMBLE.size + hlen :]
    assert _reason(broken) is Reason.BAD_HEADER


@pytest.mark.parametrize(
    "field,value",
    [("fx", float("nan")), ("fy", -1.0), ("cx", 1e9), ("depth_scale", 0), ("depth_scale", float("inf")), ("width", 0)],
)
def test_bad_intrinsics_are_rejected(field, value):
    payload = encode_frame(make_frame(), "png")
    assert _reason(_rewrite_header(payload, lambda h: h["camera"].update({field: value}))) is Reason.BAD_INTRINSICS


@pytest.mark.parametrize(
    "odom", [[0, 0, 0, 0, 0, 0, 2.0], [float("nan")] * 7, [0, 0, 0, 1], "pose", [1e9, 0, 0, 0, 0, 0, 1]]
)
def test_bad_odometry_is_rejected(odom):
    payload = encode_frame(make_frame(), "png")
    assert _reason(_rewrite_header(payload, lambda h: h.update(odometry=odom))) is Reason.BAD_POSE


def test_nan_timestamp_is_a_bad_field():
    payload = encode_frame(make_frame(), "png")
    assert _reason(_rewrite_header(payload, lambda h: h.update(timestamp=float("nan")))) is Reason.BAD_FIELD
    assert _reason(_rewrite_header(payload, lambda h: h.pop("timestamp"))) is Reason.BAD_FIELD
    assert _reason(_rewrite_header(payload, lambda h: h.update(seq=-1))) is Reason.BAD_FIELD


@pytest.mark.parametrize(
    "edit",
    [
        lambda h: h.update(timestamp=10**400),
        lambda h: h["camera"].update(fx=10**400),
        lambda h: h["camera"].update(depth_scale=10**30),
        lambda h: h.update(odometry=[10**400, 0, 0, 0, 0, 0, 1]),
        lambda h: h["detections"][0].update(box=[0, 0, 10**400, 5]),
        lambda h: h["camera"].update(depth_to_color=[[10**400] * 4] * 4),
        lambda h: h.update(unknown=-(2**63)),
    ],
)
def test_integers_beyond_64_bits_are_a_bad_header_not_an_overflow(edit):
    # fuzz finding: such literals made float() raise OverflowError (or int() ValueError) past the validators
    payload = encode_frame(make_frame(), "rgb8", "u16le")
    assert _reason(_rewrite_header(payload, edit)) is Reason.BAD_HEADER


def test_integer_beyond_pythons_digit_limit_is_a_bad_header():
    payload = encode_frame(make_frame(), "rgb8", "u16le")
    header, body = split_message(payload)
    head = json.dumps(header).replace('"seq": 0', '"seq": ' + "9" * 5000).encode()  # int() refuses > 4300 digits
    assert _reason(PREAMBLE.pack(b"OSLM", 1, 0, len(head)) + head + body) is Reason.BAD_HEADER


def test_largest_64_bit_integers_still_decode():
    payload = encode_frame(make_frame(), "rgb8", "u16le")
    assert decode_frame(_rewrite_header(payload, lambda h: h.update(seq=2**63 - 1))).seq == 2**63 - 1


@pytest.mark.parametrize(
    "dets",
    [
        [{"label": "cup", "score": 0.5, "box": [10, 10, 5, 5]}],  # corners out of order
        [{"label": "cup", "score": 0.5, "box": [1000, 1000, 2000, 2000]}],  # outside the image
        [{"label": "cup", "score": 1.5, "box": [1, 1, 5, 5]}],  # score out of range
        [{"label": "", "score": 0.5, "box": [1, 1, 5, 5]}],  # empty label
        [{"label": "cup", "score": 0.5, "box": [1, 1, float("nan"), 5]}],  # NaN coordinate
        "cup",
    ],
)
def test_absurd_detections_are_rejected(dets):
    payload = encode_frame(make_frame(), "png")
    assert _reason(_rewrite_header(payload, lambda h: h.update(detections=dets))) is Reason.BAD_DETECTIONS


def test_boxes_partly_outside_are_clipped_to_the_image():
    f = make_frame()
    payload = _rewrite_header(
        encode_frame(f, "png"), lambda h: h.update(detections=[{"label": "tv", "score": 0.7, "box": [-5, -5, 30, 400]}])
    )
    assert decode_frame(payload).detections[0].box == (0.0, 0.0, 30.0, 48.0)


def test_image_whose_size_disagrees_with_header_is_rejected():
    payload = encode_frame(make_frame(), "png")
    assert _reason(_rewrite_header(payload, lambda h: h["camera"].update(width=65))) is Reason.SIZE_MISMATCH
    assert _reason(_rewrite_header(payload, lambda h: h["color"].update(encoding="bmp"))) is Reason.BAD_FIELD


def test_corrupt_image_bytes_are_bad_image():
    f = make_frame()
    payload = bytearray(encode_frame(f, "png"))
    _, body = split_message(bytes(payload))
    start = len(payload) - len(body)
    payload[start : start + 40] = b"\0" * 40  # destroy the colour PNG signature
    assert _reason(bytes(payload)) is Reason.BAD_IMAGE


def test_oversized_payload_is_too_large():
    payload = encode_frame(make_frame(), "png")
    assert _reason(payload, Limits(max_payload_bytes=1024)) is Reason.TOO_LARGE
