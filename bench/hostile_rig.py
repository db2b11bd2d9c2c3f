"""The rig of ``objslam bench hostile``: a fresh service per attack, what is sampled, paced and flooded sending."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from bench.attacks import (
    CAMERA_HZ,
    DATASET,
    PREFIX,
    QUERY_FRAMES,
    QUERY_RATE_HZ,
    QUERY_TIMEOUT_S,
    ROBOT,
    STATUS_KEY,
)
from bench.overload import FrameLoop, _accounted, rss_mb
from bench.rig import client, free_port, query_status, router, start_serve, stop_serve, wait_for_status
from service.replay import frame_publisher

# ---------------------------------------------------------------- the rig and what is sampled


@dataclass
class Rig:
    """A serve subprocess, the robot's session (good frames, status) and the attacker's session."""

    proc: Any
    robot: zenoh.Session
    attacker: zenoh.Session
    frames: zenoh.Publisher
    crafted: zenoh.Publisher


@contextmanager
def service(env: dict[str, str] | None = None) -> Iterator[Rig]:
    """A fresh router, ``objslam serve`` and attacker session for one attack."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    session = router(port)
    proc, log = start_serve(endpoint, ROBOT, env)
    attacker = None
    try:
        wait_for_status(session, STATUS_KEY, proc, log)
        attacker = client(endpoint)
        key = f"{PREFIX}/rgbd"
        yield Rig(proc, session, attacker, frame_publisher(session, key), frame_publisher(attacker, key))
    finally:
        if attacker is not None:
            attacker.close()
        stop_serve(proc)
        session.close()
        log.unlink(missing_ok=True)


class Monitor:
    """The service's RSS at 20 Hz and, given a session, its frame counters from ``status`` at about 50 Hz."""

    def __init__(self, pid: int, session: zenoh.Session | None = None):
        self.pid, self.session = pid, session
        self.rss: list[tuple[float, float]] = []
        self.progress: list[tuple[float, int, int]] = []  # (time, processed, accounted)
        self.queue_depth_max = self.queue_capacity = 0
        self._stop = threading.Event()

    def __enter__(self) -> Monitor:
        self.before, self._hwm_start = rss_mb(self.pid)
        self._threads = [threading.Thread(target=self._sample_rss, daemon=True)]
        if self.session is not None:
            self._threads.append(threading.Thread(target=self._poll, daemon=True))
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=10)
        hwm = rss_mb(self.pid)[1]
        self.peak = max([self.before, *(r for _t, r in self.rss), *([hwm] if hwm > self._hwm_start else [])])

    def _sample_rss(self) -> None:
        while not self._stop.wait(0.05):
            self.rss.append((time.monotonic(), rss_mb(self.pid)[0]))

    def _poll(self) -> None:
        assert self.session is not None
        while not self._stop.wait(0.015):
            status = query_status(self.session, STATUS_KEY, timeout=1.0)
            if status is not None:
                self.progress.append((time.monotonic(), status["frames_processed"], _accounted(status)))
                self.queue_depth_max = max(self.queue_depth_max, status["queue_depth"])
                self.queue_capacity = status["queue_capacity"]

    def rise_after(self, t: float, window_s: float = 1.0) -> float:
        """RSS rise (MB) within ``window_s`` after ``t`` over the last sample before it."""
        before = [r for s, r in self.rss if s < t] or [self.before]
        during = [r for s, r in self.rss if t <= s <= t + window_s] or before[-1:]
        return max(during) - before[-1]

    def done_at(self, accounted: int) -> float | None:
        """When ``status`` first showed ``accounted`` messages processed, rejected, dropped or failed."""
        return next((t for t, _, a in self.progress if a >= accounted), None)

    def max_gap(self, since: float) -> float:
        """Longest time (s) between two consecutive increases of frames_processed after ``since``."""
        times = [t for (t, p, _), (_, q, _) in zip(self.progress[1:], self.progress, strict=False) if p > q]
        times = [t for t in times if t >= since]
        return max(np.diff(times), default=0.0)


@dataclass
class Played:
    """What an attack published, and for each crafted frame when it went out and the messages sent through the
    good frame after it (its recovery ends when the service has accounted for that many)."""

    good: int = 0
    crafted: int = 0
    marks: list[tuple[float, int]] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class Outcome:
    attack: str
    played: Played
    before: dict
    after: dict
    rss_before: float
    rss_peak: float
    rss_rises: list[float]
    recoveries: list[float | None]
    max_gap_s: float
    queue: tuple[int, int]
    load: float

    def delta(self, name: str) -> int:
        return self.after[name] - self.before[name]

    def rejected(self) -> dict[str, int]:
        a, b = self.after["frames_rejected"], self.before["frames_rejected"]
        return {k: a[k] - b.get(k, 0) for k in sorted(a) if a[k] > b.get(k, 0)}


def _settle(rig: Rig, received: int, timeout: float = 180.0, idle_s: float = 5.0) -> dict:
    """Status once ``received`` messages arrived and every arrived one was processed, rejected, dropped or failed;
    or once everything that arrived was done and nothing changed for ``idle_s`` (a message the transport refused,
    as zenoh does beyond ``transport/link/rx/max_message_size``, never arrives)."""
    deadline = time.monotonic() + timeout
    last, since = None, time.monotonic()
    while True:
        status = query_status(rig.robot, STATUS_KEY)
        if status is not None:
            counts = (status["frames_received"], _accounted(status))
            if counts[0] >= received and counts[1] >= received:
                return status
            if counts != last:
                last, since = counts, time.monotonic()
            elif counts[1] >= counts[0] and time.monotonic() - since >= idle_s:
                return status
        if time.monotonic() > deadline or rig.proc.poll() is not None:
            seen = "no status" if status is None else f"{status['frames_received']} received, {_accounted(status)} done"
            raise RuntimeError(f"the service did not account for {received} messages ({seen}; exit {rig.proc.poll()})")
        time.sleep(0.05)


