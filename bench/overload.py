"""Overload and memory: ``objslam serve`` fed faster than it processes, or for a long paced run (SPEC 7, 8).

Overload (``--seconds``): after measuring the service's processing rate, publish a synthetic scene at
``factor`` times that rate. The bounded ingest queue must drop what it cannot hold and count it, memory must
stay bounded, and ``status`` queried from another zenoh session must keep answering (p99 < 100 ms).
Memory (``--frames``): publish N frames paced so that none is dropped and report the RSS growth.

Frames are rendered and encoded once and replayed forwards and backwards (the motion stays continuous),
re-stamped with increasing timestamps; the service's RSS is read from ``/proc/<pid>/status``.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh
from rich.console import Console

from bench.report import load_note, markdown_table, record, show_table
from bench.rig import (
    client,
    free_port,
    query_status,
    require_status,
    router,
    start_serve,
    stop_serve,
    wait_for_status,
)
from service.protocol import PREAMBLE, encode_frame, split_message
from service.replay import frame_publisher
from sources import open_dataset

ROBOT = "overload"
STATUS_KEY = f"objslam/{ROBOT}/status"
DISTINCT_FRAMES = 120
RSS_TARGET_MB = 50.0
STATUS_P99_TARGET_MS = 100.0


class FrameLoop:
    """Pre-encoded frames played 0..K-1, K-2..1, 0.. with fresh timestamps and sequence numbers."""

    def __init__(self, dataset: str, count: int = DISTINCT_FRAMES):
        data = open_dataset(dataset)
        self.resolution = f"{data.camera.width}x{data.camera.height}"
        self._frames = [split_message(encode_frame(data.frame(i))) for i in range(min(count, len(data)))]
        self._order = list(range(len(self._frames))) + list(range(len(self._frames) - 2, 0, -1))
        self.payload_mb = float(np.mean([len(body) for _, body in self._frames])) / 2**20
        self.sent = 0

    def next(self) -> bytes:
        header, body = self._frames[self._order[self.sent % len(self._order)]]
        head = json.dumps({**header, "timestamp": self.sent / 30.0, "seq": self.sent}).encode()
        self.sent += 1
        return PREAMBLE.pack(b"OSLM", 1, 0, len(head)) + head + body


def rss_mb(pid: int) -> tuple[float, float]:
    """(current, peak) resident set size of a process in MB, from /proc (VmRSS, VmHWM)."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return int(fields["VmRSS"].split()[0]) / 1024, int(fields["VmHWM"].split()[0]) / 1024


@dataclass
class Probe:
    """Background sampling while frames flow: the service's RSS, and status queries from their own session."""

    pid: int
    endpoint: str
    period_s: float = 0.05
    rss: list[float] = field(default_factory=list)
    load: list[float] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    failed: int = 0
    queue_depth_max: int = 0
    queue_capacity: int = 0
    dropped_seen: list[int] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)

    def __enter__(self) -> Probe:
        self._session = client(self.endpoint)
        self._threads = [
            threading.Thread(target=self._sample_rss, daemon=True),
            threading.Thread(target=self._query, daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *_) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=10)
        self._session.close()

    def _sample_rss(self) -> None:
        while not self._stop.wait(0.25):
            self.rss.append(rss_mb(self.pid)[0])
            self.load.append(os.getloadavg()[0])

    def _query(self) -> None:
        while not self._stop.wait(self.period_s):
            t0 = time.perf_counter()
            status = query_status(self._session, STATUS_KEY, timeout=2.0)
            if status is None:
                self.failed += 1
                continue
            self.latency_ms.append((time.perf_counter() - t0) * 1e3)
            self.queue_depth_max = max(self.queue_depth_max, status["queue_depth"])
            self.queue_capacity = status["queue_capacity"]
            self.dropped_seen.append(status["frames_dropped"])


def _accounted(status: dict) -> int:
    return (
        status["frames_processed"]
        + status["frames_rejected_total"]
        + status["frames_dropped"]
        + sum(status["errors"].values())
    )


def _settle(session: zenoh.Session, published: int, timeout: float = 180.0) -> dict:
    """Status once every published frame was received and processed, rejected, dropped or failed."""
    deadline = time.monotonic() + timeout
    while True:
        status = query_status(session, STATUS_KEY)
        if status is not None and status["frames_received"] >= published and _accounted(status) >= published:
            return status
        if time.monotonic() > deadline:
            raise RuntimeError(f"the service did not account for {published} frames within {timeout:.0f} s: {status}")
        time.sleep(0.05)


