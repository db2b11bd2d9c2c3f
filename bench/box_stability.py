"""``objslam bench box-stability``: how much a detector's boxes move between consecutive frames.

The object path is tuned on the synthetic family, whose simulated detector puts each box side within a few
percent of the object's edge, independently per frame. This measures the same statistics for the real
detector on the real sequences and for the simulated one (at its defaults or with the knobs of
``sources.detector_errors``), so the error levels of ``bench objects --family --detector-errors`` can be read
against what CenterNet does on real frames.

The previous frame's boxes are first moved into the current image by the true relative pose (``moved``: the
box's centre at its middle's median depth goes where the pose takes it, its size scales with the depth), so
the camera's motion, fast in the synthetic paths, does not count as the detector's. Each detection is then
paired with the previous frame's detection of the same label that overlaps it most (IoU >= ``PAIR_IOU``). Per
pair and box side not at the image border: the side's change as a share of the box's size (width for left /
right, height for top / bottom).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from rich.console import Console

from bench.report import markdown_table, record, show_table
from graph.geometry import inverse
from graph.trajectory import nearest_timestamps
from perception.camera import Intrinsics
from perception.features import Box
from perception.frame import Detection
from perception.npda import box_iou
from sources import open_dataset
from sources.base import ground_truth_of

PAIR_IOU = 0.3
"""A detection continues the previous frame's box of its label that overlaps it most, at least this much."""
SWITCH_IOU = 0.5
"""A detection over a previous frame's box of another label this much, with none of its own, switched label."""
PART_RATIO = 0.6
"""A pair whose smaller box has under this share of the larger's area is a part box next to a whole one."""
BORDER_PX = 3.0
"""Box sides within this many pixels of the image border are cut by it and left out."""


@dataclass(frozen=True)
class Stability:
    """Frame-to-frame box statistics of one source."""

    frames: int
    pairs: int
    sides: int
    robust_sd: float  # 1.4826 x the median absolute deviation of the side changes
    p90: float  # 90th percentile of the absolute side changes
    part_pairs: float  # share of pairs whose area ratio is under PART_RATIO
    switches: float  # share of overlapping boxes (IoU >= SWITCH_IOU) whose label changed


def moved(box: Box, depth_m: np.ndarray, K: Intrinsics, T_cur_prev: np.ndarray) -> Box:
    """``box`` of the previous image moved into the current one: its centre, at the median depth of the box's
    middle half, goes where ``T_cur_prev`` takes it and its size scales by the depth's change; unmoved when the
    middle has no depth or the centre goes behind the camera."""
    x1, y1, x2, y2 = box
    u, v, hw, hh = (x1 + x2) / 2, (y1 + y2) / 2, (x2 - x1) / 2, (y2 - y1) / 2
    rows = slice(max(int(v - hh / 2), 0), max(int(v + hh / 2), 1))
    cols = slice(max(int(u - hw / 2), 0), max(int(u + hw / 2), 1))
    middle = depth_m[rows, cols]
    middle = middle[np.isfinite(middle) & (middle > 0)]
    if len(middle) == 0:
        return box
    z = float(np.median(middle))
    p = T_cur_prev[:3, :3] @ np.array([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z]) + T_cur_prev[:3, 3]
    if p[2] < 0.1:
        return box
    su, sv, scale = K.fx * p[0] / p[2] + K.cx, K.fy * p[1] / p[2] + K.cy, z / p[2]
    return (su - scale * hw, sv - scale * hh, su + scale * hw, sv + scale * hh)


