"""RGB-D frames, camera models and detections: the data every stage of the pipeline consumes."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from perception.camera import Intrinsics  # also the name snapshots of 0.1.0 give it: perception.frame.Intrinsics


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Colour camera intrinsics and image size, depth units, and (optionally) an unregistered depth sensor.

    ``depth_scale`` is raw depth units per metre (TUM: 5000, 7-Scenes: 1000).
    ``depth_intrinsics`` is None when depth is registered to colour; otherwise the depth camera's
    intrinsics, and ``depth_to_color`` the 4x4 transform from the depth to the colour camera frame.
    """

    color: Intrinsics
    width: int
    height: int
    depth_scale: float = 5000.0
    depth_intrinsics: Intrinsics | None = None
    depth_to_color: np.ndarray | None = None

    def _key(self) -> tuple:
        return self.color, self.width, self.height, self.depth_scale, self.depth_intrinsics

    def __eq__(self, other: object) -> bool:
        """Field by field, the depth-to-colour transform by value (the generated ``__eq__`` compared it as a
        tuple element and raised on an unregistered camera's 4 x 4 array)."""
        if not isinstance(other, CameraModel):
            return NotImplemented
        a, b = self.depth_to_color, other.depth_to_color
        same = a is b or (a is not None and b is not None and np.array_equal(a, b))
        return same and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    @property
    def registered(self) -> bool:
        return self.depth_intrinsics is None

    @property
    def depth(self) -> Intrinsics:
        """Intrinsics of the depth image (the colour ones when registered)."""
        return self.depth_intrinsics if self.depth_intrinsics is not None else self.color


@dataclass(frozen=True)
class Detection:
    """One detected object: COCO label, confidence and box [x1, y1, x2, y2] in colour pixels."""

    label: str
    score: float
    box: tuple[float, float, float, float]


@dataclass
class Frame:
    """One RGB-D frame as the service receives it.

    ``rgb`` is HxWx3 uint8 in RGB order; ``depth`` is uint16 in raw units (0 = invalid);
    ``odometry`` is an optional 4x4 camera-to-world pose from an external odometry source;
    ``detections`` is None when the frame carries none (the detector then runs), else a list.
    """

    timestamp: float
    seq: int
    frame_id: str
    camera: CameraModel
    rgb: np.ndarray
    depth: np.ndarray
    odometry: np.ndarray | None = None
    detections: list[Detection] | None = None
    index: int = -1
    _depth_m: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    def depth_m(self) -> np.ndarray:
        """Depth in metres as float32, NaN where invalid (0 or 65535).

        Computed once per frame (odometry, loop closure, objects and map points all read it) and read-only.
        """
        if self._depth_m is None:
            d = self.depth.astype(np.float32) / np.float32(self.camera.depth_scale)
            d[(self.depth == 0) | (self.depth == 65535)] = np.nan
            d.flags.writeable = False
            self._depth_m = d
        return self._depth_m


class Reason(str, Enum):  # noqa: UP042 - str() of a member stays "Reason.X" as in 0.1.0 (StrEnum gives the value)
    """Why a frame was rejected; the values are the keys of ``frames_rejected`` in status."""

    TRUNCATED = "truncated"
    BAD_MAGIC = "bad_magic"
    UNSUPPORTED_VERSION = "unsupported_version"
    BAD_HEADER = "bad_header"
    BAD_FIELD = "bad_field"
    BAD_INTRINSICS = "bad_intrinsics"
    BAD_POSE = "bad_pose"
    SIZE_MISMATCH = "size_mismatch"
    BAD_IMAGE = "bad_image"
    BAD_DETECTIONS = "bad_detections"
    TOO_LARGE = "too_large"
    RATE_LIMITED = "rate_limited"
    DUPLICATE_TIMESTAMP = "duplicate_timestamp"
    OUT_OF_ORDER = "out_of_order"
    TIME_JUMP = "time_jump"
    EMPTY_DEPTH = "empty_depth"
    NO_ODOMETRY = "no_odometry"
    ODOMETRY_JUMP = "odometry_jump"


class FrameRejected(Exception):
    """A message that is not a valid frame; ``reason`` is counted, ``detail`` is logged."""

    def __init__(self, reason: Reason, detail: str):
        super().__init__(f"{reason.value}: {detail}")
        self.reason = reason
        self.detail = detail
