"""The bounded ingest queue: zenoh callbacks inspect each message (no pixel decoded) and enqueue the valid
ones; the decoder thread decodes their images. Garbage is refused before it can displace a good frame."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

from perception.frame import Frame, FrameRejected, Reason
from service.budget import TokenBucket
from service.protocol import Inspected, Limits, decode_images, inspect_message
from service.stats import ServiceStats

log = logging.getLogger(__name__)


@dataclass
class Ingested:
    """An inspected message and the monotonic time it arrived."""

    message: Inspected
    received: float


class IngestQueue:
    """Thread-safe FIFO of at most ``capacity`` items; a full queue drops its oldest item.

    ``put`` never blocks, so it is safe on zenoh's callback thread.
    """

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._items: deque[Ingested] = deque()
        self._cond = threading.Condition()
        self.dropped = 0  # every frame dropped: the queue was full, the service stopped, or stale
        self.stale = 0  # ... of them: skipped for a newer frame (live ingest, ``get_newest``)

    def put(self, message: Inspected, received: float | None = None) -> bool:
        """Enqueue; returns True when the oldest item had to be dropped to make room."""
        with self._cond:
            dropped = len(self._items) >= self.capacity
            if dropped:
                self._items.popleft()
                self.dropped += 1
            self._items.append(Ingested(message, time.monotonic() if received is None else received))
            self._cond.notify_all()
            return dropped

    def get(self, timeout: float) -> Ingested | None:
        """The oldest item, waiting up to ``timeout`` seconds; None when nothing arrived."""
        with self._cond:
            if not self._items and not self._cond.wait_for(lambda: bool(self._items), timeout):
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def get_newest(self, timeout: float) -> Ingested | None:
        """The newest item, the older ones dropped as stale (live ingest: tracking works on the freshest frame,
        and a frame skipped here was never decoded); None when nothing arrived within ``timeout``."""
        with self._cond:
            if not self._items and not self._cond.wait_for(lambda: bool(self._items), timeout):
                return None
            item = self._items.pop()
            self.count_stale(len(self._items))
            self._items.clear()
            self._cond.notify_all()
            return item

    def count_stale(self, n: int) -> None:
        """Count ``n`` frames skipped for a newer one (dropped, reason stale)."""
        with self._cond:
            self.dropped += n
            self.stale += n

    def discard(self) -> int:
        """Drop every queued item and count it in ``dropped`` (shutdown); returns how many."""
        with self._cond:
            n = len(self._items)
            self._items.clear()
            self.dropped += n
            self._cond.notify_all()
            return n

    def count_dropped(self, n: int) -> int:
        """Count ``n`` items taken from the queue but dropped later (shutdown); returns ``n``."""
        with self._cond:
            self.dropped += n
            return n

    @property
    def depth(self) -> int:
        """Items waiting, read without the lock (a deque's length is read atomically): for status replies."""
        return len(self._items)

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class Gate:
    """What the subscriber callback does before queuing: inspect the message and spend the frame budget."""

    def __init__(self, limits: Limits, stats: ServiceStats):
        self.limits, self.stats = limits, stats
        self.budget = TokenBucket(limits.max_frame_rate_hz, limits.max_frame_rate_hz)

    def admit(self, payload: bytes) -> Inspected | None:
        """The inspected message, or None when it was rejected (counted by reason)."""
        message = inspect_counted(payload, self.limits, self.stats)
        if message is not None and not self.budget.take():
            self.stats.count_rejected(Reason.RATE_LIMITED.value)
            return None
        return message


def inspect_counted(payload: bytes, limits: Limits, stats: ServiceStats) -> Inspected | None:
    """The inspected message, or None when it was rejected (counted by reason) or inspection failed (counted)."""
    try:
        return inspect_message(payload, limits)
    except FrameRejected as exc:
        stats.count_rejected(exc.reason.value)
        log.debug("rejected frame: %s", exc)
    except Exception:  # the inspection must survive anything a message can trigger
        log.exception("unexpected error while inspecting a frame")
        stats.count_error("internal")
    return None


def decode_counted(message: Inspected, stats: ServiceStats) -> Frame | None:
    """The decoded frame, or None when its images were rejected (counted by reason) or decoding failed (counted)."""
    t0 = time.monotonic()
    try:
        frame = decode_images(message)
    except FrameRejected as exc:
        stats.count_rejected(exc.reason.value)
        log.debug("rejected frame: %s", exc)
        return None
    except Exception:  # the decoder must survive anything a message can trigger
        log.exception("unexpected error while decoding a frame")
        stats.count_error("internal")
        return None
    stats.time("decode", time.monotonic() - t0)
    return frame
