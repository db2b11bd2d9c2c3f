"""``objslam bench stages``: per-stage cost of the whole pipeline on a dataset, and keyframes/s of detection + association."""

from __future__ import annotations

import tempfile
from pathlib import Path

from rich.console import Console

from service.bench.report import markdown_table, record, show_table
from service.config import load_settings
from service.run import run_dataset
from service.sources import WithoutOdometry, open_dataset

STAGES = ("decode", "frontend", "detector", "objects", "loop_closure", "graph", "ingest_to_graph")


def run_stages_bench(console: Console, dataset: str, frames: int | None, write: Path | None) -> dict:
    """Run the service end to end (own odometry, detector when the data has no detections) and tabulate stages."""
    data = WithoutOdometry(open_dataset(dataset))
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_dataset(data, Path(tmp), load_settings(), max_frames=frames, progress=False)
    lat = summary["latency"]
    rows = [[s, lat[s]["n"], lat[s]["p50_ms"], lat[s]["p95_ms"]] for s in STAGES if lat.get(s, {}).get("n")]
    header = ["stage", "calls", "p50 (ms)", "p95 (ms)"]
    show_table(console, "pipeline stages", header, rows)
    per_kf = sum(lat[s]["p50_ms"] for s in ("detector", "objects") if lat.get(s, {}).get("n"))
    kf_rate = 1000.0 / per_kf if per_kf else float("nan")
    console.print(f"detection + association per keyframe: {per_kf:.1f} ms p50 = {kf_rate:.1f} keyframes/s "
                  f"(target >= 10)")
    notes = (f"{summary['frames_processed']} frames, {summary['keyframes']} keyframes, frames replayed without "
             f"odometry. Detection + association (detector + objects stages, p50): {per_kf:.1f} ms per keyframe "
             f"= **{kf_rate:.1f} keyframes/s** (target >= 10). 'objects' is NPDA with depth warping, tracks, "
             "back-projection and intermittent clustering; 'graph' is the whole pipeline step of a frame.")
    name = Path(dataset).name or dataset
    record("stages", f"Pipeline stage cost ({name})",
           f"objslam bench stages --dataset {dataset}" + (f" --frames {frames}" if frames else ""),
           markdown_table(header, rows), notes, write)
    return {"per_keyframe_ms": per_kf, "keyframes_per_s": kf_rate, "latency": lat}
