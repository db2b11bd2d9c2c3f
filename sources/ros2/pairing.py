"""Pairing ROS 2 colour and depth images into objslam frames by their header stamps (pure: no I/O, no threads).

A ROS camera publishes colour, depth and camera info on separate topics; odometry and detections come on
their own. ``FramePairer`` takes the decoded messages in arrival order and gives frames in timestamp order:

1. a colour or depth message pairs with the unpaired message of the other kind nearest in stamp, within
   ``sync_tolerance_s``, as long as the frame would come after the last one; each message pairs once;
2. a pair takes the latest CameraInfo (none yet: dropped, ``no_camera_info``) and must match its size
   (else dropped, ``size_mismatch``);
3. after ``hold_s`` (stamp time, 0 by default) the pair becomes a frame with the odometry nearest in stamp and
   the detections of the same stamp, each within the tolerance (else None);
4. unpaired messages older than the newest pair by more than the tolerance, beyond ``MAX_UNPAIRED`` or
   ``MAX_UNPAIRED_AGE_S`` are dropped and counted (``unpaired_color``, ``unpaired_depth``).
"""

from __future__ import annotations

import bisect
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from perception.frame import CameraModel, Detection, Frame, Reason
from sources.ros2.cdr import Stamped

MAX_UNPAIRED = 30
"""Unpaired messages of each kind kept waiting for a partner (a second of a 30 Hz camera)."""
MAX_UNPAIRED_AGE_S = 3.0
"""An unpaired message this much older than the newest image is given up."""
MAX_SIDE_MESSAGES = 1000
SIDE_MESSAGES_AGE_S = 5.0
"""Odometry and detections kept to join later frames: the newest ones, up to this many and this old."""
DEPTH_ENCODINGS = ("16UC1", "32FC1")


@dataclass(frozen=True)
class RosTopics:
    """The topics of one RGB-D camera; ``compressed``: the colour topic carries sensor_msgs/CompressedImage."""

    rgb: str
    depth: str
    camera_info: str
    odom: str | None = None
    detections: str | None = None
    compressed: bool = False

    def names(self) -> list[str]:
        """Every topic given, colour first."""
        return [t for t in (self.rgb, self.depth, self.camera_info, self.odom, self.detections) if t]


@dataclass(frozen=True)
class Pair:
    """A colour and a depth message paired, with what makes them a frame; their values are images (HxWx3 uint8
    RGB, HxW uint16) or, before decoding, anything with the image's ``shape``."""

    seq: int
    color: Stamped[Any]
    depth: Stamped[Any]
    camera: CameraModel
    odometry: np.ndarray | None = None
    detections: list[Detection] | None = None

    @property
    def timestamp(self) -> float:
        return self.color.stamp

    def frame(self, rgb: np.ndarray | None = None, depth: np.ndarray | None = None) -> Frame:
        """The frame of this pair, with its own images or the decoded ``rgb`` and ``depth`` given."""
        return Frame(
            timestamp=self.color.stamp,
            seq=self.seq,
            frame_id=self.color.frame_id,
            camera=self.camera,
            rgb=self.color.value if rgb is None else rgb,
            depth=self.depth.value if depth is None else depth,
            odometry=None if self.odometry is None else self.odometry.copy(),
            detections=None if self.detections is None else list(self.detections),
        )


def _size(image: Any) -> tuple[int, int]:
    """(width, height) of an image array or of anything with its ``shape``."""
    shape = image.shape
    return int(shape[1]), int(shape[0])


