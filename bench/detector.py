"""Detector quality and speed on real frames: per-class counts, ms/frame, and an annotated contact sheet."""

from __future__ import annotations

import logging
import os
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from rich.console import Console
from rich.table import Table

from bench.report import markdown_table, record
from perception.detector import Detector, DetectorSettings
from perception.frame import Detection
from sources import open_dataset

log = logging.getLogger(__name__)

SHEET_FILE = Path("docs/detector_contact_sheet.jpg")
SHEET_GRID = (4, 5)  # rows, columns
SHEET_TILE_WIDTH = 320


@dataclass
class ModelRun:
    """What one model found on the sampled frames, and how long it took."""

    kind: str
    name: str = ""
    frames: int = 0
    counts: Counter = field(default_factory=Counter)
    ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)
    sheet: list[tuple[int, np.ndarray, list[Detection]]] = field(default_factory=list)

    def summary(self) -> dict:
        ms = np.asarray(self.ms)
        return {
            "kind": self.kind,
            "model": self.name or self.kind,
            "frames": self.frames,
            "p50_ms": float(np.percentile(ms, 50)),
            "p95_ms": float(np.percentile(ms, 95)),
            "fps": 1000.0 / float(ms.mean()),
            "cpu_ms": float(np.median(self.cpu_ms)),
            "detections": int(sum(self.counts.values())),
            "counts": dict(self.counts.most_common()),
        }


def _colour(label: str) -> tuple[int, int, int]:
    """A stable bright BGR colour per label."""
    hue = zlib.crc32(label.encode()) % 180
    hsv = np.array([[[hue, 220, 255]]], np.uint8)
    b, g, r = (int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])
    return b, g, r


