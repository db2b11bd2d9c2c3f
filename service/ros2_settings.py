"""The ``ros2`` settings section: ROS 2 topics carried by rmw_zenoh, and the results published back."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Ros2Settings(BaseModel):
    """ROS 2 topics carried by rmw_zenoh (``serve --ros2``) and the results published back as ROS 2 messages."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = Field(False, description="subscribe to the ROS 2 topics below (serve --ros2)")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID")
    rgb_topic: str = Field("/camera/color/image_raw", description="sensor_msgs/Image or CompressedImage")
    depth_topic: str = Field("/camera/aligned_depth_to_color/image_raw", description="16UC1 mm or 32FC1 m")
    camera_info_topic: str = Field("/camera/color/camera_info", description="sensor_msgs/CameraInfo, undistorted")
    odom_topic: str | None = Field(None, description="nav_msgs/Odometry: the frames' external odometry")
    detections_topic: str | None = Field(None, description="vision_msgs/Detection2DArray: provided detections")
    sync_tolerance_s: float = Field(0.02, gt=0, description="colour and depth stamps paired within this")
    queue_messages: int = Field(4096, ge=8, description="raw messages held for decoding; beyond, the oldest drop")
    queue_bytes: int = Field(
        256 * 2**20, ge=2**20, description="bytes of raw messages held for decoding; beyond, the oldest drop"
    )
    publish: bool = Field(True, description="publish the path, pose and objects as ROS 2 messages")
    map_frame: str = Field("map", description="frame_id of the published results")
    results_namespace: str = Field("/objslam", description="topics: <namespace>/path, /pose, /objects")
