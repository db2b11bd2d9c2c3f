"""Measure the hand-annotated object boxes of a real sequence from its marked pixels, depth and reference poses.

Usage:
  python scripts/annotate_kitchen.py [DATASET] [--annotation FILE] [--out FILE] [--overlays DIR]
                                     [--check-frames 0,100,...] [--only ID,...]

DATASET defaults to ../shared/data/7scenes_redkitchen_1000 beside the repository, the annotation to
evaluation/data/7scenes_redkitchen_1000/annotation.json (the polygons marked by hand, per object and frame)
and the output to objects_gt.json beside it. The method is evaluation/data/7scenes_redkitchen_1000/README.md;
the measuring functions are evaluation/box_annotation.py. ``--overlays DIR`` also draws every box into each
marked frame and into the ``--check-frames`` (the object's kept points in green on its own marked frames),
which is how the annotation was checked.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evaluation.box_annotation import (  # noqa: E402
    BOX_EDGES,
    Box,
    View,
    carve,
    complete,
    fit_box,
    floor_plane,
    largest_component,
    outline_box,
    project,
    registered_depth,
    upright_frame,
    view_points,
)
from sources import open_dataset, truth_per_frame  # noqa: E402
from sources.base import Dataset  # noqa: E402

DATA = ROOT / "evaluation" / "data" / "7scenes_redkitchen_1000"
DATASET = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_1000"
SUPPORT_CLEARANCE = 0.02  # points this close above the supporting plane belong to it, not to the object


class Frames:
    """Registered depth and reference pose of the dataset's frames, each read once."""

    def __init__(self, dataset: Dataset):
        self.dataset = dataset
        self.poses = truth_per_frame(dataset)
        self._depth: dict[int, np.ndarray] = {}

    def view(self, frame: int, polygon) -> View:
        if frame not in self._depth:
            self._depth[frame] = registered_depth(self.dataset.frame(frame).depth_m(), self.dataset.camera)
        vertices = [(float(p[0]), float(p[1])) for p in polygon]
        cut = np.array([len(p) > 2 and p[2] == 0 for p in polygon])  # [u, v, 0]: not on the outline
        return View(frame, self._depth[frame], self.poses[frame], np.array(vertices), cut)


def upright(annotation: dict, frames: Frames, gravity: np.ndarray) -> tuple[np.ndarray, float]:
    """(rotation from the world frame to the upright frame of the measured floor, the floor's height there)."""
    camera = frames.dataset.camera
    points = np.concatenate([view_points(frames.view(v["frame"], v["polygon"]), camera) for v in annotation["floor"]])
    up, height = floor_plane(points, gravity)
    return upright_frame(up), height


def dependencies(entry: dict) -> set[int]:
    """The ids of the objects ``entry`` is measured from: what it stands on, its plane, its completions' targets."""
    refs = [entry.get("on"), entry.get("plane_of"), *(g["toward"] for g in entry.get("complete", []))]
    return {r for r in refs if isinstance(r, int)}


def measure_object(entry: dict, frames: Frames, R: np.ndarray, floor: float, boxes: dict, kept: dict):
    """(box, kept upright-frame points) of one annotated object; ``boxes`` / ``kept``: the objects before it."""
    camera = frames.dataset.camera
    views = [frames.view(v["frame"], v["polygon"]) for v in entry["views"]]
    if entry.get("carve", True):
        points = carve(views, camera) @ R.T
    else:  # too few views agree on the depth (a screen at the image border): the polygons' union
        points = np.concatenate([view_points(v, camera) for v in views]) @ R.T
    on = entry.get("on", "floor")  # "floor", the id of the object it stands on, or null (it hangs)
    bottom = None if on is None else floor if on == "floor" else float(boxes[on].center[2] + boxes[on].size[2] / 2)
    if bottom is not None:
        points = points[points[:, 2] > bottom + entry.get("clearance", SUPPORT_CLEARANCE)]
    points = largest_component(points)
    if entry.get("outline"):  # sparse depth (a screen): its plane from the depth, its extents from the outline
        box = outline_box(views, camera, R, kept[entry["plane_of"]] if "plane_of" in entry else points)
    else:
        box = fit_box(points, bottom, entry.get("yaw_from", "footprint"), entry.get("top", "max"))
    for grow in entry.get("complete", []):  # sides no depth reached, towards a point or an object's centre
        toward = grow["toward"]
        target = boxes[toward].center if isinstance(toward, int) else np.asarray(toward, float)
        box = complete(box, grow["axis"], grow["length"], target)
    return box, points