def stability(frames: Iterable[tuple[Sequence[Detection], Sequence[Detection]]], width: int, height: int) -> Stability:
    """The statistics above over frames given as (their detections, the previous frame's ``moved`` into them)."""
    changes: list[float] = []
    pairs = parts = overlapping = switched = count = 0
    lo, hi = np.full(4, BORDER_PX), np.array([np.inf, np.inf, width - BORDER_PX, height - BORDER_PX])
    for dets, previous in frames:
        count += 1
        if not dets or not previous:
            continue
        overlap = box_iou([d.box for d in dets], [p.box for p in previous])
        same = np.array([[d.label == p.label for p in previous] for d in dets])
        for i, d in enumerate(dets):
            mine = np.where(same[i], overlap[i], 0.0)
            j = int(np.argmax(mine))
            if mine[j] >= SWITCH_IOU or np.where(same[i], 0.0, overlap[i]).max() >= SWITCH_IOU:
                overlapping += 1
                switched += mine[j] < SWITCH_IOU
            if mine[j] < PAIR_IOU:
                continue
            pairs += 1
            a, b = np.asarray(d.box, float), np.asarray(previous[j].box, float)
            size = np.array([a[2] - a[0], a[3] - a[1]] * 2)
            keep = (a >= lo) & (a <= hi) & (b >= lo) & (b <= hi)  # sides the image border does not cut
            changes.extend(((a - b) / size)[keep].tolist())
            areas = sorted([size[0] * size[1], (b[2] - b[0]) * (b[3] - b[1])])
            parts += areas[0] < PART_RATIO * areas[1]
    side = np.asarray(changes)
    return Stability(
        frames=count,
        pairs=pairs,
        sides=len(side),
        robust_sd=float(1.4826 * np.median(np.abs(side - np.median(side)))) if len(side) else float("nan"),
        p90=float(np.percentile(np.abs(side), 90)) if len(side) else float("nan"),
        part_pairs=parts / pairs if pairs else float("nan"),
        switches=switched / overlapping if overlapping else float("nan"),
    )


def source_detections(
    spec: str, start: int, frames: int
) -> tuple[list[tuple[list[Detection], list[Detection]]], int, int]:
    """Frames ``start``.. of ``spec`` as (detections, the previous frame's moved into it by the true poses):
    its own detections when it has them (synthetic), else CenterNet's."""
    from perception.detector import Detector

    data = open_dataset(spec)
    truth = ground_truth_of(data)
    match = nearest_timestamps(data.timestamps, truth.timestamps, 0.01)  # -1: no pose (a pair is then skipped)
    detector: Detector | None = None
    out: list[tuple[list[Detection], list[Detection]]] = []
    width = height = 0
    previous: tuple[list[Detection], np.ndarray, np.ndarray] | None = None
    for i in range(start, min(start + frames, len(data))):
        frame = data.frame(i)
        height, width = frame.rgb.shape[:2]
        if frame.detections is None:
            detector = detector or Detector()
            dets = detector.detect(frame.rgb)
        else:
            dets = list(frame.detections)
        pose = truth.poses[match[i]] if match[i] >= 0 else None
        if previous is not None and pose is not None:
            T = inverse(pose) @ previous[2]
            K = frame.camera.color
            shifted = [replace(p, box=moved(p.box, previous[1], K, T)) for p in previous[0]]
            out.append((dets, shifted))
        previous = None if pose is None else (dets, frame.depth_m(), pose)
    return out, width, height


def run_box_stability(console: Console, specs: list[str], start: int, frames: int, write: Path | None) -> dict:
    header = [
        "source",
        "frames",
        "box pairs",
        "side change, robust sd",
        "side change, 90th percentile",
        "part box beside a whole one",
        "label switched",
    ]
    rows: list[list[object]] = []
    results = {}
    for spec in specs:
        dets, width, height = source_detections(spec, start, frames)
        s = stability(dets, width, height)
        results[spec] = s
        rows.append(
            [
                f"`{spec}`",
                s.frames,
                s.pairs,
                f"{100 * s.robust_sd:.1f} %",
                f"{100 * s.p90:.1f} %",
                f"{100 * s.part_pairs:.1f} %",
                f"{100 * s.switches:.1f} %",
            ]
        )
    show_table(console, "Detector boxes from frame to frame", header, rows)
    if write is not None:
        command = "objslam bench box-stability " + " ".join(f"--dataset '{s}'" for s in specs)
        command += f" --start {start} --frames {frames}"
        notes = (
            f"Frames {start}-{start + frames - 1} of each source; real sequences through the service's detector "
            f"(CenterNet, default thresholds), synthetic ones with their simulated detections. The previous frame's "
            f"boxes are moved into the current image by the true relative pose (each box's centre at its middle's "
            f"median depth, its size scaled by the depth's change), so the camera's motion is not counted; frames "
            f"without a true pose are skipped. A detection is paired "
            f"with the previous frame's box of its label that overlaps it most (IoU >= {PAIR_IOU}); side change = "
            f"the change of a box side not within {BORDER_PX:g} px of the image border, as a share of the box's "
            f"width (left, right) or height (top, bottom). Part box beside a whole one: pairs whose smaller box has "
            f"under {PART_RATIO:g} of the larger's area. Label switched: detections over a previous box (IoU >= "
            f"{SWITCH_IOU}) of another label and none of their own."
        )
        record(
            "box-stability", "Detector boxes from frame to frame", command, markdown_table(header, rows), notes, write
        )
    return results