class FramePairer:
    """Colour, depth, camera info, odometry and detections messages in; frames in timestamp order out."""

    def __init__(self, sync_tolerance_s: float = 0.02, max_pixels: int = 2048 * 1536, hold_s: float = 0.0):
        if not sync_tolerance_s >= 0 or not hold_s >= 0:
            raise ValueError("sync_tolerance_s and hold_s must be non-negative")
        self.tolerance = float(sync_tolerance_s)
        self.max_pixels = int(max_pixels)
        self.hold_s = float(hold_s)
        self._unpaired: dict[str, list[Stamped[Any]]] = {"color": [], "depth": []}
        self._odometry: list[Stamped[np.ndarray]] = []
        self._detections: list[Stamped[list[Detection]]] = []
        self._held: list[tuple[Stamped[Any], Stamped[Any], CameraModel]] = []
        self._camera: CameraModel | None = None
        self._last_pair = -np.inf
        self._newest = -np.inf
        self._seq = 0
        self._counts: Counter[str] = Counter({"unpaired_color": 0, "unpaired_depth": 0, "no_camera_info": 0})

    @property
    def camera(self) -> CameraModel | None:
        """The latest CameraInfo's camera (decode detections against its size), None before the first."""
        return self._camera

    def counters(self) -> dict[str, int]:
        """Messages dropped: ``unpaired_color``, ``unpaired_depth``, ``no_camera_info``, and by reason value."""
        return dict(self._counts)

    def count_rejected(self, reason: Reason) -> None:
        """Count a message a decoder rejected, under its reason, with the pairer's own drops."""
        self._counts[reason.value] += 1

    def camera_info(self, msg: Stamped[CameraModel]) -> None:
        camera = msg.value
        if camera.width * camera.height > self.max_pixels:
            self.count_rejected(Reason.TOO_LARGE)
            return
        self._camera = camera

    def odometry(self, msg: Stamped[np.ndarray]) -> None:
        self._keep(self._odometry, msg)

    def detections(self, msg: Stamped[list[Detection]]) -> None:
        self._keep(self._detections, msg)

    def color(self, msg: Stamped[Any]) -> list[Frame]:
        return [pair.frame() for pair in self.add_color(msg)]

    def depth(self, msg: Stamped[Any]) -> list[Frame]:
        return [pair.frame() for pair in self.add_depth(msg)]

    def flush(self) -> list[Frame]:
        """The frames still held (``hold_s``), at the end of a stream."""
        return [pair.frame() for pair in self.flush_pairs()]

    def add_color(self, msg: Stamped[Any]) -> list[Pair]:
        """``color`` before the frames are made: the pairs released, in timestamp order."""
        if msg.encoding in DEPTH_ENCODINGS:
            self.count_rejected(Reason.BAD_FIELD)
            return []
        return self._add("color", msg)

    def add_depth(self, msg: Stamped[Any]) -> list[Pair]:
        """``depth`` before the frames are made: the pairs released, in timestamp order."""
        if msg.encoding and msg.encoding not in DEPTH_ENCODINGS:
            self.count_rejected(Reason.BAD_FIELD)
            return []
        return self._add("depth", msg)

    def flush_pairs(self) -> list[Pair]:
        held, self._held = self._held, []
        return [self._release(*pair) for pair in held]

    # ------------------------------------------------------------ steps

    def _add(self, kind: str, msg: Stamped[Any]) -> list[Pair]:
        other_kind = "depth" if kind == "color" else "color"
        self._newest = max(self._newest, msg.stamp)
        if msg.stamp < self._last_pair - self.tolerance:
            self._counts[f"unpaired_{kind}"] += 1
        elif (match := self._partner(kind, msg)) is None:
            bisect.insort(self._unpaired[kind], msg, key=lambda m: m.stamp)
        else:
            partner = self._unpaired[other_kind].pop(match)
            color, depth = (msg, partner) if kind == "color" else (partner, msg)
            self._pair(color, depth)
        self._evict()
        return self._released()

    def _partner(self, kind: str, msg: Stamped[Any]) -> int | None:
        """Index of the unpaired message of the other kind nearest to ``msg`` that can pair with it."""
        best, best_dt = None, np.inf
        for i, other in enumerate(self._unpaired["depth" if kind == "color" else "color"]):
            dt = abs(other.stamp - msg.stamp)
            color_stamp = msg.stamp if kind == "color" else other.stamp
            if dt <= self.tolerance and dt < best_dt and color_stamp > self._last_pair:
                best, best_dt = i, dt
        return best

    def _pair(self, color: Stamped[Any], depth: Stamped[Any]) -> None:
        self._last_pair = color.stamp
        camera = self._camera
        if camera is None:
            self._counts["no_camera_info"] += 1
        elif _size(color.value) != (camera.width, camera.height) or _size(depth.value) != _size(color.value):
            self.count_rejected(Reason.SIZE_MISMATCH)
        else:
            self._held.append((color, depth, camera))

    def _evict(self) -> None:
        for kind, waiting in self._unpaired.items():
            while waiting and (
                waiting[0].stamp < self._last_pair - self.tolerance
                or waiting[0].stamp < self._newest - MAX_UNPAIRED_AGE_S
                or len(waiting) > MAX_UNPAIRED
            ):
                waiting.pop(0)
                self._counts[f"unpaired_{kind}"] += 1

    def _released(self) -> list[Pair]:
        out = []
        while self._held and self._held[0][0].stamp + self.hold_s <= self._newest:
            out.append(self._release(*self._held.pop(0)))
        return out

    def _release(self, color: Stamped[Any], depth: Stamped[Any], camera: CameraModel) -> Pair:
        odometry = self._nearest(self._odometry, color.stamp)
        detections = self._nearest(self._detections, color.stamp)
        self._seq += 1
        return Pair(
            seq=self._seq - 1,
            color=color,
            depth=depth,
            camera=camera,
            odometry=None if odometry is None else odometry.value,
            detections=None if detections is None else detections.value,
        )

    def _keep(self, messages: list[Any], msg: Stamped[Any]) -> None:
        bisect.insort(messages, msg, key=lambda m: m.stamp)
        newest = messages[-1].stamp
        while len(messages) > MAX_SIDE_MESSAGES or messages[0].stamp < newest - SIDE_MESSAGES_AGE_S:
            messages.pop(0)

    def _nearest(self, messages: list[Any], stamp: float) -> Any:
        i = bisect.bisect_left(messages, stamp, key=lambda m: m.stamp)
        candidates = [m for m in messages[max(i - 1, 0) : i + 1] if abs(m.stamp - stamp) <= self.tolerance]
        return min(candidates, key=lambda m: abs(m.stamp - stamp), default=None)
