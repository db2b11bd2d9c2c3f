"""rosbag2 recordings (MCAP or sqlite3) as objslam datasets, and datasets written as rosbag2 recordings.

A ``RosbagDataset`` reads the bag once on opening: camera info, odometry and detections are decoded, colour
and depth only checked (their headers), and ``FramePairer`` pairs them. It keeps, per frame, where its two
images lie in the bag (topic, log time, rank among that time's messages), and reads and decodes them again
when the frame is asked for, so memory holds no image.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from perception.frame import Frame, FrameRejected
from sources.base import Dataset, DatasetError
from sources.ros2.cdr import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DETECTIONS,
    IMAGE,
    ODOMETRY,
    Stamped,
    stamp_ns,
    typestore,
)
from sources.ros2.decoders import (
    decode_camera_info,
    decode_compressed_image,
    decode_detections,
    decode_image,
    decode_odometry,
    peek_compressed_image,
    peek_image,
)
from sources.ros2.encoders import (
    encode_camera_info,
    encode_compressed_image,
    encode_detections,
    encode_image,
    encode_odometry,
)
from sources.ros2.pairing import DEPTH_ENCODINGS, FramePairer, Pair, RosTopics

log = logging.getLogger(__name__)

BAG_HOLD_S = 1.0
"""A recording is paired with this hold: odometry and detections logged up to a second after their images
(a detector's latency) still join their frame."""
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def expected_types(topics: RosTopics) -> dict[str, str]:
    """The message type each of the topics must carry."""
    types = {
        topics.rgb: COMPRESSED_IMAGE if topics.compressed else IMAGE,
        topics.depth: IMAGE,
        topics.camera_info: CAMERA_INFO,
    }
    if topics.odom:
        types[topics.odom] = ODOMETRY
    if topics.detections:
        types[topics.detections] = DETECTIONS
    return types


def _open(path: Path) -> Reader:
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # FileNotFoundError, ReaderError, YAML and storage errors
        raise DatasetError(f"cannot open rosbag2 recording {path}: {exc}") from None
    return reader


def read_messages(path: Path, topics: RosTopics) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type name, log time ns, CDR bytes) of the messages on ``topics``, in log-time order."""
    reader = _open(Path(path))
    try:
        wanted = [c for c in reader.connections if c.topic in topics.names()]
        if not wanted:
            return
        for connection, log_time, raw in reader.messages(connections=wanted):
            yield connection.topic, connection.msgtype, log_time, bytes(raw)
    except DatasetError:
        raise
    except Exception as exc:
        raise DatasetError(f"cannot read rosbag2 recording {path}: {exc}") from None
    finally:
        reader.close()


@dataclass(frozen=True)
class ImageRef:
    """Where an image message lies in a bag (its topic, log time and rank among that topic's messages of that
    time) and the image's (height, width), which is all pairing needs."""

    topic: str
    log_time: int
    rank: int
    shape: tuple[int, int]


