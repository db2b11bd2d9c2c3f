"""Counters and latency percentiles for the status reply."""

from __future__ import annotations

import threading
from collections import Counter, deque

import numpy as np


def summarize(seconds: np.ndarray) -> dict[str, float | int]:
    """Count and p50 / p95 / p99 / max in milliseconds of durations given in seconds."""
    if not len(seconds):
        return {"n": 0}
    arr = seconds * 1e3
    p50, p95, p99 = np.percentile(arr, [50, 95, 99])
    return {
        "n": len(arr),
        "p50_ms": round(float(p50), 3),
        "p95_ms": round(float(p95), 3),
        "p99_ms": round(float(p99), 3),
        "max_ms": round(float(arr.max()), 3),
    }


class LatencyWindow:
    """The last ``size`` durations of one stage, in seconds; percentiles reported in milliseconds."""

    def __init__(self, size: int = 2000):
        self._values: deque[float] = deque(maxlen=size)

    def add(self, seconds: float) -> None:
        self._values.append(seconds)

    def values(self) -> np.ndarray:
        """A copy of the durations (taken under the owner's lock; percentiles are computed outside it)."""
        return np.fromiter(self._values, dtype=float, count=len(self._values))

    def summary(self) -> dict[str, float | int]:
        return summarize(self.values())


class ServiceStats:
    """Thread-safe frame counters (received, processed, rejected by reason) and stage latencies."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.received = 0
        self.processed = 0
        self.rejected: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()
        self.stages: dict[str, LatencyWindow] = {}

    def count_received(self) -> None:
        with self._lock:
            self.received += 1

    def count_processed(self) -> None:
        with self._lock:
            self.processed += 1

    def count_rejected(self, reason: str) -> None:
        with self._lock:
            self.rejected[reason] += 1

    def count_error(self, kind: str) -> None:
        with self._lock:
            self.errors[kind] += 1

    def completed(self) -> int:
        """Frames processed, rejected or failed (dropped frames are the ingest queue's count)."""
        with self._lock:
            return self.processed + sum(self.rejected.values()) + sum(self.errors.values())

    def counters(self) -> dict:
        """The frame counters as plain data (kept in snapshots; latencies are not)."""
        with self._lock:
            return {
                "received": self.received,
                "processed": self.processed,
                "rejected": dict(self.rejected),
                "errors": dict(self.errors),
            }

    def restore_counters(self, counters: dict) -> None:
        with self._lock:
            self.received, self.processed = counters["received"], counters["processed"]
            self.rejected, self.errors = Counter(counters["rejected"]), Counter(counters["errors"])

    def time(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.stages.setdefault(stage, LatencyWindow()).add(seconds)

    def snapshot(self) -> dict:
        """Counters and latency percentiles; the lock is held only to copy, not for the percentiles."""
        with self._lock:
            snap = {
                "frames_received": self.received,
                "frames_processed": self.processed,
                "frames_rejected": dict(self.rejected),
                "frames_rejected_total": sum(self.rejected.values()),
                "errors": dict(self.errors),
            }
            durations = {name: w.values() for name, w in self.stages.items()}
        snap["latency"] = {name: summarize(values) for name, values in durations.items()}
        return snap
