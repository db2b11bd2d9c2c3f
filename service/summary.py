"""The summary table that ``objslam run`` (and ``make run``) prints."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text


def print_summary(console: Console, summary: dict[str, Any], out: Path) -> None:
    """Frames, poses, objects by class, loop closures, ATE against ground truth, throughput (an empty map
    included: no frame processed prints zeros)."""
    table = Table(title=Text(f"objslam run: {summary.get('dataset')}"), show_header=False)
    rows = [
        ("frames", summary["frames"]),
        ("frames processed", summary["frames_processed"]),
        ("frames rejected", json.dumps(summary["frames_rejected"]) if summary["frames_rejected"] else 0),
        ("frames dropped", summary["frames_dropped"]),
        ("keyframes (poses in graph)", summary["keyframes"]),
        ("objects by class", json.dumps(summary["objects_by_class"]) if summary["objects_by_class"] else "none"),
        (
            "keyframe detections by class",
            json.dumps(dict(sorted(summary.get("keyframe_detections_by_class", {}).items(), key=lambda kv: -kv[1])[:8]))
            or "none",
        ),
        ("loop closures accepted", summary["loop_closures"]),
    ]
    for name, err in summary.get("ate", {}).items():
        rows.append((f"ATE RMSE {name}", f"{err['ate_rmse_m'] * 100:.2f} cm ({err['pairs']} poses)"))
    if not summary.get("ate"):
        rows.append(("ATE", "no ground truth"))
    rows.append(("throughput", f"{summary['throughput_fps']:.1f} frames/s ({summary['seconds']:.1f} s)"))
    lat = summary.get("latency", {}).get("ingest_to_graph", {})
    if lat.get("n"):
        rows.append(("ingest-to-graph latency", f"p50 {lat['p50_ms']:.1f} ms, p95 {lat['p95_ms']:.1f} ms"))
    rows.append(("outputs", str(out)))
    for name, value in rows:  # plain text: a dataset path or class name with [...] is no rich markup
        table.add_row(Text(name), Text(str(value)))
    console.print(table)
