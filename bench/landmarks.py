"""``objslam bench landmarks``: objects in the graph (SPEC 6.8) end to end, with and without loop closures.

Each dataset is run through the service four times (frames without odometry, so the visual front end runs):
object landmarks off / on, loop closures off / appearance. The table gives the trajectory error of each
run, what entered the graph, how often the objects were re-posed and re-clustered, and on synthetic data
how far the landmarks and the cluster centres lie from the true box centres.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from bench.report import load_note, markdown_table, record, show_table
from bench.slam import default_datasets, short_name
from evaluation.object_metrics import MappedObject, match_objects
from service.config import load_settings
from service.run import run_dataset
from sources import WithoutOdometry, open_dataset

VARIANTS = [("off", False), ("off", True), ("appearance", False), ("appearance", True)]


def run_variant(spec: str, loops: str, landmarks: bool) -> dict[str, Any]:
    """One run; its ATE, graph counts and (with ground-truth objects) centre errors."""
    dataset = WithoutOdometry(open_dataset(spec))
    settings = load_settings(None, {"loops": {"source": loops}, "objects": {"landmarks": landmarks}})
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_dataset(dataset, Path(tmp), settings, progress=False)
        objects = json.loads((Path(tmp) / "objects.json").read_text())
    row = {
        "dataset": spec,
        "loops": loops,
        "landmarks": landmarks,
        "ate_cm": summary["ate"]["trajectory"]["ate_rmse_m"] * 100,
        "ate_odometry_cm": summary["ate"]["odometry"]["ate_rmse_m"] * 100,
        "loop_closures": summary["loop_closures"],
        "objects": len(objects),
        "in_graph": summary["landmarks"],
        "measurements": summary["landmark_measurements"],
        "reposes": summary["object_reposes"],
        "fps": summary["throughput_fps"],
        "landmark_error_m": None,
        "mean_error_m": None,
    }
    truth = dataset.objects
    if truth:
        aligned = _alignment(summary)
        placed = [o for o in objects if o["landmark"] is not None]
        for key, field in (("landmark_error_m", "landmark"), ("mean_error_m", "mean")):
            centres = [MappedObject(o["label"], aligned(np.asarray(o[field]))) for o in placed]
            errors = [
                np.linalg.norm(centres[a].mean - np.asarray(truth[b].center)) for a, b in match_objects(centres, truth)
            ]
            row[key] = float(np.median(errors)) if errors else None
    return row


def _alignment(summary: dict[str, Any]):
    """Map trajectory-frame points into the ground-truth frame with the run's SE(3) ATE alignment."""
    T = np.asarray(summary["ate"]["trajectory"].get("alignment", np.eye(4)), float)
    return lambda p: T[:3, :3] @ p + T[:3, 3]


def run_landmarks_bench(console: Console, datasets: list[str] | None, write: Path | None) -> list[dict[str, Any]]:
    results = []
    for spec in datasets or default_datasets():
        for loops, landmarks in VARIANTS:
            console.print(f"{short_name(spec)}: loops {loops}, object landmarks {'on' if landmarks else 'off'}")
            results.append(run_variant(spec, loops, landmarks))
    load = os.getloadavg()[0]

    def cm(v):
        return "n/a" if v is None else f"{v * 100:.1f}"

    header = [
        "dataset",
        "loop closures",
        "object landmarks",
        "ATE (cm)",
        "accepted loops",
        "objects",
        "landmarks in graph",
        "landmark measurements",
        "re-posings",
        "median landmark error (cm)",
        "median cluster-centre error (cm)",
        "frames/s",
    ]
    rows = [
        [
            short_name(r["dataset"]),
            r["loops"],
            "on" if r["landmarks"] else "off",
            f"{r['ate_cm']:.2f}",
            r["loop_closures"],
            r["objects"],
            r["in_graph"],
            r["measurements"],
            r["reposes"],
            cm(r["landmark_error_m"]),
            cm(r["mean_error_m"]),
            f"{r['fps']:.1f}",
        ]
        for r in results
    ]
    show_table(console, "Objects in the graph", header, rows)
    notes = (
        "Frames replayed without odometry (visual front end). ATE: RMSE over every frame after SE(3) "
        "alignment. A stable object (>= 5 pooled feature vectors) is a Point3 landmark measured by the "
        "camera-frame centre of each view not cut by the image border (amodally completed, as in "
        "`bench objects`; sigma = max(0.1 m, largest point std) across the viewing ray and 3 x that along "
        "it, Huber); re-posings "
        "count the optimisations that moved an observing keyframe > 1 cm or 0.5 deg, after which every "
        "feature vector is recomputed from the new poses and the objects re-clustered. Errors: landmark "
        "estimate and cluster centre (objects with a landmark, after the ATE alignment) against the true "
        "box centre, matched as in `bench objects`." + load_note(load)
    )
    command = "objslam bench landmarks" + "".join(f" --dataset {d}" for d in datasets or [])
    record(
        "landmarks",
        "Objects in the graph: landmarks, re-clustering and trajectory error",
        command,
        markdown_table(header, rows),
        notes,
        write,
    )
    return results
