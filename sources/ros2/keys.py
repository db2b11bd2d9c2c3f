"""rmw_zenoh's names on the wire: topic key expressions, RIHS01 type hashes and the publication attachment.

A ROS 2 node on rmw_zenoh (Jazzy) publishes topic ``/camera/color/image_raw`` of domain 0 under the key
``0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/RIHS01_<sha256>``, the payload being the CDR message
and the attachment its sequence number, source timestamp and publisher GID (zenoh-cpp's ext serializer).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from sources.ros2.cdr import typestore

ANY_HASH = "*"
_WILDCARDS = set("*$?#")
_DDS_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)::(msg|srv|action)::dds_::([A-Za-z][A-Za-z0-9_]*)_$")
_TYPENAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)$")

JAZZY_TYPE_HASHES: dict[str, str] = {
    # Each value is the RIHS01 ROS 2 Jazzy's own packages publish, found independently of rosbags:
    # rmw_zenoh keys and `ros2 topic info -v` output quoted in public code, and rosidl-generated C
    # (`*__TYPE_HASH`, `*__get_type_hash`) of Jazzy builds (vision_msgs 4.1: Detection2DArray).
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CompressedImage": "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "nav_msgs/msg/Odometry": "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "vision_msgs/msg/Detection2DArray": "RIHS01_214274120007f4a683866481336b70310268cfa107aebe9d594a6acf75bda968",
    "nav_msgs/msg/Path": "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    "geometry_msgs/msg/PoseStamped": "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "visualization_msgs/msg/MarkerArray": "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
}


@dataclass(frozen=True)
class RosKey:
    """A parsed rmw_zenoh topic key: ``topic`` with its leading slash, ``typename`` as ``sensor_msgs/msg/Image``."""

    domain_id: int
    topic: str
    typename: str
    type_hash: str


def type_hash(typename: str) -> str:
    """The RIHS01 hash of a message type in objslam's typestore (Jazzy, plus vision_msgs)."""
    return typestore().hash_rihs01(typename)


def ros_key(domain_id: int, topic: str, typename: str, type_hash: str | None) -> str:
    """The key expression rmw_zenoh publishes ``topic`` of ``typename`` under; ``type_hash=None`` puts ``*`` in the
    hash's place (a subscription to any version of the type)."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise ValueError(f"ROS domain id must be a non-negative integer, got {domain_id!r}")
    name = topic.strip("/")
    if not name or _WILDCARDS & set(name) or any(not chunk for chunk in name.split("/")):
        raise ValueError(
            f"ROS topic {topic!r} must be a non-empty name without empty parts or {''.join(sorted(_WILDCARDS))}"
        )
    dds = dds_type_name(typename)
    if type_hash is not None and (not type_hash or "/" in type_hash or _WILDCARDS & set(type_hash)):
        raise ValueError(f"type hash {type_hash!r} is not a single key chunk")
    return f"{domain_id}/{name}/{dds}/{ANY_HASH if type_hash is None else type_hash}"


def dds_type_name(typename: str) -> str:
    """rmw_zenoh's type chunk of ``typename``: ``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_``."""
    match = _TYPENAME.match(typename)
    if match is None:
        raise ValueError(f"message type {typename!r} is not of the form package/msg/Type")
    package, kind, name = match.groups()
    return f"{package}::{kind}::dds_::{name}_"


def parse_ros_key(key: str) -> RosKey:
    """The parts of an rmw_zenoh topic key; ValueError for a key not of the form ``ros_key`` makes."""
    chunks = str(key).split("/")
    if len(chunks) < 4 or not chunks[0].isdigit() or not chunks[0].isascii():
        raise ValueError(f"{key!r} is not an rmw_zenoh topic key (domain/topic/type/hash)")
    match = _DDS_TYPE.match(chunks[-2])
    if match is None or not chunks[-1] or any(not chunk for chunk in chunks[1:-2]):
        raise ValueError(f"{key!r} is not an rmw_zenoh topic key (domain/topic/package::msg::dds_::Type_/hash)")
    package, kind, name = match.groups()
    return RosKey(int(chunks[0]), "/" + "/".join(chunks[1:-2]), f"{package}/{kind}/{name}", chunks[-1])


# ---------------------------------------------------------------- attachment

GID_SIZE = 16  # RMW_GID_STORAGE_SIZE in Jazzy
_INT64_PAIR = struct.Struct("<qq")


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to each publication: sequence number, source timestamp (ns), publisher GID."""

    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes


def encode_attachment(a: Attachment) -> bytes:
    """rmw_zenoh's attachment (``attachment_helpers.cpp``, zenoh-cpp ``ext::Serializer``): int64 LE sequence
    number, int64 LE source timestamp, then the GID as a sequence: LEB128 length 16 and the 16 bytes."""
    if len(a.source_gid) != GID_SIZE:
        raise ValueError(f"source_gid must be {GID_SIZE} bytes, got {len(a.source_gid)}")
    return _INT64_PAIR.pack(a.sequence_number, a.source_timestamp_ns) + _leb128(GID_SIZE) + bytes(a.source_gid)


def decode_attachment(data: bytes | None) -> Attachment | None:
    """The attachment of ``encode_attachment``'s layout; None when absent or not parseable (never raises)."""
    try:
        if data is None:
            return None
        data = bytes(data)
        if len(data) < _INT64_PAIR.size + 1 + GID_SIZE:
            return None
        sequence_number, timestamp = _INT64_PAIR.unpack_from(data)
        length, pos = _read_leb128(data, _INT64_PAIR.size)
        if length != GID_SIZE or pos + GID_SIZE > len(data):
            return None
        return Attachment(sequence_number, timestamp, data[pos : pos + GID_SIZE])
    except Exception:  # whatever the bytes are, the frame itself does not depend on them
        return None


def _leb128(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _read_leb128(data: bytes, pos: int) -> tuple[int, int]:
    """The unsigned LEB128 integer at ``pos`` and the position after it; ValueError past 10 bytes or the end."""
    value = 0
    for shift in range(0, 70, 7):
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
    raise ValueError("LEB128 integer longer than 10 bytes")
