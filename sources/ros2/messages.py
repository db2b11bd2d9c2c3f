"""The ROS 2 messages of objslam in one place: type names, the typestore, stamps, decoders and encoders.

Decoders (``sources.ros2.decoders``) turn CDR bytes into frame parts and raise only ``FrameRejected``;
encoders (``sources.ros2.encoders``) make CDR bytes with the encapsulation header, as rmw_zenoh sends them.
"""

from __future__ import annotations

from sources.ros2.cdr import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DETECTIONS,
    IMAGE,
    MARKER_ARRAY,
    ODOMETRY,
    PATH,
    POSE_STAMPED,
    Stamped,
    from_stamp,
    stamp_ns,
    to_stamp,
    typestore,
)
from sources.ros2.decoders import (
    RawImage,
    decode_camera_info,
    decode_compressed_image,
    decode_detections,
    decode_image,
    decode_odometry,
    peek_compressed_image,
    peek_image,
    peek_raw_compressed_image,
    peek_raw_image,
    pixels,
)
from sources.ros2.encoders import (
    encode_camera_info,
    encode_compressed_image,
    encode_detections,
    encode_image,
    encode_marker_array,
    encode_odometry,
    encode_path,
    encode_pose_stamped,
)

__all__ = [
    "CAMERA_INFO",
    "COMPRESSED_IMAGE",
    "DETECTIONS",
    "IMAGE",
    "MARKER_ARRAY",
    "ODOMETRY",
    "PATH",
    "POSE_STAMPED",
    "RawImage",
    "Stamped",
    "decode_camera_info",
    "decode_compressed_image",
    "decode_detections",
    "decode_image",
    "decode_odometry",
    "encode_camera_info",
    "encode_compressed_image",
    "encode_detections",
    "encode_image",
    "encode_marker_array",
    "encode_odometry",
    "encode_path",
    "encode_pose_stamped",
    "from_stamp",
    "peek_compressed_image",
    "peek_image",
    "peek_raw_compressed_image",
    "peek_raw_image",
    "pixels",
    "stamp_ns",
    "to_stamp",
    "typestore",
]
