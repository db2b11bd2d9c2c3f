"""What the viewer costs: the same pre-encoded frames into ``objslam serve`` with and without a Rerun recording.

Runs alternate (off, on, off, on, ...) so that a change of the machine's load falls on both; each is a fresh
``serve`` subprocess fed every frame at once (``bench.throughput.serve_and_publish``), the viewer on as
``viewer.rrd`` (the sink thread, the .rrd written as the map grows; the same sink feeds ``--rerun`` and
``--rerun-web``).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
from rich.console import Console

from bench.report import load_note, markdown_table, record, show_table
from bench.throughput import serve_and_publish
from service.protocol import encode_frame
from sources import open_dataset

COST_TARGET = 0.05
ROUNDS = 3


def run_viewer_throughput(console: Console, dataset: str, frames: int, write: Path | None) -> float:
    """Measure, print and record the viewer's cost; the cost as a fraction of the throughput without it."""
    data = open_dataset(dataset)
    frames = min(frames, len(data))
    payloads = [encode_frame(data.frame(i)) for i in range(frames)]
    fps: dict[bool, list[float]] = {False: [], True: []}
    sizes, loads = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(ROUNDS):
            for on in (False, True):
                rrd = Path(tmp) / f"map-{r}.rrd"
                env = {"OBJSLAM_VIEWER__RRD": str(rrd)} if on else {}
                status, _, elapsed = serve_and_publish(payloads, None, env)
                fps[on].append(status["frames_processed"] / elapsed)
                loads.append(os.getloadavg()[0])
                if on:
                    sizes.append(rrd.stat().st_size / 1e6 if rrd.exists() else 0.0)
    off, on_ = float(np.median(fps[False])), float(np.median(fps[True]))
    cost = 1.0 - on_ / off
    header = ["viewer", "throughput (frames/s, median)", "runs", ".rrd MB"]
    rows: list[list[object]] = [
        ["off", round(off, 1), ", ".join(f"{v:.1f}" for v in fps[False]), "-"],
        ["on (recording)", round(on_, 1), ", ".join(f"{v:.1f}" for v in fps[True]), f"{np.median(sizes):.1f}"],
        ["**cost**", f"**{100 * cost:.1f} %**", f"target <= {100 * COST_TARGET:.0f} %", ""],
    ]
    show_table(console, "The viewer's cost to throughput", header, rows)
    notes = (
        f"`{dataset}`, {frames} frames pre-encoded (JPEG + PNG16), all published at once into a `serve` "
        f"subprocess behind a zenoh router; {ROUNDS} rounds of off / on, alternating; throughput = frames "
        "processed / (first publish to last frame in the graph)." + load_note(sum(loads) / len(loads))
    )
    cmd = f"objslam bench throughput --rerun --frames {frames} --dataset '{dataset}'"
    path = record(
        "throughput_rerun", "The viewer's cost to throughput", cmd, markdown_table(header, rows), notes, write
    )
    console.print(f"recorded in {path}")
    return cost
