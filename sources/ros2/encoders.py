"""Encoding objslam's frames, trajectory and map as ROS 2 messages: CDR bytes with the encapsulation header,
as rmw_zenoh puts them on the wire and rosbag2 stores them."""

from __future__ import annotations

import colorsys
import struct
import zlib
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from graph.geometry import pose_to_tum
from perception.frame import CameraModel, Detection
from sources.ros2.cdr import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DETECTIONS,
    IMAGE,
    MARKER_ARRAY,
    ODOMETRY,
    POSE_STAMPED,
    header,
    make,
    serialize,
    to_stamp,
)

_IMAGE_LAYOUT = {  # encoding: (dtype, channels)
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "mono8": (np.uint8, 1),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}
SPHERE, LINE_LIST, TEXT_VIEW_FACING = 2, 5, 9  # visualization_msgs/Marker types
ADD, DELETEALL = 0, 3  # and actions
IDENTITY = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # TUM row of the identity pose


def encode_image(stamp: float, frame_id: str, image: np.ndarray, encoding: str) -> bytes:
    """A sensor_msgs/Image of ``image`` in ``encoding``: rgb8 and bgr8 from an HxWx3 uint8 RGB image (bgr8
    reverses the channels on the wire, so ``decode_image`` gives the image back), mono8 from HxW uint8, 16UC1
    from HxW uint16 (millimetres), 32FC1 from HxW float32 (metres); little-endian, no row padding."""
    if encoding not in _IMAGE_LAYOUT:
        raise ValueError(f"encoding {encoding!r} not in {sorted(_IMAGE_LAYOUT)}")
    dtype, channels = _IMAGE_LAYOUT[encoding]
    image = np.asarray(image)
    shape = "HxWx3" if channels > 1 else "HxW"
    if image.dtype != dtype or image.shape[2:] != ((channels,) if channels > 1 else ()) or image.ndim < 2:
        raise ValueError(f"{encoding} needs an {shape} {np.dtype(dtype)} image, got {image.shape} {image.dtype}")
    if encoding == "bgr8":
        image = image[..., ::-1]
    height, width = image.shape[:2]
    data = np.ascontiguousarray(image, dtype=np.dtype(dtype).newbyteorder("<")).view(np.uint8).reshape(-1)
    msg = make(
        IMAGE,
        header=header(stamp, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels * np.dtype(dtype).itemsize,
        data=data,
    )
    return serialize(msg, IMAGE)


def encode_compressed_image(stamp: float, frame_id: str, rgb: np.ndarray, fmt: str = "jpeg") -> bytes:
    """A sensor_msgs/CompressedImage of an HxWx3 uint8 RGB image as ``jpeg`` (quality 95) or ``png``."""
    ext = {"jpeg": ".jpg", "png": ".png"}.get(fmt)
    if ext is None:
        raise ValueError(f"compressed format {fmt!r} is neither jpeg nor png")
    ok, buf = cv2.imencode(
        ext, cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95]
    )
    if not ok:
        raise ValueError(f"could not encode the image as {fmt}")
    msg = make(COMPRESSED_IMAGE, header=header(stamp, frame_id), format=fmt, data=np.asarray(buf, np.uint8).reshape(-1))
    return serialize(msg, COMPRESSED_IMAGE)