def annotate(rgb: np.ndarray, dets: list[Detection], width: int, caption: str = "") -> np.ndarray:
    """A BGR thumbnail ``width`` pixels wide with boxes, labels and scores drawn on it."""
    scale = width / rgb.shape[1]
    tile = cv2.resize(rgb[..., ::-1], (width, round(rgb.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    for d in dets:
        x1, y1, x2, y2 = (round(v * scale) for v in d.box)
        colour = _colour(d.label)
        cv2.rectangle(tile, (x1, y1), (x2, y2), colour, 1)
        text = f"{d.label} {d.score:.2f}"
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)
        ty = max(y1, th + 2)
        cv2.rectangle(tile, (x1, ty - th - 2), (x1 + tw + 2, ty), colour, -1)
        cv2.putText(tile, text, (x1 + 1, ty - 2), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    if caption:
        cv2.putText(
            tile, caption, (3, tile.shape[0] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA
        )
    return tile


def contact_sheet(tiles: list[np.ndarray], columns: int) -> np.ndarray:
    """Tiles of equal size in a grid, row by row (missing cells black)."""
    h, w = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = tile
    return sheet


def sheet_path(kind: str, first: bool) -> Path:
    """The default model's sheet is docs/detector_contact_sheet.jpg; others get a ``_<kind>`` suffix."""
    return SHEET_FILE if first else SHEET_FILE.with_name(f"{SHEET_FILE.stem}_{kind}{SHEET_FILE.suffix}")


def model_name(config: DetectorSettings) -> str:
    """The model's kind, plus the input when CenterNet runs on an input fitted to the image (``fit_aspect``)."""
    return config.kind + (
        " (fit_aspect: 512 x 384 input for 4:3)" if config.kind == "centernet" and config.fit_aspect else ""
    )


def measure(dataset_dir: str, every: int, configs: list[DetectorSettings]) -> list[ModelRun]:
    """Run each detector on every ``every``-th frame, interleaved per frame so load drift hits all alike."""
    data = open_dataset(dataset_dir)
    indices = list(range(0, len(data), every))
    cells = SHEET_GRID[0] * SHEET_GRID[1]
    on_sheet = {indices[int(i)] for i in np.linspace(0, len(indices) - 1, min(cells, len(indices)))}
    detectors = [Detector(cfg) for cfg in configs]
    runs = [ModelRun(cfg.kind, model_name(cfg)) for cfg in configs]
    first = data.frame(indices[0]).rgb
    for detector in detectors:
        detector.detect(first)  # warm-up, not timed
    for i in indices:
        rgb = data.frame(i).rgb
        for detector, run in zip(detectors, runs, strict=True):
            cpu = time.process_time()
            dets = detector.detect(rgb)
            run.cpu_ms.append((time.process_time() - cpu) * 1000.0)
            run.ms.append(detector.last_ms)
            run.frames += 1
            run.counts.update(d.label for d in dets)
            if i in on_sheet:
                run.sheet.append((i, rgb, dets))
    for run in runs:
        log.info("%s: %d frames, %.1f ms/frame median", run.kind, run.frames, float(np.median(run.ms)))
    return runs


def _write_sheet(run: ModelRun, path: Path) -> Path:
    tiles = [annotate(rgb, dets, SHEET_TILE_WIDTH, f"#{i} {run.kind}") for i, rgb, dets in run.sheet]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), contact_sheet(tiles, SHEET_GRID[1]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return path


def run_detector_bench(
    console: Console, dataset_dir: str, every: int, write: Path | None, configs: list[DetectorSettings] | None = None
) -> dict:
    """Measure each detector (default: both shipped models), print and record the tables, save contact sheets."""
    configs = configs or [
        DetectorSettings(kind="centernet"),
        DetectorSettings(kind="nanodet"),
        DetectorSettings(kind="centernet", fit_aspect=True),
    ]
    started = time.monotonic()
    runs = measure(dataset_dir, every, configs)
    sheets = [
        _write_sheet(run, sheet_path(run.kind, i == 0)) for i, run in enumerate(runs) if run.name == run.kind
    ]  # one sheet per shipped model, as it runs by default
    results = [run.summary() for run in runs]
    header = [
        "model",
        "frames",
        "ms/frame p50",
        "ms/frame p95",
        "frames/s",
        "CPU ms/frame p50",
        "detections",
        "per frame",
    ]
    rows = [
        [
            r["model"],
            r["frames"],
            f"{r['p50_ms']:.1f}",
            f"{r['p95_ms']:.1f}",
            f"{r['fps']:.1f}",
            f"{r['cpu_ms']:.0f}",
            r["detections"],
            f"{r['detections'] / r['frames']:.2f}",
        ]
        for r in results
    ]
    labels = sorted(
        {label for r in results for label in r["counts"]},
        key=lambda label: -sum(r["counts"].get(label, 0) for r in results),
    )
    class_rows = [[label] + [r["counts"].get(label, 0) for r in results] for label in labels]
    table = Table(title=f"detector on every {every}th frame of {dataset_dir}")
    for h in header:
        table.add_column(h)
    for row in rows:
        table.add_row(*map(str, row))
    console.print(table)
    console.print(
        "detections per class: "
        + "; ".join(f"{r['model']}: " + ", ".join(f"{k} {v}" for k, v in r["counts"].items()) for r in results)
    )
    thresholds = "; ".join(
        f"{c.kind}: floor {c.thresholds()[0]}, per class {c.thresholds()[1] or 'none'}"
        for c in {c.kind: c for c in configs}.values()
    )
    load = os.getloadavg()[0]
    notes = (
        f"Detector only (pre-processing, onnxruntime with {configs[0].threads} intra-op threads, decoding, "
        f"NMS), models interleaved frame by frame after one warm-up frame; frames/s = 1000 / mean ms; "
        f"CPU ms counts all threads. "
        f"1-minute load average at the end: {load:.1f} on {os.cpu_count()} cores (other work inflates "
        f"the wall-clock figures). Thresholds: {thresholds}. "
        f"Contact sheets: {', '.join(f'`{p.as_posix()}`' for p in sheets)}."
    )
    tables = (
        markdown_table(header, rows)
        + "\n\nDetections per class:\n\n"
        + markdown_table(["class"] + [r["model"] for r in results], class_rows)
    )
    path = record(
        "detector",
        "Object detector on real frames",
        f"objslam bench detector --dataset '{dataset_dir}' --every {every}",
        tables,
        notes,
        write,
    )
    console.print(f"recorded in {path}; contact sheets {', '.join(map(str, sheets))}")
    log.info("detector bench took %.0f s", time.monotonic() - started)
    return {"dataset": dataset_dir, "every": every, "models": results, "sheets": [str(p) for p in sheets]}