class RosbagDataset(Dataset):
    """The frames of a rosbag2 recording: colour and depth paired by stamp (``FramePairer``), with CameraInfo,
    and odometry and detections when their topics are given. No ground truth."""

    def __init__(self, path: Path, topics: RosTopics, max_pixels: int = 2048 * 1536, sync_tolerance_s: float = 0.02):
        self.path = Path(path)
        self.topics = topics
        self.max_pixels = max_pixels
        self.name = self.path.name
        self._check_topics()
        self._pairs, self._counters = self._pair(sync_tolerance_s)
        if not self._pairs:
            raise DatasetError(f"{self.path}: no colour and depth images pair into frames ({self._counters})")
        self.camera = self._pairs[0].camera
        self._times = np.array([p.timestamp for p in self._pairs])

    def __len__(self) -> int:
        return len(self._pairs)

    def counters(self) -> dict[str, int]:
        """The bag's messages that made no frame (``FramePairer.counters``)."""
        return dict(self._counters)

    @property
    def timestamps(self) -> np.ndarray:
        return self._times.copy()

    def frame(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        pair = self._pairs[index]
        reader = _open(self.path)
        try:
            rgb, depth = self._load(reader, pair.color), self._load(reader, pair.depth)
        except FrameRejected as exc:
            raise DatasetError(f"{self.path}: frame {index}: {exc}") from None
        except DatasetError:
            raise
        except Exception as exc:  # the storage's own errors on a damaged file
            raise DatasetError(f"{self.path}: cannot read frame {index}: {exc}") from None
        finally:
            reader.close()
        frame = pair.frame(rgb.value, depth.value)
        frame.index = index
        return frame

    def _check_topics(self) -> None:
        if len(set(self.topics.names())) != len(self.topics.names()):
            raise DatasetError(f"the topics {self.topics.names()} must all differ")
        reader = _open(self.path)
        try:
            found = {name: info.msgtype for name, info in reader.topics.items()}
        finally:
            reader.close()
        for topic, typename in expected_types(self.topics).items():
            if topic not in found:
                raise DatasetError(f"{self.path} has no topic {topic}; it has {', '.join(sorted(found)) or 'none'}")
            if found[topic] != typename:
                raise DatasetError(f"{self.path}: topic {topic} carries {found[topic]}, not {typename}")

    def _pair(self, sync_tolerance_s: float) -> tuple[list[Pair], dict[str, int]]:
        """Pairs of the whole bag; their images are ``ImageRef``s."""
        pairer = FramePairer(sync_tolerance_s, self.max_pixels, hold_s=BAG_HOLD_S)
        ranks: Counter[tuple[str, int]] = Counter()
        pairs: list[Pair] = []
        for topic, _, log_time, raw in read_messages(self.path, self.topics):
            try:
                if topic == self.topics.camera_info:
                    pairer.camera_info(decode_camera_info(raw))
                elif topic == self.topics.odom:
                    pairer.odometry(decode_odometry(raw))
                elif topic == self.topics.detections:
                    if pairer.camera is not None:  # boxes are clipped to the camera's image
                        pairer.detections(decode_detections(raw, pairer.camera.width, pairer.camera.height))
                elif topic in (self.topics.rgb, self.topics.depth):
                    rank = ranks[topic, log_time]
                    ranks[topic, log_time] += 1
                    add = pairer.add_color if topic == self.topics.rgb else pairer.add_depth
                    pairs += add(self._peek(topic, log_time, rank, raw))
            except FrameRejected as exc:
                log.debug("%s: %s at %d ns rejected: %s", self.path, topic, log_time, exc)
                pairer.count_rejected(exc.reason)
        pairs += pairer.flush_pairs()
        return pairs, pairer.counters()

    def _compressed(self, topic: str) -> bool:
        return topic == self.topics.rgb and self.topics.compressed

    def _peek(self, topic: str, log_time: int, rank: int, raw: bytes) -> Stamped[ImageRef]:
        peek = peek_compressed_image if self._compressed(topic) else peek_image
        found = peek(raw, self.max_pixels)
        return Stamped(found.stamp, found.frame_id, ImageRef(topic, log_time, rank, found.value), found.encoding)

    def _load(self, reader: Reader, msg: Stamped[Any]) -> Stamped[np.ndarray]:
        """The decoded image of a pair's ``ImageRef``, read again from the bag."""
        ref: ImageRef = msg.value
        connections = [c for c in reader.connections if c.topic == ref.topic]
        found = reader.messages(connections=connections, start=ref.log_time, stop=ref.log_time + 1)
        raw = next((bytes(data) for i, (_, _, data) in enumerate(found) if i == ref.rank), None)
        if raw is None:
            raise DatasetError(f"{self.path}: the {ref.topic} message at {ref.log_time} ns is gone")
        decode = decode_compressed_image if self._compressed(ref.topic) else decode_image
        return decode(raw, self.max_pixels)


def write_rosbag(
    dataset: Dataset,
    path: Path,
    topics: RosTopics,
    storage: str = "mcap",
    depth_encoding: str = "16UC1",
    frames: int | None = None,
    color_format: str = "jpeg",
    frame_id: str = "camera_color_optical_frame",
    odom_frame_id: str = "odom",
) -> Path:
    """Write ``dataset``'s first ``frames`` frames (all by default) as a new rosbag2 recording at ``path``, as a
    ROS 2 RGB-D camera would record them: per frame, logged at its stamp, CameraInfo, Odometry (when the frame
    carries odometry and ``topics.odom`` is set; ``frame_id`` the camera's child of ``odom_frame_id``),
    Detection2DArray (likewise), the colour Image rgb8 (CompressedImage as ``color_format`` when
    ``topics.compressed``) and the depth Image (16UC1 millimetres or 32FC1 metres)."""
    if storage not in STORAGES:
        raise ValueError(f"storage {storage!r} not in {sorted(STORAGES)}")
    if depth_encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"depth encoding {depth_encoding!r} not in {DEPTH_ENCODINGS}")
    if not dataset.camera.registered:
        raise DatasetError(f"{dataset.name}: depth is not registered to colour; ROS topics here carry registered depth")
    count = len(dataset) if frames is None else min(frames, len(dataset))
    path = Path(path)
    try:
        writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=STORAGES[storage])
        writer.open()
    except Exception as exc:
        raise DatasetError(f"cannot create rosbag2 recording {path}: {exc}") from None
    try:
        store = typestore()
        connections = {
            t: writer.add_connection(t, typename, typestore=store) for t, typename in expected_types(topics).items()
        }
        for i in range(count):
            frame = dataset.frame(i)
            for topic, raw in _frame_messages(frame, topics, depth_encoding, color_format, frame_id, odom_frame_id):
                writer.write(connections[topic], stamp_ns(frame.timestamp), raw)
    except BaseException:
        writer.abort()
        raise
    writer.close()
    return path


def _frame_messages(
    frame: Frame, topics: RosTopics, depth_encoding: str, color_format: str, frame_id: str, odom_frame_id: str
) -> list[tuple[str, bytes]]:
    t = frame.timestamp
    out = [(topics.camera_info, encode_camera_info(t, frame_id, frame.camera))]
    if topics.odom and frame.odometry is not None:
        out.append((topics.odom, encode_odometry(t, odom_frame_id, frame_id, frame.odometry)))
    if topics.detections and frame.detections is not None:
        out.append((topics.detections, encode_detections(t, frame_id, frame.detections)))
    if topics.compressed:
        out.append((topics.rgb, encode_compressed_image(t, frame_id, frame.rgb, color_format)))
    else:
        out.append((topics.rgb, encode_image(t, frame_id, frame.rgb, "rgb8")))
    out.append((topics.depth, encode_image(t, frame_id, _ros_depth(frame, depth_encoding), depth_encoding)))
    return out


def _ros_depth(frame: Frame, encoding: str) -> np.ndarray:
    """Depth as ROS carries it: 16UC1 millimetres (0 invalid) or 32FC1 metres (NaN invalid)."""
    invalid = (frame.depth == 0) | (frame.depth == 65535)
    metres = frame.depth.astype(np.float64) / frame.camera.depth_scale
    if encoding == "32FC1":
        return np.where(invalid, np.nan, metres).astype(np.float32)
    if frame.camera.depth_scale == 1000.0:
        return np.where(invalid, 0, frame.depth).astype(np.uint16)
    return np.where(invalid, 0, np.clip(np.rint(metres * 1000.0), 0, 65534)).astype(np.uint16)
