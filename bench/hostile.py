"""Hostile input and hostile peers (issue 26): ``objslam serve`` under crafted messages, floods and poisoned streams.

Each attack runs against a fresh ``objslam serve`` subprocess behind a zenoh router in this process, so no
attack's numbers carry another's load or memory. The robot's good frames (``synthetic:room``, pre-encoded once
and replayed forwards and backwards by overload's FrameLoop, 30 frames/s) come from the router's session; the
crafted messages, queries and save requests from a second session, the attacker. After 30 warm-up frames the
service's status and RSS are the baseline; the attack's figures are differences from them. RSS is sampled from
/proc at 20 Hz (VmRSS, and VmHWM when it rose during the attack); the frame counters from ``status`` at about
50 Hz, which dates when each frame was done with.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable

import numpy as np
from rich.console import Console

from bench.attacks import (
    ATTACKS,
    BOMB_EVERY_S,
    BOMB_SIDE,
    CAMERA_HZ,
    DATASET,
    GARBAGE_PROCESSED_TARGET,
    GARBAGE_RATE_HZ,
    INGEST_P99_FACTOR,
    JUNK_BYTES,
    JUNK_EVERY_S,
    LABEL_FRAMES,
    POISON_STAMP,
    PREFIX,
    QUERY_FRAMES,
    QUERY_RATE_HZ,
    QUERY_TIMEOUT_S,
    RECOVERY_TARGET_S,
    RSS_TARGET_MB,
    SAVE_FRAMES,
    SAVE_RATE_HZ,
    STATUS_KEY,
    WARMUP_FRAMES,
    cached_png_bomb,
    carrier,
    flood_detections,
    garbage,
    jpeg_bomb_image,
    restamped,
)
from bench.hostile_rig import (
    Monitor,
    Outcome,
    Played,
    Queries,
    Rig,
    _flood,
    _paced,
    _reply_size,
    _settle,
    max_rate,
    service,
)
from bench.overload import DISTINCT_FRAMES, FrameLoop, _accounted
from bench.report import markdown_table, record, show_table
from service.protocol import MAX_DETECTIONS

# ---------------------------------------------------------------- attacks


def _every(message: Callable[[float], bytes], loop: FrameLoop) -> Callable[[int], bytes | None]:
    """An injector: a crafted frame every BOMB_EVERY_S, the first after half that, stamped between two good frames."""
    period = round(BOMB_EVERY_S * CAMERA_HZ)
    return lambda i: message((loop.sent - 0.5) / CAMERA_HZ) if i % period == period // 2 else None


def attack_paced(rig: Rig, loop: FrameLoop, seconds: float, attack: str, received: int) -> Played:
    """Play ``attack`` over a paced stream of good frames (``received``: messages the service had before)."""
    played, frames = Played(), round(seconds * CAMERA_HZ)
    if attack == "quiet":
        _paced(rig, loop, frames, played)
    elif attack == "jpeg_bomb":
        jpeg = jpeg_bomb_image()
        _paced(rig, loop, frames, played, _every(lambda t: carrier(t, color=jpeg), loop))
    elif attack == "png_bomb":
        png = cached_png_bomb()
        _paced(rig, loop, frames, played, _every(lambda t: carrier(t, depth=png), loop))
    elif attack == "garbage_flood":
        with _flood(rig.crafted, garbage(np.random.default_rng(0), loop.next()), GARBAGE_RATE_HZ, played):
            _paced(rig, loop, frames, played)
    elif attack == "junk_60mb":
        with _flood(rig.crafted, [np.random.default_rng(1).bytes(JUNK_BYTES)], 1.0 / JUNK_EVERY_S, played):
            _paced(rig, loop, round(frames / 3), played)
    elif attack == "label_flood":
        rng, (width, height) = np.random.default_rng(2), map(int, loop.resolution.split("x"))

        def labelled(i: int) -> bytes:
            if 30 <= i < 30 + LABEL_FRAMES:
                return restamped(loop.next(), detections=flood_detections(rng, width, height))
            return loop.next()

        _paced(rig, loop, LABEL_FRAMES + 60, played, good=labelled)
        played.extra["labels_sent"] = LABEL_FRAMES * MAX_DETECTIONS
    elif attack == "save_flood":
        with Queries(rig.attacker, [f"{PREFIX}/save"], SAVE_RATE_HZ) as saves:
            _paced(rig, loop, SAVE_FRAMES, played)
        played.extra["saves"] = saves
    elif attack == "time_poison":
        _paced(rig, loop, 30, played)
        played.extra["before_poison"] = _settle(rig, received + played.good)
        _paced(rig, loop, 30, played, lambda i: restamped(loop.next(), timestamp=POISON_STAMP) if i == 0 else None)
        played.extra["after_poison_good"] = 30
    else:
        raise ValueError(f"unknown attack {attack!r}")
    return played


def run_attack(attack: str, seconds: float) -> Outcome:
    """One attack against a fresh service: warm-up, baseline, the attack with monitoring, settle, differences."""
    loop = FrameLoop(DATASET)
    with (
        tempfile.TemporaryDirectory(prefix="objslam-hostile-") as state_dir,
        service({"OBJSLAM_STATE_DIR": state_dir} if attack == "save_flood" else None) as rig,
    ):
        warm = Played()
        _paced(rig, loop, WARMUP_FRAMES, warm)
        before = _settle(rig, warm.good)
        load0 = os.getloadavg()[0]
        with Monitor(rig.proc.pid, rig.robot) as monitor:
            start = time.monotonic()
            played = attack_paced(rig, loop, seconds, attack, before["frames_received"])
            after = _settle(rig, before["frames_received"] + played.good + played.crafted)
            time.sleep(0.2)
        if attack == "label_flood":
            played.extra["status_bytes"] = _reply_size(rig.robot, STATUS_KEY)
    base = _accounted(before)
    recoveries = [None if (done := monitor.done_at(base + n)) is None else done - t for t, n in played.marks]
    return Outcome(
        attack=attack,
        played=played,
        before=before,
        after=after,
        rss_before=monitor.before,
        rss_peak=monitor.peak,
        rss_rises=[monitor.rise_after(t) for t, _ in played.marks],
        recoveries=recoveries,
        max_gap_s=monitor.max_gap(start),
        queue=(monitor.queue_depth_max, monitor.queue_capacity),
        load=(load0 + os.getloadavg()[0]) / 2,
    )


# ---------------------------------------------------------------- the table


def _met(ok: bool) -> str:
    return "yes" if ok else "**no**"


def _good(o: Outcome) -> tuple[str, float]:
    processed = o.delta("frames_processed")
    good = o.played.good
    loss = 100.0 * (good - processed) / good if good else 0.0
    errors = sum(o.after["errors"].values()) - sum(o.before["errors"].values())
    detail = f"; dropped {o.delta('frames_dropped')}, errors {errors}" if processed < good else ""
    return f"{processed} / {good} ({loss:.1f} % lost{detail})", 100.0 - loss


def _rejections(o: Outcome) -> str:
    return ", ".join(f"{k} {v}" for k, v in o.rejected().items()) or "none"


def _rows(o: Outcome, quiet: Outcome | None) -> list[list[object]]:
    a, good = o.attack, _good(o)
    growth = o.rss_peak - o.rss_before
    ref = f" (quiet {quiet.rss_peak - quiet.rss_before:+.0f})" if quiet is not None and a != "quiet" else ""
    rows: list[list[object]] = [[a, "good frames processed / published", good[0], "", ""]]
    if a == "garbage_flood":
        rows[0][3:] = [f">= {GARBAGE_PROCESSED_TARGET:.0f} % processed", _met(good[1] >= GARBAGE_PROCESSED_TARGET)]
    if o.played.crafted:
        reached = o.delta("frames_received") - o.played.good
        rows.append([a, "crafted messages sent / received by the service", f"{o.played.crafted} / {reached}", "", ""])
    rows.append([a, "rejected by reason", _rejections(o), "", ""])
    if "flood_rate_hz" in o.played.extra:
        rows.append([a, "crafted messages per second (achieved)", f"{o.played.extra['flood_rate_hz']:.1f}", "", ""])
    single = a in ("jpeg_bomb", "png_bomb", "junk_60mb")
    rows.append(
        [
            a,
            f"peak RSS growth over {o.rss_before:.0f} MB before (MB)",
            f"{growth:+.1f}{ref}",
            f"<= {RSS_TARGET_MB:.0f}" if single else "",
            _met(growth <= RSS_TARGET_MB) if single else "",
        ]
    )
    if a in ("jpeg_bomb", "png_bomb"):
        rise = max(o.rss_rises)
        rows.append(
            [
                a,
                "largest RSS rise within 1 s of a crafted frame (MB)",
                f"{rise:+.1f}",
                f"<= {RSS_TARGET_MB:.0f}",
                _met(rise <= RSS_TARGET_MB),
            ]
        )
        rec = [r for r in o.recoveries if r is not None]
        ok = len(rec) == len(o.recoveries) and max(rec, default=np.inf) <= RECOVERY_TARGET_S
        rows.append(
            [
                a,
                "crafted frame sent to next good frame done, median / max (s)",
                f"{np.median(rec):.3f} / {max(rec):.3f}"
                + (f" ({len(o.recoveries) - len(rec)} never)" if len(rec) < len(o.recoveries) else ""),
                f"<= {RECOVERY_TARGET_S:.0f}",
                _met(ok),
            ]
        )
    if a in ("quiet", "label_flood", "save_flood", "junk_60mb", "garbage_flood"):
        rows.append(
            [
                a,
                "longest gap between processed frames (ms); queue depth max / capacity",
                f"{o.max_gap_s * 1e3:.0f}; {o.queue[0]} / {o.queue[1]}",
                "",
                "",
            ]
        )
    if a == "label_flood":
        labels = o.after.get("labels", {})
        rows += [
            [
                a,
                "labels sent; admitted / relabelled 'other' / detections dropped",
                f"{o.played.extra['labels_sent']}; {labels.get('labels_admitted')} / {labels.get('labels_relabelled')} "
                f"/ {labels.get('detections_dropped')}",
                "",
                "",
            ],
            [a, "classes in keyframe_detections_by_class", len(o.after["keyframe_detections_by_class"]), "", ""],
            [a, "status reply after (bytes)", o.played.extra["status_bytes"], "", ""],
        ]
    if a == "save_flood":
        saves: Queries = o.played.extra["saves"]
        s = saves.outcomes
        rows.append(
            [
                a,
                "save requests: done / busy / error / timeout",
                f"{s['answered']} / {s['busy']} / {s['error']} / {s['timeout']}",
                "",
                "",
            ]
        )
    if a == "time_poison":
        after = o.after["frames_processed"] - o.played.extra["before_poison"]["frames_processed"]
        n = o.played.extra["after_poison_good"]
        rows += [
            [a, "rejected time_jump", o.rejected().get("time_jump", 0), "1", _met(o.rejected().get("time_jump") == 1)],
            [a, "good frames after the poisoned one processed", f"{after} / {n}", "all", _met(after == n)],
        ]
    return rows


def _query_rows(quiet: dict, flood: dict) -> list[list[object]]:
    q: Queries = flood["queries"]
    out, a = q.outcomes, "query_flood"
    ratio = flood["ingest_p99_ms"] / quiet["ingest_p99_ms"]
    return [
        [
            a,
            "queries sent (per second achieved) over status, trajectory, objects",
            f"{q.sent} ({q.sent / q.seconds:.0f})",
            "",
            "",
        ],
        [
            a,
            "answered / busy / error / timeout",
            f"{out['answered']} / {out['busy']} / {out['error']} / {out['timeout']}",
            "0 timeouts",
            _met(out["timeout"] == 0),
        ],
        [a, "query latency p50 / p99 (ms)", f"{q.percentile(50):.1f} / {q.percentile(99):.1f}", "", ""],
        [
            a,
            f"max rate, {QUERY_FRAMES} frames: processed, frames/s, quiet -> flooded",
            f"{quiet['status']['frames_processed']}, {quiet['fps']:.1f} -> {flood['status']['frames_processed']}, "
            f"{flood['fps']:.1f}",
            "",
            "",
        ],
        [
            a,
            "ingest-to-graph p99 (ms), quiet -> flooded",
            f"{quiet['ingest_p99_ms']:.0f} -> {flood['ingest_p99_ms']:.0f} ({ratio:.2f}x)",
            f"<= {INGEST_P99_FACTOR:g}x quiet",
            _met(ratio <= INGEST_P99_FACTOR),
        ],
        [
            a,
            "peak RSS growth (MB), quiet -> flooded",
            f"{quiet['rss_growth']:+.1f} -> {flood['rss_growth']:+.1f}",
            "",
            "",
        ],
    ]


def run_hostile(console: Console, attacks: list[str], seconds: float, write: bool) -> list[list[object]]:
    """Run the attacks in turn, each against a fresh service; print the table and record it (``hostile``)."""
    rows: list[list[object]] = []
    quiet: Outcome | None = None
    loads: list[float] = []
    for attack in attacks:
        console.print(f"[bold]{attack}[/bold] ...")
        try:
            if attack == "query_flood":
                calm, flood = max_rate(False), max_rate(True)
                rows += _query_rows(calm, flood)
                continue
            outcome = run_attack(attack, seconds)
        except RuntimeError as exc:
            last = [line.strip() for line in str(exc).splitlines() if line.strip()] or [""]
            rows.append([attack, "failed", last[-1][:200].replace("|", "/"), "", "**no**"])
            continue
        quiet = outcome if attack == "quiet" else quiet
        loads.append(outcome.load)
        rows += _rows(outcome, quiet)
    header = ["attack", "measure", "value", "target", "met"]
    title = "Hostile input and hostile peers"
    show_table(console, title, header, rows)
    if write:
        options = f" --seconds {seconds:g}" + (
            "" if list(attacks) == list(ATTACKS) else f" --attacks {','.join(attacks)}"
        )
        path = record(
            "hostile", title, f"objslam bench hostile{options}", markdown_table(header, rows), _notes(seconds, loads)
        )
        console.print(f"recorded in {path}")
    return rows


def _notes(seconds: float, loads: list[float]) -> str:
    load = float(np.mean(loads)) if loads else float("nan")
    return (
        "Each attack against a fresh `objslam serve` (default configuration) in a subprocess behind a zenoh router: "
        f"good frames of `{DATASET}` (640x480, odometry and detections; its first {DISTINCT_FRAMES} frames forwards "
        f"and backwards) at {CAMERA_HZ:.0f} frames/s from the robot's session after {WARMUP_FRAMES} warm-up frames; "
        "crafted messages, queries and saves from a second session ('received by the service': its "
        "frames_received; zenoh's transport may refuse a message before). "
        f"**quiet**: {seconds:g} s of good frames only. **jpeg_bomb**: a 64x48 frame whose ~1 KB JPEG's SOF declares "
        f"{BOMB_SIDE}x{BOMB_SIDE}; **png_bomb**: its depth a 16-bit PNG of zeros that decodes to "
        f"{BOMB_SIDE}x{BOMB_SIDE} (1.8 GB; {len(cached_png_bomb()) / 2**20:.1f} MB); one every {BOMB_EVERY_S:g} s for "
        f"{seconds:g} s, sent just before a good frame. Recovery: the bomb sent to the first status (polled every "
        "~20 ms) showing that good frame done, its own processing included. **garbage_flood**: random byte strings "
        f"(12 B to 64 KB) and good frames with a bad magic at {GARBAGE_RATE_HZ:.0f}/s for {seconds:g} s. "
        f"**junk_60mb**: 60 MB of random bytes every {JUNK_EVERY_S:g} s for {seconds / 3:g} s (the blocking "
        f"publisher's achieved rate in the table). **label_flood**: 30 good frames, {LABEL_FRAMES} carrying "
        f"{MAX_DETECTIONS} detections with fresh random labels, 30 good frames. **query_flood**: {QUERY_FRAMES} frames "
        f"published at once (queue of {QUERY_FRAMES + 1}) to a fresh service, quiet, then to another under "
        f"{QUERY_RATE_HZ:.0f} queries/s (non-blocking gets, timeout {QUERY_TIMEOUT_S:g} s) until every frame is done; "
        "latency of the answered queries; 'busy' = an error reply saying so. Ingest-to-graph p99 from status. "
        f"**save_flood**: `save` {SAVE_RATE_HZ:.0f} times a second during {SAVE_FRAMES} good frames (state directory "
        f"in /tmp). **time_poison**: 30 good frames, one stamped {POISON_STAMP:g}, 30 more. RSS of the serve process "
        "from /proc at 20 Hz (VmRSS; VmHWM when it rose), growth over its RSS after the warm-up; it includes the "
        f"map's own growth, as the quiet row shows. 1-minute load average during the attacks {load:.1f} on 2 cores "
        "(this bench, its router and the service)."
    )