def encode_camera_info(stamp: float, frame_id: str, camera: CameraModel) -> bytes:
    """A sensor_msgs/CameraInfo of the colour camera: K, P = [K | 0], R = I, plumb_bob with zero distortion."""
    c = camera.color
    k = np.array([c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0])
    p = np.array([c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    msg = make(
        CAMERA_INFO,
        header=header(stamp, frame_id),
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=k,
        r=np.eye(3).reshape(-1),
        p=p,
    )
    return serialize(msg, CAMERA_INFO)


def _pose(T: np.ndarray) -> Any:
    return _pose_of_row(pose_to_tum(np.asarray(T, dtype=float)))


def _pose_of_row(row: np.ndarray) -> Any:
    """A geometry_msgs/Pose of a TUM row ``tx ty tz qx qy qz qw``."""
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in row)
    return make(
        "geometry_msgs/msg/Pose",
        position=make("geometry_msgs/msg/Point", x=tx, y=ty, z=tz),
        orientation=make("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
    )


def encode_odometry(stamp: float, frame_id: str, child_frame_id: str, pose: np.ndarray) -> bytes:
    """A nav_msgs/Odometry carrying a 4x4 pose (zero covariance and twist)."""
    msg = make(
        ODOMETRY,
        header=header(stamp, frame_id),
        child_frame_id=child_frame_id,
        pose=make("geometry_msgs/msg/PoseWithCovariance", pose=_pose(pose)),
    )
    return serialize(msg, ODOMETRY)


def encode_pose_stamped(stamp: float, frame_id: str, pose: np.ndarray) -> bytes:
    """A geometry_msgs/PoseStamped."""
    return serialize(_pose_stamped(stamp, frame_id, pose), POSE_STAMPED)


def _pose_stamped(stamp: float, frame_id: str, pose: np.ndarray) -> Any:
    return make(POSE_STAMPED, header=header(stamp, frame_id), pose=_pose(pose))


def encode_path(stamp: float, frame_id: str, poses: list[tuple[float, np.ndarray]]) -> bytes:
    """A nav_msgs/Path: one PoseStamped per (time, 4x4 pose), each stamped with its own time.

    Written field by field (the bytes ``serialize`` gives, with every rotation converted in one call): a
    path of a thousand keyframes takes a few milliseconds, not the tenth of a second of message objects."""
    rows = _tum_rows(np.array([T for _, T in poses], dtype=float).reshape(-1, 4, 4))
    name = frame_id.encode() + b"\x00"
    out = bytearray(b"\x00\x01\x00\x00")  # CDR little-endian; alignment counts from after these 4 bytes
    _cdr_header(out, stamp, name)
    out += bytes(-(len(out) - 4) % 4) + struct.pack("<I", len(poses))
    for (t, _), row in zip(poses, rows, strict=True):
        _cdr_header(out, t, name)
        out += bytes(-(len(out) - 4) % 8)  # the float64s of the Pose are 8-aligned
        out += struct.pack("<7d", *row)
    return bytes(out)


def _cdr_header(out: bytearray, stamp: float, name: bytes) -> None:
    """A std_msgs/Header (4-aligned stamp, then frame_id as a NUL-terminated string) appended to ``out``."""
    out += bytes(-(len(out) - 4) % 4)
    out += struct.pack("<iII", *to_stamp(stamp), len(name))
    out += name


def _tum_rows(T: np.ndarray) -> np.ndarray:
    """``pose_to_tum`` of K 4x4 poses at once, (K, 7)."""
    if not len(T):
        return np.zeros((0, 7))
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat().reshape(-1, 4)
    q[q[:, 3] < 0] *= -1
    return np.concatenate([T[:, :3, 3], q], axis=1)


def encode_detections(stamp: float, frame_id: str, detections: list[Detection]) -> bytes:
    """A vision_msgs/Detection2DArray: per detection one result (label as class_id, score) and its box."""
    items = []
    for det in detections:
        x1, y1, x2, y2 = det.box
        hypothesis = make("vision_msgs/msg/ObjectHypothesis", class_id=det.label, score=float(det.score))
        identity = make("geometry_msgs/msg/Pose", orientation=make("geometry_msgs/msg/Quaternion", w=1.0))
        result = make(
            "vision_msgs/msg/ObjectHypothesisWithPose",
            hypothesis=hypothesis,
            pose=make("geometry_msgs/msg/PoseWithCovariance", pose=identity),
        )
        center = make(
            "vision_msgs/msg/Pose2D", position=make("vision_msgs/msg/Point2D", x=(x1 + x2) / 2, y=(y1 + y2) / 2)
        )
        bbox = make("vision_msgs/msg/BoundingBox2D", center=center, size_x=x2 - x1, size_y=y2 - y1)
        items.append(make("vision_msgs/msg/Detection2D", header=header(stamp, frame_id), results=[result], bbox=bbox))
    return serialize(make(DETECTIONS, header=header(stamp, frame_id), detections=items), DETECTIONS)


def encode_marker_array(
    stamp: float, frame_id: str, objects: list[dict[str, Any]], loops: list[tuple[np.ndarray, np.ndarray]]
) -> bytes:
    """A visualization_msgs/MarkerArray of the map: a DELETEALL first (objects removed since disappear), per
    object (``objects.json`` fields) an ellipsoid (SPHERE, ns ``objects``) and its label (TEXT_VIEW_FACING, ns
    ``labels``: "label #id (n)"), and one LINE_LIST (ns ``loops``) with a segment per loop closure (two
    positions, or two 4x4 poses)."""
    hdr = header(stamp, frame_id)
    markers = [_marker(hdr, "", 0, SPHERE, action=DELETEALL)]
    shapes = [_ellipsoid(np.asarray(obj["axes"], dtype=float)) for obj in objects]
    means = np.array([obj["mean"] for obj in objects], dtype=float).reshape(-1, 3)
    poses = np.tile(np.eye(4), (len(objects), 1, 1))
    poses[:, :3, :3] = np.array([rotation for rotation, _ in shapes]).reshape(-1, 3, 3)
    poses[:, :3, 3] = means
    for obj, row, (_, radii) in zip(objects, _tum_rows(poses), shapes, strict=True):  # one rotation call for all
        r, g, b = _label_colour(str(obj["label"]))
        ellipsoid = _marker(hdr, "objects", int(obj["id"]), SPHERE, pose=row, scale=2 * radii, colour=(r, g, b, 0.5))
        above = np.array([*row[:2], row[2] + (float(radii.max()) + 0.1), 0.0, 0.0, 0.0, 1.0])  # the label's place
        text = f"{obj['label']} #{obj['id']} ({obj.get('n_observations', 0)})"
        label = _marker(hdr, "labels", int(obj["id"]), TEXT_VIEW_FACING, pose=above, scale=(0.0, 0.0, 0.12), text=text)
        markers += [ellipsoid, label]
    if loops:
        points = [_point(end) for loop in loops for end in loop]
        markers.append(
            _marker(hdr, "loops", 0, LINE_LIST, scale=(0.02, 0.0, 0.0), colour=(1.0, 0.2, 0.2, 1.0), points=points)
        )
    return serialize(make(MARKER_ARRAY, markers=markers), MARKER_ARRAY)


def _marker(
    hdr: Any,
    ns: str,
    marker_id: int,
    kind: int,
    action: int = ADD,
    pose: np.ndarray | None = None,  # a TUM row
    scale: Any = (1.0, 1.0, 1.0),
    colour: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0),
    text: str = "",
    points: list[Any] | None = None,
) -> Any:
    sx, sy, sz = (float(v) for v in scale)
    return make(
        "visualization_msgs/msg/Marker",
        header=hdr,
        ns=ns,
        id=marker_id,
        type=kind,
        action=action,
        pose=_pose_of_row(IDENTITY if pose is None else pose),
        scale=make("geometry_msgs/msg/Vector3", x=sx, y=sy, z=sz),
        color=make("std_msgs/msg/ColorRGBA", r=colour[0], g=colour[1], b=colour[2], a=colour[3]),
        text=text,
        points=points or [],
    )


def _ellipsoid(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (columns: the principal directions) and radii of an ellipsoid given as rows = direction x radius."""
    axes = np.nan_to_num(axes.reshape(3, 3))
    radii = np.linalg.norm(axes, axis=1)
    if radii.min() < 1e-9:  # a flat or empty cluster: no orientation to show
        return np.eye(3), np.maximum(radii, 0.005)
    u, _, vt = np.linalg.svd((axes / radii[:, None]).T)  # the rotation nearest to the normalised directions
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        rotation[:, 2] *= -1
    return rotation, radii


def _label_colour(label: str) -> tuple[float, float, float]:
    """A colour of its own for each label, the same in every run (crc32, not Python's salted hash)."""
    hue = (zlib.crc32(label.encode()) % 360) / 360.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return r, g, b


def _point(end: np.ndarray) -> Any:
    end = np.asarray(end, dtype=float)
    x, y, z = (float(v) for v in (end[:3, 3] if end.shape == (4, 4) else end[:3]))
    return make("geometry_msgs/msg/Point", x=x, y=y, z=z)
