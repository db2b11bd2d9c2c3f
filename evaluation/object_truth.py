"""Which object ground truth ``objslam eval`` scores a run against, and in which frame.

A dataset's own ``objects_gt.json`` (the synthetic scenes) is a list of boxes in the dataset's world frame. A
hand annotation kept in the repository (``evaluation/data/<dataset>/objects_gt.json``, e.g. the 7-Scenes
kitchen, whose data folder is read-only) is an object with the boxes under ``objects`` and the rotation
``box_frame_from_world`` from the dataset's world frame into the upright frame the boxes are in (ground-plane
IoU needs z up); it is found by the dataset's reference trajectory (``fingerprint``: its pose count and first
and last positions), so a renamed copy of the data still finds it. ``--objects-gt FILE`` names one directly.

``per_object`` lists what became of each true object and each mapped one, for the report.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.object_metrics import ellipse_box_iou, match_objects
from sources import Dataset, DatasetError, ObjectTruth

BUNDLED = Path(__file__).resolve().parent / "data"
FINGERPRINT_TOL_M = 1e-3


@dataclass(frozen=True)
class ObjectGroundTruth:
    """True boxes, the 4x4 transform from the dataset's world frame into their frame, names, and the source."""

    objects: list[ObjectTruth]
    box_frame_from_world: np.ndarray
    names: dict[int, str]
    source: str


def read_object_truth(path: Path) -> ObjectGroundTruth:
    """An ``objects_gt.json``: a list of boxes (world frame), or an annotation with a frame (see module doc)."""
    try:
        content = json.loads(Path(path).read_text())
        items = content["objects"] if isinstance(content, dict) else content
        frame = np.eye(4)
        if isinstance(content, dict) and "box_frame_from_world" in content:
            frame[:3, :3] = np.asarray(content["box_frame_from_world"], float).reshape(3, 3)
        objects = [
            ObjectTruth(int(o["id"]), str(o["label"]), _triple(o["center"]), _triple(o["size"]), float(o.get("yaw", 0)))
            for o in items
        ]
        names = {int(o["id"]): str(o.get("name", "")) for o in items}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"cannot read object ground truth {path}: {exc}") from None
    return ObjectGroundTruth(objects, frame, names, str(path))


def bundled_object_truth(dataset: Dataset, root: Path = BUNDLED) -> ObjectGroundTruth | None:
    """The repository's annotation whose fingerprint matches ``dataset``'s reference trajectory, if any."""
    gt = dataset.ground_truth
    if gt is None or len(gt.poses) == 0:
        return None
    for path in sorted(root.glob("*/objects_gt.json")):
        try:
            fingerprint = json.loads(path.read_text()).get("fingerprint", {})
            if (
                int(fingerprint["poses"]) == len(gt.poses)
                and np.allclose(fingerprint["first_position"], gt.poses[0, :3, 3], atol=FINGERPRINT_TOL_M)
                and np.allclose(fingerprint["last_position"], gt.poses[-1, :3, 3], atol=FINGERPRINT_TOL_M)
            ):
                return read_object_truth(path)
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
    return None


def object_truth_for(dataset: Dataset, objects_gt: Path | None = None) -> ObjectGroundTruth | None:
    """``objects_gt`` when given, else the dataset's own ``objects_gt.json``, else a bundled annotation."""
    if objects_gt is not None:
        return read_object_truth(objects_gt)
    own = dataset.objects
    if own:
        return ObjectGroundTruth(own, np.eye(4), {}, f"{dataset.name}/objects_gt.json")
    return bundled_object_truth(dataset)


def per_object(
    objects: list, truth: ObjectGroundTruth, axis_scale: float, entries: list[dict]
) -> dict[str, list[dict[str, Any]]]:
    """Each true object with the mapped one matched to it (``match_objects``: its id, centroid error and its
    components in the boxes' frame, IoU), and each unmatched mapped object with the nearest true object (what
    it may duplicate or be mistaken for). ``entries``: the ``objects.json`` entries ``objects`` come from."""
    ids = [e.get("id", i) for i, e in enumerate(entries)]
    matches = {b: a for a, b in match_objects(objects, truth.objects)}
    true_rows = []
    for b, t in enumerate(truth.objects):
        row: dict[str, Any] = {"id": t.id, "label": t.label, "name": truth.names.get(t.id, ""), "mapped": None}
        if b in matches:
            o = objects[matches[b]]
            row.update(
                mapped=ids[matches[b]],
                centroid_error_m=float(np.linalg.norm(o.mean - np.asarray(t.center))),
                error_xyz_m=[float(x) for x in o.mean - np.asarray(t.center)],
                iou=ellipse_box_iou(o.mean, o.cov, axis_scale, t),
            )
        true_rows.append(row)
    false_rows = []
    matched = set(matches.values())
    for a, o in enumerate(objects):
        if a in matched:
            continue
        d = [float(np.linalg.norm(o.mean - np.asarray(t.center))) for t in truth.objects]
        near = int(np.argmin(d)) if d else -1
        false_rows.append(
            {
                "mapped": ids[a],
                "label": o.label,
                "nearest_true": truth.objects[near].id if d else None,
                "nearest_label": truth.objects[near].label if d else None,
                "distance_m": d[near] if d else None,
            }
        )
    return {"true": true_rows, "false": false_rows}


def per_object_markdown(rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    """Report lines: a table of the true objects and one of the false mapped ones."""
    lines = [
        "",
        "| true object | label | mapped as | centroid error (m) | error x, y, z (m) | IoU |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows["true"]:
        if r["mapped"] is None:
            lines.append(f"| {r['id']} {r['name']} | {r['label']} | - | - | - | - |")
        else:
            xyz = ", ".join(f"{x:+.3f}" for x in r["error_xyz_m"])
            lines.append(
                f"| {r['id']} {r['name']} | {r['label']} | {r['mapped']} | {r['centroid_error_m']:.3f} | "
                f"{xyz} | {r['iou']:.2f} |"
            )
    if rows["false"]:
        lines += ["", "| false mapped object | label | nearest true object | distance (m) |", "|---|---|---|---|"]
        for r in rows["false"]:
            near = "-" if r["nearest_true"] is None else f"{r['nearest_true']} ({r['nearest_label']})"
            dist = "-" if r["distance_m"] is None else f"{r['distance_m']:.2f}"
            lines.append(f"| {r['mapped']} | {r['label']} | {near} | {dist} |")
    return lines


def _triple(values) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return x, y, z
