"""The ROS 2 flags of ``serve``, ``replay`` and ``run`` (``--ros2``, ``--rgb-topic``, ...)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    from sources.ros2.pairing import RosTopics

Ros2Opt = Annotated[bool, typer.Option("--ros2", help="subscribe to ROS 2 topics carried by rmw_zenoh")]
RgbTopicOpt = Annotated[str | None, typer.Option("--rgb-topic", help="ROS 2 colour topic (Image or CompressedImage)")]
DepthTopicOpt = Annotated[str | None, typer.Option("--depth-topic", help="ROS 2 depth topic (16UC1 mm or 32FC1 m)")]
InfoTopicOpt = Annotated[str | None, typer.Option("--camera-info-topic", help="ROS 2 CameraInfo topic")]
OdomTopicOpt = Annotated[str | None, typer.Option("--odom-topic", help="ROS 2 nav_msgs/Odometry topic")]
DetectionsTopicOpt = Annotated[
    str | None, typer.Option("--detections-topic", help="ROS 2 vision_msgs/Detection2DArray topic")
]
DomainOpt = Annotated[int | None, typer.Option("--ros-domain-id", help="ROS_DOMAIN_ID (default 0)")]


def ros2_overrides(
    enabled: bool,
    rgb: str | None,
    depth: str | None,
    info: str | None,
    domain: int | None = None,
    odom: str | None = None,
    detections: str | None = None,
) -> dict[str, Any]:
    """The ``ros2`` settings the flags give (only those given)."""
    values = {
        "enabled": True if enabled else None,
        "rgb_topic": rgb,
        "depth_topic": depth,
        "camera_info_topic": info,
        "domain_id": domain,
        "odom_topic": odom,
        "detections_topic": detections,
    }
    return {k: v for k, v in values.items() if v is not None}


def is_rosbag(spec: str) -> bool:
    """A rosbag2 recording: a directory holding ``metadata.yaml``."""
    return (Path(spec) / "metadata.yaml").is_file()


def ros_topics(
    rgb: str | None, depth: str | None, info: str | None, odom: str | None, detections: str | None
) -> RosTopics | None:
    """The topics of a rosbag2 recording to read; None when no topic flag was given."""
    if rgb is None and depth is None and info is None:
        return None
    from service.cli_common import UserError
    from sources.ros2.pairing import RosTopics

    if rgb is None or depth is None or info is None:
        raise UserError("a rosbag2 recording needs --rgb-topic, --depth-topic and --camera-info-topic")
    return RosTopics(rgb, depth, info, odom, detections)