def _calibrate(session: zenoh.Session, publish: Callable[[], None], frames: FrameLoop) -> float:
    """Processing rate (frames/s): a warm-up burst, then a burst that fits the queue, timed until processed."""
    for burst in (16, 48):
        start = time.monotonic()
        for _ in range(burst):
            publish()
        _settle(session, frames.sent)
    return burst / (time.monotonic() - start)


def measure(dataset: str, seconds: float | None, frames: int | None, factor: float) -> dict:
    """Run one overload (``seconds``) or paced memory run (``frames``) against a serve subprocess."""
    loop = FrameLoop(dataset)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    session = router(port)
    serve, log = start_serve(endpoint, ROBOT)
    try:
        wait_for_status(session, STATUS_KEY, serve, log)
        rss_idle = rss_mb(serve.pid)[0]
        pub = frame_publisher(session, f"objslam/{ROBOT}/rgbd")

        def publish() -> None:
            pub.put(loop.next())

        rate = _calibrate(session, publish, loop)
        before = require_status(session, STATUS_KEY)
        rss_start = rss_mb(serve.pid)[0]
        with Probe(serve.pid, endpoint) as probe:
            start = time.monotonic()
            if frames is not None:
                sent = _publish_paced(session, publish, loop, frames)
            elif seconds is not None:
                sent = _publish_for(publish, seconds, factor * rate)
            else:
                raise ValueError("an overload run needs seconds, a memory run frames")
            publish_s = time.monotonic() - start
            status = _settle(session, loop.sent)
            elapsed = time.monotonic() - start
        rss_end, rss_peak = rss_mb(serve.pid)
        pub.undeclare()
    finally:
        stop_serve(serve)
        session.close()
    log.unlink(missing_ok=True)
    processed = status["frames_processed"] - before["frames_processed"]
    lat = np.array(probe.latency_ms) if probe.latency_ms else np.array([np.inf])
    return {
        "dataset": dataset,
        "resolution": loop.resolution,
        "calibrated_fps": rate,
        "seconds": publish_s,
        "published": sent,
        "publish_fps": sent / publish_s,
        "processed": processed,
        "processing_fps": processed / elapsed,
        "dropped": status["frames_dropped"] - before["frames_dropped"],
        "keyframes": status["keyframes"] - before["keyframes"],
        "load": float(np.mean(probe.load or [np.nan])),
        "rejected": status["frames_rejected_total"] - before["frames_rejected_total"],
        "errors": status["errors"],
        "received": status["frames_received"],
        "accounted": _accounted(status),
        "total_published": loop.sent,
        "queue_depth_max": probe.queue_depth_max,
        "queue_capacity": probe.queue_capacity or status["queue_capacity"],
        "drops_seen_while_running": max(probe.dropped_seen, default=0) - before["frames_dropped"],
        "payload_mb": loop.payload_mb,
        "rss_idle": rss_idle,
        "rss_start": rss_start,
        "rss_end": rss_end,
        "rss_peak": max([rss_start, rss_end, *probe.rss]),
        "rss_hwm": rss_peak,
        "status_queries": len(probe.latency_ms) + probe.failed,
        "status_failed": probe.failed,
        "status_p50_ms": float(np.percentile(lat, 50)),
        "status_p99_ms": float(np.percentile(lat, 99)),
        "status_max_ms": float(lat.max()),
    }


def _publish_for(publish: Callable[[], None], seconds: float, rate_hz: float) -> int:
    """Publish at ``rate_hz`` for ``seconds``; returns how many frames were published."""
    start = time.monotonic()
    sent = 0
    while (now := time.monotonic()) - start < seconds:
        due = start + sent / rate_hz
        if due > now:
            time.sleep(due - now)
        publish()
        sent += 1
    return sent


def _publish_paced(
    session: zenoh.Session, publish: Callable[[], None], loop: FrameLoop, frames: int, window: int = 16
) -> int:
    """Publish ``frames`` frames keeping at most ``window`` unaccounted for, so the queue never drops."""
    accounted = _accounted(require_status(session, STATUS_KEY))
    for _ in range(frames):
        while loop.sent - accounted >= window:
            time.sleep(0.02)
            status = query_status(session, STATUS_KEY)
            accounted = _accounted(status) if status is not None else accounted
        publish()
    return frames


