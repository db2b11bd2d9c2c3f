"""Pairing ROS 2 colour and depth images into objslam frames by their header stamps (pure: no I/O, no threads).

A ROS camera publishes colour, depth and camera info on separate topics; odometry and detections come on
their own. Each topic arrives in order, but the topics interleave as they will (rmw_zenoh delivers each
subscription on its own): in a flood a frame's colour may come dozens of messages before its depth.
``FramePairer`` takes the messages in arrival order and gives frames in timestamp order:

1. a colour or depth message pairs with the unpaired message of the other kind nearest in stamp, within
   ``sync_tolerance_s``, as long as the frame would come after the last one released; each message pairs once;
2. a pair takes the latest CameraInfo (none yet: dropped, ``no_camera_info``) and must match its size
   (else dropped, ``size_mismatch``);
3. pairs are released in stamp order, each once no older colour still waits for its depth (the depth topic
   has not passed it yet) and once the side topics it ``waits_for`` (``odom``, ``detections``) have reached
   its stamp (or fell silent), or the images are ``hold_s`` newer (without ``waits_for``: always ``hold_s``,
   0 by default; released before the side topics reached it: counted, ``released_before_side``);
   it takes the odometry nearest in stamp and the detections of the same stamp, each within the tolerance;
4. unpaired messages that can no longer make a frame (older than the last frame, or passed by the other topic
   beyond the tolerance: their partner was lost), or older than the newest image by ``MAX_UNPAIRED_AGE_S``,
   are dropped and counted (``unpaired_color``, ``unpaired_depth``); so are the oldest when the images held
   (unpaired and paired) exceed ``max_bytes`` (pairs held then are released first, waiting or not).
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from perception.frame import CameraModel, Detection, Frame, Reason
from sources.ros2.cdr import Stamped

MAX_UNPAIRED_AGE_S = 10.0
"""An unpaired message this much older (stream time) than the newest image is given up (its partner's topic
may lag that far behind in a flood: the bound that matters is ``MAX_UNPAIRED_BYTES``)."""
MAX_UNPAIRED_BYTES = 256 * 2**20
"""Image bytes held waiting (unpaired messages and pairs not released yet): about 170 VGA RGB-D frames."""
MAX_UNPAIRED = 1000
"""Unpaired messages of each kind at most (for values that do not tell their size, such as a bag's references)."""
MAX_SIDE_MESSAGES = 1000
SIDE_MESSAGES_AGE_S = 10.0
"""Odometry and detections kept to join later frames: the newest ones, up to this many and this old."""
DEPTH_ENCODINGS = ("16UC1", "32FC1")
SIDE_KINDS = ("odom", "detections")


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


def _nbytes(msg: Stamped[Any]) -> int:
    """Bytes an image message holds: its value's ``nbytes`` (an array, a raw message), else 0."""
    return int(getattr(msg.value, "nbytes", 0))


class FramePairer:
    """Colour, depth, camera info, odometry and detections messages in; frames in timestamp order out."""

    def __init__(
        self,
        sync_tolerance_s: float = 0.02,
        max_pixels: int = 2048 * 1536,
        hold_s: float = 0.0,
        waits_for: Iterable[str] = (),
        max_bytes: int = MAX_UNPAIRED_BYTES,
    ):
        if not sync_tolerance_s >= 0 or not hold_s >= 0:
            raise ValueError("sync_tolerance_s and hold_s must be non-negative")
        self.tolerance = float(sync_tolerance_s)
        self.max_pixels = int(max_pixels)
        self.hold_s = float(hold_s)
        self.waits_for = tuple(waits_for)
        if not set(self.waits_for) <= set(SIDE_KINDS):
            raise ValueError(f"waits_for: {self.waits_for} not among {SIDE_KINDS}")
        self.max_bytes = int(max_bytes)
        self._unpaired: dict[str, list[Stamped[Any]]] = {"color": [], "depth": []}
        self._odometry: list[Stamped[np.ndarray]] = []
        self._detections: list[Stamped[list[Detection]]] = []
        self._held: list[tuple[Stamped[Any], Stamped[Any], CameraModel]] = []  # by colour stamp
        self._bytes = 0  # of the images unpaired and held
        self._camera: CameraModel | None = None
        self._newest: dict[str, float] = {}  # the newest stamp of each kind of message
        self._first_image = np.inf
        self._last_frame = -np.inf  # the stamp of the last pair released
        self._seq = 0
        self._counts: Counter[str] = Counter({"unpaired_color": 0, "unpaired_depth": 0, "no_camera_info": 0})

    @property
    def camera(self) -> CameraModel | None:
        """The latest CameraInfo's camera (decode detections against its size), None before the first."""
        return self._camera

    @property
    def held_bytes(self) -> int:
        """Image bytes waiting: unpaired messages and pairs not released yet."""
        return self._bytes

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
        self._keep("odom", self._odometry, msg)

    def detections(self, msg: Stamped[list[Detection]]) -> None:
        self._keep("detections", self._detections, msg)

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

    def ready_pairs(self) -> list[Pair]:
        """The pairs that may go now (after odometry or detections came, which return nothing themselves)."""
        return self._released()

    def flush_pairs(self) -> list[Pair]:
        """Every pair held, waiting or not (the end of a stream, or a pause in it)."""
        out = []
        while self._held:
            out.append(self._release_first())
        return out

    # ------------------------------------------------------------ steps

    def _add(self, kind: str, msg: Stamped[Any]) -> list[Pair]:
        other_kind = "depth" if kind == "color" else "color"
        self._newest[kind] = max(self._newest.get(kind, -np.inf), msg.stamp)
        self._first_image = min(self._first_image, msg.stamp)
        if not self._can_pair(kind, msg.stamp):
            self._counts[f"unpaired_{kind}"] += 1
        elif (match := self._partner(kind, msg)) is None:
            bisect.insort(self._unpaired[kind], msg, key=lambda m: m.stamp)
            self._bytes += _nbytes(msg)
        else:
            partner = self._unpaired[other_kind].pop(match)
            self._bytes -= _nbytes(partner)
            color, depth = (msg, partner) if kind == "color" else (partner, msg)
            self._pair(color, depth)
        return self._released()

    def _can_pair(self, kind: str, stamp: float) -> bool:
        """A message of this stamp can still make a frame after the last one released."""
        return stamp > self._last_frame if kind == "color" else stamp >= self._last_frame - self.tolerance

    def _partner(self, kind: str, msg: Stamped[Any]) -> int | None:
        """Index of the unpaired message of the other kind nearest to ``msg`` that can pair with it."""
        waiting = self._unpaired["depth" if kind == "color" else "color"]
        stamps = [m.stamp for m in waiting]
        lo = bisect.bisect_left(stamps, msg.stamp - self.tolerance)
        hi = bisect.bisect_right(stamps, msg.stamp + self.tolerance)
        best, best_dt = None, np.inf
        for i in range(lo, hi):
            dt = abs(stamps[i] - msg.stamp)
            color_stamp = msg.stamp if kind == "color" else stamps[i]
            if dt < best_dt and color_stamp > self._last_frame:
                best, best_dt = i, dt
        return best

    def _pair(self, color: Stamped[Any], depth: Stamped[Any]) -> None:
        camera = self._camera
        if camera is None:
            self._counts["no_camera_info"] += 1
        elif _size(color.value) != (camera.width, camera.height) or _size(depth.value) != _size(color.value):
            self.count_rejected(Reason.SIZE_MISMATCH)
        else:
            bisect.insort(self._held, (color, depth, camera), key=lambda held: held[0].stamp)
            return
        self._bytes -= _nbytes(color) + _nbytes(depth)

    def _released(self) -> list[Pair]:
        """The pairs ready (or pushed out by ``max_bytes``), in stamp order; what can no longer pair is dropped."""
        out = []
        self._evict()
        while self._held and (self._bytes > self.max_bytes or self._ready(self._held[0][0].stamp)):
            if any(self._newest.get(k, -np.inf) < self._held[0][0].stamp for k in self.waits_for):
                self._counts["released_before_side"] += 1
            out.append(self._release_first())
            self._evict()
        while self._bytes > self.max_bytes and (self._unpaired["color"] or self._unpaired["depth"]):
            oldest = min((k for k in self._unpaired if self._unpaired[k]), key=lambda k: self._unpaired[k][0].stamp)
            self._drop(oldest)
        return out

    def _ready(self, stamp: float) -> bool:
        """The pair of this stamp may go: no older colour still waits for its depth, and the images are ``hold_s``
        newer or every side topic it waits for has reached it (or fallen silent)."""
        if self._waiting_older(stamp):
            return False
        images = max(self._newest.get("color", -np.inf), self._newest.get("depth", -np.inf))
        if images >= stamp + self.hold_s:
            return True
        return bool(self.waits_for) and all(self._side_reached(k, stamp, images) for k in self.waits_for)

    def _side_reached(self, kind: str, stamp: float, images: float) -> bool:
        """Side topic ``kind`` has reached ``stamp``, or is silent: nothing (since the first image) within
        ``hold_s`` of the newest image, so that a topic given but not published costs no frame a wait."""
        if kind not in self._newest:
            return images - self._first_image > self.hold_s
        newest = self._newest[kind]
        return newest >= stamp or images - newest > self.hold_s

    def _waiting_older(self, stamp: float) -> bool:
        """An older colour still waits for its depth (which the depth topic has not passed yet). (A depth waiting
        has a colour newer than it coming, if any: the colour topic has passed ``stamp``.)"""
        waiting = self._unpaired["color"]
        return bool(waiting) and waiting[0].stamp < stamp

    def _release_first(self) -> Pair:
        color, depth, camera = self._held.pop(0)
        self._bytes -= _nbytes(color) + _nbytes(depth)
        self._last_frame = max(self._last_frame, color.stamp)
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

    def _evict(self) -> None:
        """Drop (and count) unpaired messages that can no longer pair: older than the last frame, passed by the
        other topic (each topic arrives in order: their partner is lost), too old, or beyond the bounds."""
        images = max(self._newest.get("color", -np.inf), self._newest.get("depth", -np.inf))
        for kind, other in (("color", "depth"), ("depth", "color")):
            waiting, passed = self._unpaired[kind], self._newest.get(other, -np.inf) - self.tolerance
            while waiting and (
                not self._can_pair(kind, waiting[0].stamp)
                or waiting[0].stamp < passed
                or waiting[0].stamp < images - MAX_UNPAIRED_AGE_S
                or len(waiting) > MAX_UNPAIRED
            ):
                self._drop(kind)

    def _drop(self, kind: str) -> None:
        self._bytes -= _nbytes(self._unpaired[kind].pop(0))
        self._counts[f"unpaired_{kind}"] += 1

    def _keep(self, kind: str, messages: list[Any], msg: Stamped[Any]) -> None:
        self._newest[kind] = max(self._newest.get(kind, -np.inf), msg.stamp)
        bisect.insort(messages, msg, key=lambda m: m.stamp)
        newest = messages[-1].stamp
        while len(messages) > MAX_SIDE_MESSAGES or messages[0].stamp < newest - SIDE_MESSAGES_AGE_S:
            messages.pop(0)

    def _nearest(self, messages: list[Any], stamp: float) -> Any:
        i = bisect.bisect_left(messages, stamp, key=lambda m: m.stamp)
        candidates = [m for m in messages[max(i - 1, 0) : i + 1] if abs(m.stamp - stamp) <= self.tolerance]
        return min(candidates, key=lambda m: abs(m.stamp - stamp), default=None)