def _paced(
    rig: Rig,
    loop: FrameLoop,
    count: int,
    played: Played,
    inject: Callable[[int], bytes | None] = lambda i: None,
    good: Callable[[int], bytes] | None = None,
) -> None:
    """``count`` good frames at 30 frames/s (the loop's next, or ``good(i)``); ``inject(i)`` may return a crafted
    frame sent just before good frame i."""
    start = time.monotonic()
    for i in range(count):
        if (delay := start + i / CAMERA_HZ - time.monotonic()) > 0:
            time.sleep(delay)
        crafted = inject(i)
        if crafted is not None:
            sent = time.monotonic()
            rig.crafted.put(crafted)
            played.crafted += 1
            played.marks.append((sent, played.good + played.crafted + 1))
        rig.frames.put(loop.next() if good is None else good(i))
        played.good += 1


@contextmanager
def _flood(publisher: zenoh.Publisher, messages: list[bytes], rate_hz: float, played: Played) -> Iterator[None]:
    """Publish ``messages`` round robin at ``rate_hz`` on a thread while the body runs."""
    stop = threading.Event()

    def run() -> None:
        start, sent = time.monotonic(), 0
        while not stop.is_set():
            if (delay := start + sent / rate_hz - time.monotonic()) > 0:
                time.sleep(delay)
            publisher.put(messages[sent % len(messages)])
            sent += 1
        played.crafted += sent
        played.extra["flood_rate_hz"] = sent / (time.monotonic() - start)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


# ---------------------------------------------------------------- queries


class Queries:
    """Queries sent at ``rate_hz`` round robin over ``keys`` (non-blocking gets, replies on zenoh's threads)."""

    def __init__(self, session: zenoh.Session, keys: list[str], rate_hz: float, timeout_s: float = QUERY_TIMEOUT_S):
        self.session, self.keys, self.rate_hz, self.timeout_s = session, keys, rate_hz, timeout_s
        self.latency_ms: list[float] = []
        self.outcomes: dict[str, int] = {"answered": 0, "busy": 0, "error": 0, "timeout": 0}
        self.sent, self._pending, self.seconds = 0, 0, 0.0
        self._lock, self._stop = threading.Condition(), threading.Event()

    def __enter__(self) -> Queries:
        self._thread = threading.Thread(target=self._send, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()
        with self._lock:
            self._lock.wait_for(lambda: self._pending == 0, self.timeout_s + 5)

    def _send(self) -> None:
        start = time.monotonic()
        while not self._stop.is_set():
            if (delay := start + self.sent / self.rate_hz - time.monotonic()) > 0:
                time.sleep(delay)
            with self._lock:
                self._pending += 1
            on_reply, on_done = self._handlers(time.perf_counter())
            key = self.keys[self.sent % len(self.keys)]
            self.session.get(key, handler=zenoh.handlers.Callback(on_reply, on_done), timeout=self.timeout_s)
            self.sent += 1
        self.seconds = time.monotonic() - start

    def _handlers(self, t0: float) -> tuple[Callable[[zenoh.Reply], None], Callable[[], None]]:
        first: list[str] = []

        def on_reply(reply: zenoh.Reply) -> None:
            if first:
                return
            if reply.ok is not None:
                first.append("answered")
                with self._lock:
                    self.latency_ms.append((time.perf_counter() - t0) * 1e3)
                return
            text = reply.err.payload.to_bytes().decode(errors="replace") if reply.err is not None else ""
            first.append("timeout" if text == "Timeout" else "busy" if "busy" in text else "error")

        def on_done() -> None:
            with self._lock:
                self.outcomes[first[0] if first else "timeout"] += 1
                self._pending -= 1
                self._lock.notify_all()

        return on_reply, on_done

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latency_ms, q)) if self.latency_ms else float("nan")


def _reply_size(session: zenoh.Session, key: str) -> int:
    for reply in session.get(key, timeout=5.0):
        if reply.ok is not None:
            return len(reply.ok.payload.to_bytes())
    return 0


def max_rate(flood: bool) -> dict[str, Any]:
    """QUERY_FRAMES frames published at once to a fresh service (queue holds them all), optionally under a flood
    of queries on status, trajectory and objects from the attacker's session."""
    loop = FrameLoop(DATASET)
    payloads = [loop.next() for _ in range(QUERY_FRAMES)]
    with service({"OBJSLAM_INGEST__QUEUE_SIZE": str(QUERY_FRAMES + 1)}) as rig:
        keys = [f"{PREFIX}/{name}" for name in ("status", "trajectory", "objects")]
        with Monitor(rig.proc.pid) as monitor:
            queries = Queries(rig.attacker, keys, QUERY_RATE_HZ)
            with queries if flood else nullcontext():
                start = time.monotonic()
                for p in payloads:
                    rig.frames.put(p)
                status = _settle(rig, QUERY_FRAMES)
                elapsed = time.monotonic() - start
    return {
        "status": status,
        "fps": status["frames_processed"] / elapsed,
        "queries": queries if flood else None,
        "rss_growth": monitor.peak - monitor.before,
        "ingest_p99_ms": status["latency"]["ingest_to_graph"]["p99_ms"],
    }