def measure(annotation: dict, frames: Frames, R: np.ndarray, floor: float, only: set[int] | None = None):
    """(the ground-truth file's content, the kept upright-frame points by object id). Objects are measured in
    the annotation's order; what one depends on (``dependencies``) must come before it."""
    entries = annotation["objects"]
    wanted = {e["id"] for e in entries} if not only else set(only)
    for entry in reversed(entries):
        if entry["id"] in wanted:
            wanted |= dependencies(entry)
    boxes: dict[int, Box] = {}
    kept: dict[int, np.ndarray] = {}
    objects = []
    for entry in entries:
        if entry["id"] not in wanted:
            continue
        box, points = measure_object(entry, frames, R, floor, boxes, kept)
        boxes[entry["id"]], kept[entry["id"]] = box, points
        objects.append(
            {
                "id": entry["id"],
                "label": entry["label"],
                "center": [round(float(x), 3) for x in box.center],
                "size": [round(float(x), 3) for x in box.size],
                "yaw": round(float(box.yaw), 3),
                "name": entry.get("name", ""),
                "frames": [v["frame"] for v in entry["views"]],
                "points": len(points),
            }
        )
    gt = frames.dataset.ground_truth
    assert gt is not None
    result = {
        "dataset": annotation["dataset"],
        "frame": "upright: z along the measured floor normal, boxes' yaw about it; p = box_frame_from_world @ p_world",
        "box_frame_from_world": [[round(float(x), 9) for x in row] for row in R],
        "floor_z": round(floor, 3),
        "fingerprint": {
            "poses": len(gt.poses),
            "first_position": [round(float(x), 4) for x in gt.poses[0, :3, 3]],
            "last_position": [round(float(x), 4) for x in gt.poses[-1, :3, 3]],
        },
        "objects": sorted(objects, key=lambda o: o["id"]),
    }
    return result, kept


def draw(rgb: np.ndarray, boxes: list[dict], pose: np.ndarray, R: np.ndarray, frames: Frames) -> np.ndarray:
    out = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    for o in boxes:
        box = Box(np.asarray(o["center"]), np.asarray(o["size"]), o["yaw"])
        px = project(box.corners() @ R, pose, frames.dataset.camera)
        if (px[:, 2] < 0.1).any():
            continue
        colour = tuple(int(c) for c in np.random.default_rng(o["id"]).integers(60, 255, 3))
        for a, b in BOX_EDGES:
            cv2.line(out, tuple(np.int32(px[a, :2])), tuple(np.int32(px[b, :2])), colour, 2, cv2.LINE_AA)
        top = px[np.argmin(px[:, 1]), :2]
        cv2.putText(out, f"{o['id']}:{o['label']}", (int(top[0]), int(top[1]) - 3), 0, 0.5, colour, 2)
    return out


def overlays(result: dict, kept: dict, annotation: dict, frames: Frames, R: np.ndarray, out: Path, check) -> None:
    out.mkdir(parents=True, exist_ok=True)
    boxes = result["objects"]
    camera = frames.dataset.camera
    for entry in annotation["objects"]:
        if entry["id"] not in kept:
            continue
        for v in entry["views"]:
            img = draw(
                frames.dataset.frame(v["frame"]).rgb,
                [o for o in boxes if o["id"] == entry["id"]],
                frames.poses[v["frame"]],
                R,
                frames,
            )
            px = project(kept[entry["id"]] @ R, frames.poses[v["frame"]], camera)
            for u, vv in np.int32(px[::3, :2]):
                if 0 <= u < img.shape[1] and 0 <= vv < img.shape[0]:
                    img[vv, u] = (0, 255, 0)
            cv2.polylines(img, [np.int32([p[:2] for p in v["polygon"]])], True, (255, 255, 0), 1)
            cv2.imwrite(str(out / f"object{entry['id']:02d}_frame{v['frame']:04d}.png"), img)
    for i in check:
        cv2.imwrite(
            str(out / f"all_frame{i:04d}.png"), draw(frames.dataset.frame(i).rgb, boxes, frames.poses[i], R, frames)
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", nargs="?", default=str(DATASET))
    p.add_argument("--annotation", default=str(DATA / "annotation.json"))
    p.add_argument("--out", default=str(DATA / "objects_gt.json"))
    p.add_argument("--overlays", default=None)
    p.add_argument("--check-frames", default="0,100,150,250,300,400,450,550,650,750,850,950")
    p.add_argument("--only", default="", help="measure only these object ids (and what they stand on)")
    args = p.parse_args()
    dataset = open_dataset(args.dataset)
    annotation = json.loads(Path(args.annotation).read_text())
    gravity = np.loadtxt(Path(args.dataset) / "gravity-direction.txt")
    frames = Frames(dataset)
    R, height = upright(annotation, frames, gravity)
    only = {int(x) for x in args.only.split(",") if x}
    result, kept = measure(annotation, frames, R, height, only or None)
    tilt = np.degrees(np.arccos(np.clip(-R[2] @ gravity / np.linalg.norm(gravity), -1, 1)))
    result["floor_tilt_from_gravity_deg"] = round(float(tilt), 2)
    print(f"floor normal {np.round(R[2], 4)} ({tilt:.2f} deg from gravity-direction.txt), height {height:.3f} m")
    if not only:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    for o in result["objects"]:
        print(
            f"{o['id']:3d} {o['label']:13s} centre {o['center']} size {o['size']} yaw {o['yaw']:+.3f} "
            f"({o['points']} points, frames {o['frames']})"
        )
    if args.overlays:
        check = [int(x) for x in args.check_frames.split(",") if x]
        overlays(result, kept, annotation, frames, R, Path(args.overlays), check)


if __name__ == "__main__":
    main()
