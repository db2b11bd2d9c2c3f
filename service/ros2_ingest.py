"""ROS 2 camera topics carried by rmw_zenoh, into the service: no bridge, no ROS installation.

A ROS 2 robot on rmw_zenoh publishes each message as CDR on ``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<RIHS01
hash>``. The subscriber callbacks only queue the raw bytes (bounded, oldest dropped and counted); the
``objslam-ros2`` thread decodes them (``sources.ros2.messages``), pairs colour and depth by header stamp
(``sources.ros2.pairing``) and hands each pair to the node as a protocol-v1 message (raw ``rgb8`` / ``u16le``),
so a ROS 2 frame passes exactly the validation, rejection reasons and counters of any other frame. Any type hash
is accepted; one that differs from ROS 2 Jazzy's is logged once.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from perception.frame import Frame, FrameRejected, Reason
from service.protocol import encode_frame
from service.ros2_settings import Ros2Settings
from sources.ros2 import keys, messages
from sources.ros2.pairing import FramePairer

log = logging.getLogger(__name__)

REASONS = frozenset(r.value for r in Reason)
IDLE_FLUSH_S = 0.1
"""No message for this long: the pairs held for late odometry or detections become frames."""


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
        # with odometry or detections on their own topics a pair waits for the next frame's images (or an idle
        # moment) before it becomes a frame: those messages may arrive after the images they belong to
        hold = settings.sync_tolerance_s if settings.odom_topic or settings.detections_topic else 0.0
        self.pairer = FramePairer(settings.sync_tolerance_s, max_pixels, hold)
        self.counts: Counter[str] = Counter()
        self._queue: deque[Incoming] = deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._warned: set[str] = set()
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
        """Queue a raw message (never blocks; a full queue drops its oldest message, counted)."""
        with self._cond:
            if len(self._queue) >= self.settings.queue_messages:
                self._queue.popleft()
                self.counts["dropped_messages"] += 1
            self._queue.append(item)
            self._cond.notify()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                idle = not self._queue and not self._cond.wait_for(lambda: bool(self._queue), IDLE_FLUSH_S)
                item = None if idle else self._queue.popleft()
            if item is None:  # nothing arrived for a while: the pairs still held become frames
                self._submit_all(self.pairer.flush())
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

    def _submit_all(self, frames: list[Frame]) -> None:
        for frame in frames:
            self.submit(encode_frame(frame, "rgb8", "u16le"))

    def _typename(self, key: str) -> str:
        try:
            parsed = keys.parse_ros_key(key)
        except ValueError:
            raise FrameRejected(Reason.BAD_FIELD, f"{key} is not an rmw_zenoh topic key") from None
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

    def _feed(self, kind: str, typename: str, raw: bytes) -> list[Frame]:
        p = self.pairer
        if kind == "color":
            if typename == messages.COMPRESSED_IMAGE:
                return p.color(messages.decode_compressed_image(raw, self.max_pixels))
            _expect(typename, messages.IMAGE)
            return p.color(messages.decode_image(raw, self.max_pixels))
        if kind == "depth":
            _expect(typename, messages.IMAGE)
            return p.depth(messages.decode_image(raw, self.max_pixels))
        if kind == "camera_info":
            _expect(typename, messages.CAMERA_INFO)
            p.camera_info(messages.decode_camera_info(raw))
        elif kind == "odom":
            _expect(typename, messages.ODOMETRY)
            p.odometry(messages.decode_odometry(raw))
        elif kind == "detections":
            _expect(typename, messages.DETECTIONS)
            camera = p.camera
            width, height = (camera.width, camera.height) if camera is not None else (1 << 16, 1 << 16)
            p.detections(messages.decode_detections(raw, width, height))
        return []

    def status(self) -> dict[str, Any]:
        """The ``ros2`` object of ``status``: messages by kind, pairing counters, drops."""
        return {"topics": self.topics(), **dict(self.counts), **self.pairer.counters()}


def _expect(typename: str, expected: str) -> None:
    if typename != expected:
        raise FrameRejected(Reason.BAD_FIELD, f"message type {typename}, expected {expected}")
