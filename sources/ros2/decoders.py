"""Decoding ROS 2 messages into objslam's frame parts, with protocol v1's rejection reasons.

Every decoder raises ``perception.frame.FrameRejected`` and nothing else: ``BAD_HEADER`` when the bytes are not
CDR of the expected type, then the reason of the first field found wrong, with a detail naming it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from graph.geometry import pose_from_tum
from perception.frame import CameraModel, Detection, FrameRejected, Intrinsics, Reason
from perception.image_probe import ProbeError, probe
from sources.ros2.cdr import CAMERA_INFO, COMPRESSED_IMAGE, DETECTIONS, IMAGE, ODOMETRY, Stamped, deserialize, stamp_of

MAX_DETECTIONS = 512
RAW_ENCODINGS = {"rgb8": (1, 3), "bgr8": (1, 3), "mono8": (1, 1), "16UC1": (2, 1), "32FC1": (4, 1)}
"""Supported sensor_msgs/Image encodings: (bytes per channel, channels)."""
DEPTH_ENCODINGS = ("16UC1", "32FC1")


def _message(raw: bytes | memoryview, typename: str) -> Any:
    try:
        return deserialize(raw, typename)
    except Exception as exc:  # rosbags raises SerdeError, struct.error, IndexError... on hostile bytes
        raise FrameRejected(Reason.BAD_HEADER, f"not a {typename} CDR message: {exc}") from None


def _stamped(message: Any, value: Any, encoding: str = "") -> Stamped[Any]:
    return Stamped(stamp_of(message), str(message.header.frame_id), value, encoding)


def _check_size(width: int, height: int, max_pixels: int, what: str) -> None:
    if width == 0 or height == 0:
        raise FrameRejected(Reason.BAD_IMAGE, f"{what} is empty ({width}x{height})")
    if width * height > max_pixels:
        raise FrameRejected(Reason.TOO_LARGE, f"{what} {width}x{height} exceeds {max_pixels} pixels")


@dataclass(frozen=True, eq=False)
class RawImage:
    """An Image or CompressedImage message as it arrived, checked but not converted: what pairing needs (its
    ``shape``, (height, width)) and what holding it costs (``nbytes``, the message's size).

    ``rows``: a raw Image's pixel rows (height x row bytes, padding cut), a view of ``raw``; None when compressed.
    """

    raw: bytes
    shape: tuple[int, int]
    encoding: str
    rows: np.ndarray | None = None
    big_endian: bool = False

    @property
    def nbytes(self) -> int:
        return len(self.raw)


def decode_image(raw: bytes | memoryview, max_pixels: int) -> Stamped[np.ndarray]:
    """A sensor_msgs/Image: colour (rgb8, bgr8, mono8) as HxWx3 uint8 RGB, depth (16UC1, 32FC1) as HxW uint16
    millimetres (32FC1 metres x 1000, rounded; NaN, inf and <= 0 become 0, beyond 65.535 m 65535).
    ``encoding`` of the result is the message's; row padding (``step``) and byte order are honoured."""
    msg = peek_raw_image(raw, max_pixels)
    return Stamped(msg.stamp, msg.frame_id, pixels(msg.value, max_pixels), msg.encoding)


def peek_image(raw: bytes | memoryview, max_pixels: int) -> Stamped[tuple[int, int]]:
    """Every check of ``decode_image`` but the conversion: the value is the image's (height, width)."""
    msg = peek_raw_image(raw, max_pixels)
    return Stamped(msg.stamp, msg.frame_id, msg.value.shape, msg.encoding)


def peek_raw_image(raw: bytes | memoryview, max_pixels: int) -> Stamped[RawImage]:
    """Every check of ``decode_image``, no pixel copied: the value keeps the message (``pixels`` converts it)."""
    data = bytes(raw)
    msg, rows = _checked_image(memoryview(data), max_pixels)
    image = RawImage(data, (int(msg.height), int(msg.width)), str(msg.encoding), rows, bool(msg.is_bigendian))
    return _stamped(msg, image, image.encoding)


def pixels(image: RawImage, max_pixels: int, copy: bool = True) -> np.ndarray:
    """The image of a checked message: colour as HxWx3 uint8 RGB, depth as HxW uint16 millimetres (as
    ``decode_image`` and ``decode_compressed_image`` give them). ``copy=False``: rgb8 and little-endian 16UC1
    without row padding come as read-only views of the message's bytes, nothing copied."""
    if image.rows is None:
        return decode_compressed_image(image.raw, max_pixels).value
    (height, width), encoding, rows = image.shape, image.encoding, image.rows
    order = ">" if image.big_endian else "<"
    if encoding == "16UC1":
        view = np.ascontiguousarray(rows).view(f"{order}u2").reshape(height, width)
        return view.astype(np.uint16) if copy or order == ">" else view
    if encoding == "32FC1":
        metres = np.ascontiguousarray(rows).view(f"{order}f4").astype(np.float64).reshape(height, width)
        bad = ~np.isfinite(metres) | (metres <= 0)
        return np.rint(np.clip(np.where(bad, 0.0, metres) * 1000.0, 0, 65535)).astype(np.uint16)
    rgb = rows.reshape(height, width, RAW_ENCODINGS[encoding][1])
    if encoding == "mono8":
        return np.repeat(rgb, 3, axis=2)
    if encoding == "bgr8":
        return np.ascontiguousarray(rgb[..., ::-1])
    return np.array(rgb, order="C") if copy else rgb  # owned and writable, or the view


def _checked_image(raw: bytes | memoryview, max_pixels: int) -> tuple[Any, np.ndarray]:
    """The Image message and its pixel rows (height x row bytes, padding cut) once encoding and sizes agree."""
    msg = _message(raw, IMAGE)
    width, height, encoding, step = int(msg.width), int(msg.height), str(msg.encoding), int(msg.step)
    if encoding not in RAW_ENCODINGS:
        raise FrameRejected(Reason.BAD_FIELD, f"image encoding {encoding!r} not in {sorted(RAW_ENCODINGS)}")
    _check_size(width, height, max_pixels, f"{encoding} image")
    size, channels = RAW_ENCODINGS[encoding]
    row = width * size * channels
    if step < row:
        raise FrameRejected(Reason.SIZE_MISMATCH, f"{encoding} step {step} < width {width} x {size * channels} bytes")
    data = np.asarray(msg.data, dtype=np.uint8)
    if len(data) != step * height:
        raise FrameRejected(
            Reason.SIZE_MISMATCH, f"{encoding} data has {len(data)} bytes, step x height = {step * height}"
        )
    rows = data.reshape(height, step)
    return msg, rows if step == row else rows[:, :row]


def peek_compressed_image(raw: bytes | memoryview, max_pixels: int) -> Stamped[tuple[int, int]]:
    """Every check of ``decode_compressed_image`` but the decoding: the value is (height, width) as the image's
    own header (JPEG SOF, PNG IHDR) declares it, so a decompression bomb is refused unread."""
    msg, kind = _compressed(raw)
    found = _probe(msg.data, kind, max_pixels)
    return _stamped(msg, (found[0], found[1]), kind)


def peek_raw_compressed_image(raw: bytes | memoryview, max_pixels: int) -> Stamped[RawImage]:
    """``peek_compressed_image`` keeping the message: ``pixels`` decodes it."""
    found = peek_compressed_image(raw, max_pixels)
    return Stamped(found.stamp, found.frame_id, RawImage(bytes(raw), found.value, found.encoding), found.encoding)


def decode_compressed_image(raw: bytes | memoryview, max_pixels: int) -> Stamped[np.ndarray]:
    """A sensor_msgs/CompressedImage (jpeg or png, also image_transport's ``rgb8; jpeg compressed bgr8``) as
    HxWx3 uint8 RGB; its declared size is checked against ``max_pixels`` before anything is decoded."""
    msg, kind = _compressed(raw)
    height, width = _probe(msg.data, kind, max_pixels)
    bgr = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[:2] != (height, width):
        raise FrameRejected(Reason.BAD_IMAGE, f"{kind} data does not decode to its declared {width}x{height} image")
    return _stamped(msg, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), kind)


