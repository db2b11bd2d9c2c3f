"""``objslam bench stages``: per-stage cost of the pipeline on a dataset, and keyframes/s of detection + association."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from bench.report import StealMeter, markdown_table, record, show_table
from service.config import load_settings
from service.run import run_dataset
from service.scheduler import ThreadedRunner
from slam.build import build_core
from sources import WithoutOdometry, open_dataset

MAPPING_RUNS = 3  # keyframe-mapping rate: median of this many runs (the shared host's steal varies)
STAGES = ("decode", "frontend", "detector", "objects", "loop_closure", "graph", "ingest_to_graph")


def run_stages_bench(console: Console, dataset: str, frames: int | None, write: Path | None) -> dict:
    """Run the service end to end (own odometry, detector when the data has no detections) and tabulate stages."""
    data, steal = WithoutOdometry(open_dataset(dataset)), StealMeter()
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_dataset(data, Path(tmp), load_settings(), max_frames=frames, progress=False)
    lat = summary["latency"]
    rows = [[s, lat[s]["n"], lat[s]["p50_ms"], lat[s]["p95_ms"]] for s in STAGES if lat.get(s, {}).get("n")]
    header = ["stage", "calls", "p50 (ms)", "p95 (ms)"]
    show_table(console, "pipeline stages", header, rows)
    per_kf = sum(lat[s]["p50_ms"] for s in ("detector", "objects") if lat.get(s, {}).get("n"))
    every = max(1, round(summary["frames_processed"] / max(1, summary["keyframes"])))
    runs = {
        bg: sorted(keyframe_mapping_rate(dataset, summary["frames_processed"], every, bg) for _ in range(MAPPING_RUNS))
        for bg in (False, True)
    }
    rates = {bg: float(np.median(r)) for bg, r in runs.items()}
    spread = {bg: f"{r[0]:.1f}-{r[-1]:.1f}" for bg, r in runs.items()}
    console.print(
        f"detection + association: {per_kf:.1f} ms p50 per keyframe; keyframe mapping "
        f"{rates[False]:.1f} keyframes/s in one thread, {rates[True]:.1f} on the service's threads "
        f"(target >= 10)"
    )
    notes = (
        f"{summary['frames_processed']} frames, {summary['keyframes']} keyframes, frames replayed without "
        f"odometry. Detection + association (detector + objects stages, p50): {per_kf:.1f} ms per keyframe. "
        "'objects' is NPDA with depth warping, tracks, back-projection and intermittent clustering; 'graph' is "
        "the worker's pipeline step of a frame (object mapping and loop verification of a keyframe run on "
        "the mapping thread and are applied three keyframes later). Keyframe mapping: one frame in "
        f"{every} (the run's keyframe spacing) with its ground-truth odometry, each made a keyframe, "
        "through the pipeline (detector, NPDA, tracks, clustering, landmarks into iSAM2; loop closure off): "
        f"keyframes / wall time, the frames decoded beforehand, median of {MAPPING_RUNS} runs (range in "
        "brackets); 'one thread' runs each keyframe's mapping at once, 'service threads' as `serve` does "
        "(detection on the detector thread, the rest on the mapping thread, beside the tracking of the next "
        f"frames): **{rates[True]:.1f} keyframes/s** ({spread[True]}) on the service threads (target >= 10), "
        f"{rates[False]:.1f} ({spread[False]}) in one thread. CPU time stolen by the hypervisor during the runs: "
        f"{steal.percent():.1f} %."
    )
    name = Path(dataset).name or dataset
    record(
        "stages",
        f"Pipeline stage cost ({name})",
        f"objslam bench stages --dataset {dataset}" + (f" --frames {frames}" if frames else ""),
        markdown_table(header, rows),
        notes,
        write,
    )
    return {"per_keyframe_ms": per_kf, "keyframes_per_s": rates[True], "latency": lat}


def keyframe_mapping_rate(dataset: str, frames: int, every: int, background: bool) -> float:
    """Keyframes per second of detection + association + landmarks through the pipeline, every frame a keyframe."""
    ds = open_dataset(dataset)
    truth = ds.ground_truth
    keyframes = [ds.frame(i) for i in range(0, min(frames, len(ds)), every)]
    for frame in keyframes:  # tracking is not what is measured here
        if frame.odometry is None and truth is not None:
            frame.odometry = truth.poses[frame.seq]
    settings = load_settings(None, {"loops": {"source": "off"}, "keyframes": {"max_interval": 1}})
    pipeline = build_core(settings, ThreadedRunner() if background else None)
    try:
        pipeline.step(keyframes[0])  # loads the detector
        pipeline.flush()
        t0 = time.perf_counter()
        for frame in keyframes[1:]:
            pipeline.step(frame)
        pipeline.flush()
        return (len(keyframes) - 1) / (time.perf_counter() - t0)
    finally:
        pipeline.close()
