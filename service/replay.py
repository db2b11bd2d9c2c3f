"""Replaying a dataset as protocol-v1 messages on ``<prefix>/<robot>/rgbd``."""

from __future__ import annotations

import logging
import math
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
        if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"--rate must be a positive number of frames per second (got {rate_hz:g})")
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


def wait_for_subscriber(pub: zenoh.Publisher, timeout_s: float) -> bool:
    """Whether a subscriber matches ``pub`` within ``timeout_s`` (zenoh propagates interest asynchronously)."""
    deadline = time.monotonic() + timeout_s
    while not _matching(pub) and time.monotonic() < deadline:
        time.sleep(0.02)
    return _matching(pub)


def frame_publisher(
    session: zenoh.Session, key: str, wait_for_subscriber_s: float = 5.0, required: bool = False
) -> zenoh.Publisher:
    """A reliable, blocking publisher on ``key``; waits briefly for a subscriber so no frame is lost at start.

    ``required``: without a subscriber by then, ConnectionError instead of a warning. A replay into nothing
    would otherwise publish every frame into the void and exit 0 as if the service had them.
    """
    pub = session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
    )
    if wait_for_subscriber(pub, wait_for_subscriber_s):
        return pub
    if required:
        pub.undeclare()
        raise ConnectionError(
            f"no subscriber on {key} within {wait_for_subscriber_s:g} s: is `objslam serve` running for this robot "
            "and reachable? (zenoh.query_timeout_s sets the wait)"
        )
    log.warning("no subscriber on %s yet; publishing anyway", key)
    return pub