def _compressed(raw: bytes | memoryview) -> tuple[Any, str]:
    msg = _message(raw, COMPRESSED_IMAGE)
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        raise FrameRejected(
            Reason.BAD_FIELD, f"compressed image format {msg.format!r}: compressedDepth is not supported"
        )
    if "jpeg" in fmt or "jpg" in fmt:
        return msg, "jpeg"
    if "png" in fmt:
        return msg, "png"
    raise FrameRejected(Reason.BAD_FIELD, f"compressed image format {msg.format!r} is neither jpeg nor png")


def _probe(data: Any, kind: str, max_pixels: int) -> tuple[int, int]:
    try:
        found = probe(np.asarray(data, dtype=np.uint8).data, kind)
    except ProbeError as exc:
        raise FrameRejected(Reason.BAD_IMAGE, f"{kind} image: {exc}") from None
    _check_size(found.width, found.height, max_pixels, f"{kind} image")
    return found.height, found.width


def decode_camera_info(raw: bytes | memoryview) -> Stamped[CameraModel]:
    """A sensor_msgs/CameraInfo as a registered ``CameraModel`` (K, image size, depth in millimetres).

    Images with distortion are refused (objslam's geometry is pinhole), as are binning and a region of interest."""
    msg = _message(raw, CAMERA_INFO)
    width, height = int(msg.width), int(msg.height)
    if width == 0 or height == 0:
        raise FrameRejected(Reason.BAD_INTRINSICS, f"camera info image size {width}x{height}")
    d = np.asarray(msg.d, dtype=float)
    if np.any(d != 0):
        raise FrameRejected(
            Reason.BAD_INTRINSICS,
            f"distorted images are not supported (distortion_model {msg.distortion_model}, d={d.tolist()})",
        )
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1 or int(msg.roi.width) or int(msg.roi.height):
        raise FrameRejected(Reason.BAD_INTRINSICS, "camera info with binning or a region of interest is not supported")
    k = np.asarray(msg.k, dtype=float)
    fx, fy, cx, cy = float(k[0]), float(k[4]), float(k[2]), float(k[5])
    if not (np.all(np.isfinite(k)) and fx > 0 and fy > 0):
        raise FrameRejected(
            Reason.BAD_INTRINSICS, f"camera matrix K={k.tolist()} is not finite with positive focal lengths"
        )
    return _stamped(msg, CameraModel(Intrinsics(fx, fy, cx, cy), width, height, depth_scale=1000.0))


