"""ROS 2 camera topics carried by rmw_zenoh, into the service: no bridge, no ROS installation.

A ROS 2 robot on rmw_zenoh publishes each message as CDR on ``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<RIHS01
hash>``. The subscriber callbacks only queue the raw bytes (bounded, oldest dropped and counted); the
``objslam-ros2`` thread checks them (``sources.ros2.messages``; images are kept as they came, not converted),
pairs colour and depth by header stamp (``sources.ros2.pairing``) and hands each pair to the node as a
protocol-v1 message (raw ``rgb8`` / ``u16le``, the pixels copied once from the CDR bytes), so a ROS 2 frame
passes exactly the validation, rejection reasons and counters of any other frame. Any type hash is accepted;
one that differs from ROS 2 Jazzy's is logged once.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from perception.frame import Frame, FrameRejected, Reason
from service.protocol import frame_head
from service.ros2_settings import Ros2Settings
from sources.ros2 import keys, messages
from sources.ros2.pairing import FramePairer, Pair

log = logging.getLogger(__name__)

REASONS = frozenset(r.value for r in Reason)
IDLE_FLUSH_S = 0.1
"""No message for this long: the pairs held for late odometry or detections become frames."""
MAX_KEYS = 64
"""Keys whose message type is remembered (a robot has a handful; more, and the memory starts again)."""
SIDE_HOLD_S = 1.0
"""With odometry or detections on their own topics a pair waits until those topics reach its stamp, at most
until images this much newer (stream time) have come."""


@dataclass(frozen=True)
class Incoming:
    """A raw ROS 2 message as it arrived."""

    kind: str  # "color", "depth", "camera_info", "odom", "detections"
    key: str
    payload: bytes


class Ros2Ingest:
    """Subscribes to the configured topics and feeds paired frames to ``submit`` (the node's, protocol v1)."""

    def __init__(
        self,
        settings: Ros2Settings,
        max_pixels: int,
        submit: Callable[[bytes], None],
        reject: Callable[[str], None],
    ):
        self.settings, self.max_pixels = settings, max_pixels
        self.submit, self.reject = submit, reject
        # with odometry or detections on their own topics a pair waits for them (or an idle moment) before it
        # becomes a frame: those messages may arrive after the images they belong to
        waits_for = [kind for kind in ("odom", "detections") if kind in self.topics()]
        hold = SIDE_HOLD_S if waits_for else 0.0
        self.pairer = FramePairer(settings.sync_tolerance_s, max_pixels, hold, waits_for)
        self.counts: Counter[str] = Counter()
        self._queue: deque[Incoming] = deque()
        self._queued_bytes = 0
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._warned: set[str] = set()
        self._typenames: dict[str, str] = {}  # rmw_zenoh key: message type
        self._camera_info: bytes | None = None  # the last CameraInfo taken, after its stamp: not decoded again
        self._pair_rejections: Counter[str] = Counter()
        self._subscribers: list[Any] = []
        self._thread = threading.Thread(target=self._run, name="objslam-ros2", daemon=True)

    def topics(self) -> dict[str, str]:
        s = self.settings
        named = {"color": s.rgb_topic, "depth": s.depth_topic, "camera_info": s.camera_info_topic}
        if s.odom_topic:
            named["odom"] = s.odom_topic
        if s.detections_topic:
            named["detections"] = s.detections_topic
        return named

    def start(self, session: zenoh.Session) -> None:
        """Declare one subscriber per topic (any type, any hash) and start the decoding thread."""
        for kind, topic in self.topics().items():
            key = f"{self.settings.domain_id}/{topic.strip('/')}/*/*"  # any type name and hash: checked per message
            self._subscribers.append(session.declare_subscriber(key, self._callback(kind)))
            log.info("ROS 2: %s from %s (%s)", kind, topic, key)
        self._thread.start()

    def stop(self) -> None:
        for sub in self._subscribers:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        self._subscribers.clear()
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def _callback(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            self.put(Incoming(kind, str(sample.key_expr), sample.payload.to_bytes()))

        return on_sample

    def put(self, item: Incoming) -> None:
        """Queue a raw message (never blocks; beyond ``queue_messages`` messages or ``queue_bytes`` bytes the
        oldest are dropped, counted)."""
        s = self.settings
        with self._cond:
            self._queue.append(item)
            self._queued_bytes += len(item.payload)
            while len(self._queue) > s.queue_messages or self._queued_bytes > s.queue_bytes:
                self._queued_bytes -= len(self._queue.popleft().payload)
                self.counts["dropped_messages"] += 1
            self._cond.notify()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                idle = not self._queue and not self._cond.wait_for(lambda: bool(self._queue), IDLE_FLUSH_S)
                item = None if idle else self._queue.popleft()
                self._queued_bytes -= 0 if item is None else len(item.payload)
            if item is None:  # nothing arrived for a while: the pairs still held become frames
                self._submit_all(self.pairer.flush_pairs())
                continue
            try:
                self.handle(item)
            except Exception:  # the thread must survive anything a message can trigger
                log.exception("unexpected error on a ROS 2 message from %s", item.key)
                self.counts["errors"] += 1

    def handle(self, item: Incoming) -> None:
        """Decode one message and feed the pairer; each pair goes to ``submit``; a bad message to ``reject``."""
        self.counts[f"{item.kind}_messages"] += 1
        try:
            typename = self._typename(item.key)
            frames = self._feed(item.kind, typename, item.payload)
        except FrameRejected as exc:
            log.debug("ROS 2 %s rejected: %s", item.kind, exc)
            self.reject(exc.reason.value)
            return
        self._submit_all(frames)
        self._count_pair_rejections()

    def _count_pair_rejections(self) -> None:
        """Pairs the pairer refused (e.g. ``size_mismatch`` against the CameraInfo) count as rejected frames."""
        counts = self.pairer.counters()
        for reason in REASONS & counts.keys():
            for _ in range(counts[reason] - self._pair_rejections[reason]):
                self.reject(reason)
            self._pair_rejections[reason] = counts[reason]

    def _submit_all(self, pairs: list[Pair]) -> None:
        for pair in pairs:
            try:
                rgb = messages.pixels(pair.color.value, self.max_pixels, copy=False)
                depth = messages.pixels(pair.depth.value, self.max_pixels, copy=False)
            except FrameRejected as exc:  # a compressed image that does not decode
                log.debug("ROS 2 pair at %.6f rejected: %s", pair.timestamp, exc)
                self.reject(exc.reason.value)
                continue
            self.submit(frame_message(pair.frame(rgb, depth)))

    def _typename(self, key: str) -> str:
        """The message type of an rmw_zenoh key (keys seen before: from a small cache)."""
        if (typename := self._typenames.get(key)) is not None:
            return typename
        try:
            parsed = keys.parse_ros_key(key)
        except ValueError:
            raise FrameRejected(Reason.BAD_FIELD, f"{key} is not an rmw_zenoh topic key") from None
        if len(self._typenames) >= MAX_KEYS:
            self._typenames.clear()
        self._typenames[key] = parsed.typename
        known = keys.JAZZY_TYPE_HASHES.get(parsed.typename)
        if known is not None and parsed.type_hash != known and parsed.typename not in self._warned:
            self._warned.add(parsed.typename)
            log.warning(
                "ROS 2 %s arrives with type hash %s, not ROS 2 Jazzy's %s: decoding it as Jazzy's",
                parsed.typename,
                parsed.type_hash,
                known,
            )
        return parsed.typename

    def _feed(self, kind: str, typename: str, raw: bytes) -> list[Pair]:
        """The pairs a message releases; images are checked and kept as they came (converted when released)."""
        p = self.pairer
        if kind == "color":
            if typename == messages.COMPRESSED_IMAGE:
                return p.add_color(messages.peek_raw_compressed_image(raw, self.max_pixels))
            _expect(typename, messages.IMAGE)
            return p.add_color(messages.peek_raw_image(raw, self.max_pixels))
        if kind == "depth":
            _expect(typename, messages.IMAGE)
            return p.add_depth(messages.peek_raw_image(raw, self.max_pixels))
        if kind == "camera_info":
            _expect(typename, messages.CAMERA_INFO)
            if raw[12:] != self._camera_info:  # but for its stamp, the last one taken: nothing new
                info = messages.decode_camera_info(raw)
                p.camera_info(info)
                self._camera_info = raw[12:] if p.camera is info.value else None
        elif kind == "odom":
            _expect(typename, messages.ODOMETRY)
            p.odometry(messages.decode_odometry(raw))
        elif kind == "detections":
            _expect(typename, messages.DETECTIONS)
            camera = p.camera
            width, height = (camera.width, camera.height) if camera is not None else (1 << 16, 1 << 16)
            p.detections(messages.decode_detections(raw, width, height))
        return p.ready_pairs()

    def status(self) -> dict[str, Any]:
        """The ``ros2`` object of ``status``: messages by kind, pairing counters, drops."""
        return {"topics": self.topics(), **dict(self.counts), **self.pairer.counters()}


def frame_message(frame: Frame) -> bytes:
    """``protocol.encode_frame(frame, "rgb8", "u16le")`` with each image copied once, straight into the message
    (the images may be views of the CDR bytes they came in)."""
    rgb, depth = frame.rgb, frame.depth
    head = frame_head(frame, ("rgb8", rgb.size), ("u16le", 2 * depth.size))
    images = (np.ascontiguousarray(rgb, dtype=np.uint8).data, np.ascontiguousarray(depth, dtype="<u2").data)
    return b"".join((head, *images))


def _expect(typename: str, expected: str) -> None:
    if typename != expected:
        raise FrameRejected(Reason.BAD_FIELD, f"message type {typename}, expected {expected}")
