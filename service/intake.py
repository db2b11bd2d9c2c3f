"""How frames go from the ingest queue to the worker: every frame in order, or (``ingest.live``) the freshest.

In order (the default: replays of recordings, benchmarks), the decoder takes the oldest queued frame and waits
for room in the worker's hand-over queue, so every frame that fits the ingest queue is processed. Live (a
robot's camera), tracking works on the freshest frame: the decoder takes the newest queued frame and skips the
older ones undecoded, a decoded frame the worker has not taken yet is replaced by a newer one, and the worker
skips a frame older than ``ingest.max_age_ms`` when a newer one is already queued. Each skipped frame is counted
in ``frames_dropped`` with the reason ``stale``; the map never sees it, so keyframes are decided only among
the frames tracked.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from perception.frame import Frame
from service.config import IngestSettings
from service.ingest import Ingested, IngestQueue


class Intake:
    """The decoder's and the worker's side of the hand-over between them."""

    def __init__(
        self,
        settings: IngestSettings,
        ingest: IngestQueue,
        stop: threading.Event,
        completed: Callable[[], None] = lambda: None,
    ):
        self.live, self.max_age_s = settings.live, settings.max_age_ms / 1000.0
        self.ingest, self.stop = ingest, stop
        self.completed = completed  # called when frames were dropped (they are completed: ``ServiceNode.completed``)
        self.decoded: queue.Queue[tuple[Frame, float]] = queue.Queue(maxsize=1 if self.live else 2)
        self._skipped = False  # the worker skipped the last frame as too old

    def take(self, timeout: float) -> Ingested | None:
        """Decoder: the next message to decode (live: the newest; the older ones are dropped as stale)."""
        if not self.live:
            return self.ingest.get(timeout)
        stale = self.ingest.stale
        item = self.ingest.get_newest(timeout)
        if self.ingest.stale != stale:
            self.completed()
        return item

    def hand_over(self, frame: Frame, received: float) -> None:
        """Decoder: give a decoded frame to the worker; in order it waits for room (a frame that finds the
        service stopping is counted as dropped), live it replaces a frame the worker has not taken."""
        while True:
            if self.live:
                try:
                    self.decoded.get_nowait()
                    self.ingest.count_stale(1)
                    self.completed()
                except queue.Empty:
                    pass
            try:
                self.decoded.put((frame, received), timeout=0.1)
                return
            except queue.Full:
                if self.stop.is_set():
                    self.ingest.count_dropped(1)
                    return

    def next(self, timeout: float) -> tuple[Frame, float] | None:
        """Worker: the next decoded frame and its arrival time; None when none came or (live) it was too old
        while a newer one is queued (then counted as stale; not two frames running, so a machine on which
        decoding alone takes longer than ``max_age_ms`` still tracks every other frame)."""
        try:
            frame, received = self.decoded.get(timeout=timeout)
        except queue.Empty:
            return None
        too_old = self.live and time.monotonic() - received > self.max_age_s
        if too_old and self.ingest.depth > 0 and not self._skipped:  # never twice running: decoding takes time too
            self.ingest.count_stale(1)
            self.completed()
            self._skipped = True
            return None
        self._skipped = False
        return frame, received

    def discard(self) -> int:
        """Shutdown: every frame still queued or decoded is counted as dropped; returns how many."""
        decoded = 0
        while True:
            try:
                self.decoded.get_nowait()
            except queue.Empty:
                break
            decoded += 1
        return self.ingest.discard() + self.ingest.count_dropped(decoded)

    def dropped_by_reason(self) -> dict[str, int]:
        """``frames_dropped`` split: ``stale`` (skipped for a newer frame, live) and ``queue`` (the ingest queue
        was full, or the service stopped with frames queued)."""
        return {"queue": self.ingest.dropped - self.ingest.stale, "stale": self.ingest.stale}


class MappingLag:
    """Seconds from a keyframe's arrival to its mapping (objects, loop closures) applied to the map."""

    RECENT = 256  # frames whose arrival is remembered (live, a keyframe is added a few frames after its own)

    def __init__(self) -> None:
        self._arrivals: dict[int, float] = {}  # keyframes whose mapping is not applied yet -> arrival
        self._recent: OrderedDict[float, float] = OrderedDict()  # frame timestamp -> arrival

    def frame(self, timestamp: float, received: float, added: tuple[tuple[int, float], ...]) -> None:
        """A frame processed, arrived at ``received``, and the keyframes its step added (index, timestamp)."""
        self._recent[timestamp] = received
        while len(self._recent) > self.RECENT:
            self._recent.popitem(last=False)
        for kf, stamp in added:
            self._arrivals[kf] = self._recent.get(stamp, received)

    def applied(self, mapped: int, now: float) -> list[float]:
        """The lags of the keyframes newly among the first ``mapped`` (whose mapping is applied)."""
        done = [kf for kf in self._arrivals if kf < mapped]
        return [now - self._arrivals.pop(kf) for kf in done]