def decode_odometry(raw: bytes | memoryview) -> Stamped[np.ndarray]:
    """A nav_msgs/Odometry's pose.pose as a 4x4 camera-to-world pose (checked as protocol v1 checks odometry)."""
    msg = _message(raw, ODOMETRY)
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    values = np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=float)
    return _stamped(msg, pose_of(values, "odometry"))


def pose_of(values: np.ndarray, what: str) -> np.ndarray:
    """The 4x4 pose of ``tx ty tz qx qy qz qw``; BAD_POSE unless finite, unit quaternion, within 100 km."""
    if not np.all(np.isfinite(values)):
        raise FrameRejected(Reason.BAD_POSE, f"{what} has a non-finite value")
    norm = float(np.linalg.norm(values[3:]))
    if abs(norm - 1.0) > 1e-3:
        raise FrameRejected(Reason.BAD_POSE, f"{what} quaternion norm {norm:.4f} is not 1")
    if np.abs(values[:3]).max() > 1e5:
        raise FrameRejected(Reason.BAD_POSE, f"{what} translation beyond 100 km")
    return pose_from_tum(values)


def decode_detections(raw: bytes | memoryview, width: int, height: int) -> Stamped[list[Detection]]:
    """A vision_msgs/Detection2DArray as detections in a ``width`` x ``height`` image: label and score of each
    detection's first result (detections without results are skipped), box from the bounding box (a rotated one
    by its axis-aligned bounds) clipped to the image."""
    msg = _message(raw, DETECTIONS)
    if len(msg.detections) > MAX_DETECTIONS:
        raise FrameRejected(Reason.BAD_DETECTIONS, f"{len(msg.detections)} detections, at most {MAX_DETECTIONS}")
    out = []
    for i, det in enumerate(msg.detections):
        if not det.results:
            continue
        hypothesis = det.results[0].hypothesis
        label, score = str(hypothesis.class_id), float(hypothesis.score)
        if not 0 < len(label) <= 64 or not label.isprintable():
            raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: class_id must be a printable 1-64 characters")
        if not 0.0 <= score <= 1.0:
            raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: score {score} is not in [0, 1]")
        out.append(Detection(label, score, _box(det.bbox, i, width, height)))
    return _stamped(msg, out)


def _box(bbox: Any, i: int, width: int, height: int) -> tuple[float, float, float, float]:
    cx, cy, theta = float(bbox.center.position.x), float(bbox.center.position.y), float(bbox.center.theta)
    sx, sy = float(bbox.size_x), float(bbox.size_y)
    if not all(math.isfinite(v) for v in (cx, cy, theta, sx, sy)) or sx <= 0 or sy <= 0:
        raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: box must be finite with a positive size")
    c, s = abs(math.cos(theta)), abs(math.sin(theta))
    half_w, half_h = (sx * c + sy * s) / 2, (sx * s + sy * c) / 2
    x1, x2 = max(cx - half_w, 0.0), min(cx + half_w, float(width))
    y1, y2 = max(cy - half_h, 0.0), min(cy + half_h, float(height))
    if x2 - x1 < 1.0 or y2 - y1 < 1.0:
        raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: box lies outside the {width}x{height} image")
    return (x1, y1, x2, y2)
