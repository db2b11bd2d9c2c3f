"""The ROS 2 message types objslam speaks, their CDR (de)serialisation (``rosbags``) and header stamps.

The typestore is rosbags' ROS 2 Jazzy store plus ``vision_msgs`` 4.x (Jazzy's release), whose definitions
are written below as the package ships them (comments left out: they change no field and no RIHS01 hash).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
DETECTIONS = "vision_msgs/msg/Detection2DArray"
PATH = "nav_msgs/msg/Path"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

VISION_MSGS = {  # ros-perception/vision_msgs 4.1 (ROS 2 Jazzy), vision_msgs/msg/*.msg
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox2D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nDetection2D[] detections\n",
}

_NUMPY_DTYPES = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "octet": np.uint8}

T = TypeVar("T")


@dataclass(frozen=True)
class Stamped(Generic[T]):
    """A decoded message: ``stamp`` (header.stamp in seconds), ``frame_id`` (header.frame_id) and its ``value``.

    ``encoding`` says what an image's value came from (``rgb8``, ``bgr8``, ``mono8``, ``16UC1``, ``32FC1``,
    ``jpeg``, ``png``); it is empty for other messages.
    """

    stamp: float
    frame_id: str
    value: T
    encoding: str = ""


@functools.cache
def typestore() -> Typestore:
    """rosbags' ROS 2 Jazzy typestore with the ``vision_msgs`` types registered (built once)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def to_stamp(seconds: float) -> tuple[int, int]:
    """builtin_interfaces/Time ``(sec, nanosec)`` of a time in seconds, rounded to the nanosecond."""
    if not math.isfinite(seconds) or not 0.0 <= seconds < 2.0**31:
        raise ValueError(f"time {seconds} s does not fit a ROS 2 stamp")
    sec = math.floor(seconds)
    nanosec = round((seconds - sec) * 1e9)  # seconds - sec is exact
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return sec, nanosec


def from_stamp(sec: int, nanosec: int) -> float:
    """Seconds of a builtin_interfaces/Time (the nearest float)."""
    return (sec * 1_000_000_000 + nanosec) / 1e9


def stamp_ns(seconds: float) -> int:
    """Nanoseconds since the epoch of a time in seconds, as ``to_stamp`` rounds it."""
    sec, nanosec = to_stamp(seconds)
    return sec * 1_000_000_000 + nanosec


def make(typename: str, **fields: Any) -> Any:
    """A message of ``typename`` with the given fields and every other field zero, empty or default-built."""
    store = typestore()
    _, defs = store.fielddefs[typename]
    values = {name: fields.pop(name) if name in fields else _default(desc) for name, desc in defs}
    if fields:
        raise TypeError(f"{typename} has no fields {sorted(fields)}")
    return store.types[typename](**values)


def _default(desc: Any) -> Any:
    kind, rest = desc
    if kind == Nodetype.NAME:
        return make(rest)
    if kind == Nodetype.BASE:
        name = rest[0]
        return "" if name == "string" else False if name == "bool" else 0.0 if name.startswith("float") else 0
    (item_kind, item), length = rest  # ARRAY (fixed length) or SEQUENCE (length 0: empty)
    if item_kind == Nodetype.BASE and item[0] != "string":
        return np.zeros(length, dtype=_NUMPY_DTYPES.get(item[0], item[0]))
    return [_default((item_kind, item)) for _ in range(length if kind == Nodetype.ARRAY else 0)]


def header(stamp: float, frame_id: str) -> Any:
    """A std_msgs/Header."""
    sec, nanosec = to_stamp(stamp)
    return make(
        "std_msgs/msg/Header", stamp=make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def serialize(message: Any, typename: str) -> bytes:
    """CDR little-endian with its 4-byte encapsulation header (``00 01 00 00``), as rmw_zenoh sends it."""
    return bytes(typestore().serialize_cdr(message, typename, little_endian=True))


def deserialize(raw: bytes | memoryview, typename: str) -> Any:
    """The message object of CDR bytes; rosbags' exceptions pass through (decoders turn them into rejections)."""
    return typestore().deserialize_cdr(raw, typename)


def stamp_of(message: Any) -> float:
    """header.stamp of a message in seconds."""
    return from_stamp(int(message.header.stamp.sec), int(message.header.stamp.nanosec))