def _rows(r: dict, overload: bool) -> list[list[object]]:
    ratio = r["publish_fps"] / r["processing_fps"] if r["processing_fps"] else float("inf")
    errors = sum(r["errors"].values())
    rss_growth = r["rss_end"] - r["rss_start"]
    rows: list[list[object]] = [
        ["scene", f"`{r['dataset']}` {r['resolution']}, {DISTINCT_FRAMES} frames forwards and backwards", ""],
        ["processing rate measured first (frames/s)", f"{r['calibrated_fps']:.1f}", ""],
    ]
    if overload:
        rows += [
            ["publish rate (frames/s)", f"{r['publish_fps']:.1f} for {r['seconds']:.1f} s", ""],
            ["processing rate under overload (frames/s)", f"{r['processing_fps']:.1f}", ""],
            ["publish rate / processing rate", f"{ratio:.2f}", ">= 3"],
        ]
    else:
        rows += [
            ["frames published, paced (no drops)", r["published"], ""],
            ["processing rate (frames/s)", f"{r['processing_fps']:.1f}", ""],
        ]
    rows += [
        [
            "processed / rejected / dropped / errors",
            f"{r['processed']} / {r['rejected']} / {r['dropped']} / {errors}",
            "drops counted" if overload else "0 dropped",
        ],
        [
            "all frames accounted in status (received = processed + rejected + dropped + errors)",
            f"{r['received']} received, {r['accounted']} accounted, {r['total_published']} published",
            "equal",
        ],
        ["drops already in status while publishing", r["drops_seen_while_running"], "> 0" if overload else ""],
        ["queue depth max / capacity", f"{r['queue_depth_max']} / {r['queue_capacity']}", "<= capacity"],
        [
            "RSS idle / start / peak / end (MB)",
            f"{r['rss_idle']:.0f} / {r['rss_start']:.0f} / {r['rss_peak']:.0f} / {r['rss_end']:.0f}",
            "",
        ],
        [
            "RSS growth end - start (MB)",
            f"{rss_growth:+.1f}"
            + (
                f" (a full ingest queue holds {r['queue_capacity']} x {r['payload_mb']:.2f} MB = "
                f"{r['queue_capacity'] * r['payload_mb']:.0f} MB)"
                if overload
                else ""
            ),
            "bounded" if overload else f"<= {RSS_TARGET_MB:.0f}",
        ],
        [
            "keyframes added; RSS growth per keyframe (kB)",
            f"{r['keyframes']}; {rss_growth * 1024 / max(r['keyframes'], 1):.0f}",
            "",
        ],
        ["status queries from another session (failed)", f"{r['status_queries']} ({r['status_failed']})", "0 failed"],
        [
            "status latency p50 / p99 / max (ms)",
            f"{r['status_p50_ms']:.1f} / {r['status_p99_ms']:.1f} / {r['status_max_ms']:.1f}",
            f"p99 < {STATUS_P99_TARGET_MS:.0f}",
        ],
        ["machine load average during the run (2 cores, shared)", f"{r['load']:.1f}", ""],
    ]
    return rows


def run_overload(
    console: Console, dataset: str, seconds: float, frames: int | None, factor: float, write: Path | None
) -> dict:
    """Measure, print the table and record it (``overload``, or ``memory`` for a ``--frames`` run)."""
    result = measure(dataset, None if frames is not None else seconds, frames, factor)
    overload = frames is None
    header = ["metric", "value", "target"]
    rows = _rows(result, overload)
    if overload:
        title = f"Overload: {factor:g}x the processing rate for {seconds:g} s"
        command = f"objslam bench overload --seconds {seconds:g} --factor {factor:g} --dataset '{dataset}'"
        notes = (
            "`objslam serve` (default configuration, provided odometry and detections, queue of "
            f"{result['queue_capacity']}) in a subprocess behind a zenoh router; the processing rate is "
            "measured first on two bursts that fit the queue, then frames are published at the factor times "
            "that rate. RSS of the serve process from /proc (VmRSS, sampled every 0.25 s); start = after the "
            "calibration bursts. Status latency: `status` queries every 50 ms from a second zenoh session, "
            "round trip through the router."
        )
    else:
        title = f"Memory over a {frames}-frame run"
        command = f"objslam bench overload --frames {frames} --dataset '{dataset}'"
        notes = (
            "Frames are published paced (at most 16 unaccounted for), so every frame reaches the pipeline. "
            "RSS of the serve process from /proc; start = after 64 warm-up frames, growth = end - start."
        )
    notes += load_note(result["load"])
    show_table(console, title, header, rows)
    path = record("overload" if overload else "memory", title, command, markdown_table(header, rows), notes, write)
    console.print(f"recorded in {path}")
    return result
