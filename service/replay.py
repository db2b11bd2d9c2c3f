"""Replaying a dataset as protocol-v1 messages on ``<prefix>/<robot>/rgbd``."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh
from tqdm import tqdm

from service.protocol import encode_frame
from sources.base import Dataset

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayResult:
    frames: int
    seconds: float

    @property
    def rate_hz(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")


class Replayer:
    """Publishes dataset frames paced by their timestamps (default), a fixed rate, or as fast as possible."""

    def __init__(
        self,
        dataset: Dataset,
        publish: Callable[[bytes], None],
        rate_hz: float | None = None,
        max_rate: bool = False,
        max_frames: int | None = None,
        before_publish: Callable[[], None] | None = None,
        progress: bool = True,
    ):
        if rate_hz is not None and rate_hz <= 0:
            raise ValueError("--rate must be positive")
        self.dataset = dataset
        self.publish = publish
        self.rate_hz = rate_hz
        self.max_rate = max_rate
        self.count = len(dataset) if max_frames is None else min(max_frames, len(dataset))
        self.before_publish = before_publish
        self.progress = progress

    def run(self) -> ReplayResult:
        """Publish every frame; returns how many and how long it took."""
        start = time.monotonic()
        t0 = None
        bar = tqdm(
            total=self.count,
            desc=f"replay {self.dataset.name}",
            unit="frame",
            disable=None if self.progress else True,
            mininterval=1.0,
        )
        for i in range(self.count):
            frame = self.dataset.frame(i)
            payload = encode_frame(frame)
            t0 = frame.timestamp if t0 is None else t0
            self._pace(start, i, frame.timestamp - t0)
            if self.before_publish is not None:
                self.before_publish()
            self.publish(payload)
            bar.update()
        bar.close()
        return ReplayResult(self.count, time.monotonic() - start)

    def _pace(self, start: float, index: int, offset_s: float) -> None:
        if self.max_rate:
            return
        due = start + (index / self.rate_hz if self.rate_hz else offset_s)
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def _matching(pub: zenoh.Publisher) -> bool:
    """Whether a subscriber matches: zenoh 1.10 returns a MatchingStatus where its stub says bool."""
    status: object = pub.matching_status
    return bool(getattr(status, "matching", status))


def frame_publisher(session: zenoh.Session, key: str, wait_for_subscriber_s: float = 5.0) -> zenoh.Publisher:
    """A reliable, blocking publisher on ``key``; waits briefly for a subscriber so no frame is lost at start."""
    pub = session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
    )
    deadline = time.monotonic() + wait_for_subscriber_s
    while not _matching(pub) and time.monotonic() < deadline:
        time.sleep(0.02)
    if not _matching(pub):
        log.warning("no subscriber on %s yet; publishing anyway", key)
    return pub
