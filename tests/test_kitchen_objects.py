"""The hand-annotated object ground truth of the 7-Scenes kitchen (evaluation/data/7scenes_redkitchen_1000):
a valid file of plausible COCO boxes; on the real data, boxes that agree with the depth they were measured
from, that the measurement reproduces, and that ``objslam eval`` finds and scores in the right frame."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from evaluation.box_annotation import Box, View, complete, fit_box, outline_box, project, upright_frame
from evaluation.object_metrics import aligned_objects, object_scores
from evaluation.object_truth import bundled_object_truth, object_truth_for, per_object, read_object_truth
from perception.coco import COCO_CLASSES
from perception.frame import CameraModel, Intrinsics
from sources import open_dataset, truth_per_frame
from tests.conftest import REDKITCHEN, requires_redkitchen

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "evaluation" / "data" / "7scenes_redkitchen_1000"
GT = json.loads((DATA / "objects_gt.json").read_text())
ANNOTATION = json.loads((DATA / "annotation.json").read_text())
WIDTH, HEIGHT = 640, 480
SIZES = {  # label: (shorter horizontal side, longer horizontal side, height) ranges in metres
    "chair": ((0.35, 0.6), (0.4, 0.65), (0.7, 1.1)),
    "dining table": ((0.6, 1.2), (1.0, 2.6), (0.6, 0.8)),
    "cup": ((0.05, 0.12), (0.07, 0.16), (0.06, 0.15)),
    "book": ((0.12, 0.3), (0.18, 0.35), (0.005, 0.06)),
    "tv": ((0.03, 0.15), (0.5, 1.3), (0.3, 0.8)),
}


def _boxes() -> dict[int, Box]:
    return {o["id"]: Box(np.asarray(o["center"]), np.asarray(o["size"]), o["yaw"]) for o in GT["objects"]}


def _script():
    spec = importlib.util.spec_from_file_location("annotate_kitchen", ROOT / "scripts" / "annotate_kitchen.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_annotation_is_valid_coco_boxes_of_plausible_sizes():
    assert [o["id"] for o in GT["objects"]] == [o["id"] for o in ANNOTATION["objects"]]
    assert len({o["id"] for o in GT["objects"]}) == len(GT["objects"])
    counts = {label: sum(o["label"] == label for o in GT["objects"]) for label in SIZES}
    assert counts == {"chair": 5, "dining table": 1, "cup": 2, "book": 2, "tv": 2}
    for o, a in zip(GT["objects"], ANNOTATION["objects"], strict=True):
        assert o["label"] == a["label"] and o["label"] in COCO_CLASSES
        short, long_, height = SIZES[o["label"]]
        sides = sorted(o["size"][:2])
        assert short[0] <= sides[0] <= short[1] and long_[0] <= sides[1] <= long_[1], o
        assert height[0] <= o["size"][2] <= height[1], o
        assert len(a["views"]) >= 3, f"object {o['id']} is measured from fewer than three views"
        for view in a["views"]:
            poly = np.asarray([p[:2] for p in view["polygon"]], float)
            assert len(poly) >= 3 and 0 <= view["frame"] < 1000
            assert poly[:, 0].min() >= 0 and poly[:, 0].max() <= WIDTH and poly[:, 1].min() >= 0
            assert poly[:, 1].max() <= HEIGHT and cv2.contourArea(poly.astype(np.float32)) > 50


def test_the_boxes_frame_is_a_rotation_and_the_objects_stand_on_their_supports():
    R = np.asarray(GT["box_frame_from_world"])
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
    assert GT["floor_tilt_from_gravity_deg"] < 3.0  # the measured floor against gravity-direction.txt
    boxes, floor = _boxes(), GT["floor_z"]
    table_top = boxes[1].center[2] + boxes[1].size[2] / 2
    for entry in ANNOTATION["objects"]:
        bottom = boxes[entry["id"]].center[2] - boxes[entry["id"]].size[2] / 2
        on = entry.get("on", "floor")
        if on == "floor":
            assert bottom == pytest.approx(floor, abs=2e-3), entry["id"]
        elif on == 1:
            assert bottom == pytest.approx(table_top, abs=2e-3), entry["id"]
    assert 0.6 < table_top - floor < 0.8
    for a in (2, 3, 4, 5, 6):  # chairs stand apart: their footprint centres are over 0.4 m apart
        for b in (2, 3, 4, 5, 6):
            assert a == b or np.linalg.norm(boxes[a].center[:2] - boxes[b].center[:2]) > 0.4


def test_box_fitting_completion_and_outline_on_a_known_box():
    rng = np.random.default_rng(0)
    yaw = 0.4
    c, s = np.cos(yaw), np.sin(yaw)
    local = rng.uniform(-0.5, 0.5, (4000, 3)) * [0.6, 0.3, 0.8]
    points = local @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) + [1.0, 2.0, 0.4]
    box = fit_box(points, bottom=0.0)
    assert box.size == pytest.approx([0.6, 0.3, 0.8], abs=0.02) and box.center[:2] == pytest.approx(
        [1.0, 2.0], abs=0.01
    )
    assert np.cos(2 * (box.yaw - yaw)) > 0.999  # the same axes (a box's yaw is defined modulo 90 degrees)
    grown = complete(Box(np.array([0.0, 0.0, 0.5]), np.array([0.4, 0.1, 1.0]), 0.0), 1, 0.5, np.array([0.0, -3.0]))
    assert grown.size[1] == 0.5 and grown.center[1] == pytest.approx(-0.2)  # the face at y = +0.05 is kept
    assert grown.contains(np.array([[0.0, 0.04, 0.5], [0.0, -0.44, 0.5]])).all()
    # a 1 x 0.5 m panel in the plane y = 2, seen from the origin: its outline's rays cut with that plane
    camera = CameraModel(Intrinsics(500.0, 500.0, 320.0, 240.0), WIDTH, HEIGHT, 1000.0)
    pose = np.eye(4)
    pose[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # camera z along world y, image down = -z
    corners = np.array([[-0.5, 2.0, -0.25], [0.5, 2.0, -0.25], [0.5, 2.0, 0.25], [-0.5, 2.0, 0.25]])
    polygon = project(corners, pose, camera)[:, :2]
    view = View(0, np.full((HEIGHT, WIDTH), np.nan), pose, polygon)
    panel = outline_box([view], camera, np.eye(3), np.c_[rng.uniform(-0.5, 0.5, 200), np.full(200, 2.0), np.zeros(200)])
    assert panel.size[[0, 2]] == pytest.approx([1.0, 0.5], abs=1e-6) and panel.center == pytest.approx(
        [0, 2, 0], abs=1e-6
    )
    assert upright_frame(np.array([0.0, 0.0, 1.0])) == pytest.approx(np.eye(3))


def test_an_annotation_file_with_a_frame_moves_the_mapped_objects_into_it(tmp_path):
    truth = read_object_truth(DATA / "objects_gt.json")
    assert len(truth.objects) == 12 and truth.names[11] == "left wall monitor"
    R = truth.box_frame_from_world[:3, :3]
    entries = [  # the true boxes as a map in the dataset's world frame would hold them
        {
            "id": 100 + t.id,
            "label": t.label,
            "mean": list(R.T @ np.asarray(t.center)),
            "cov": np.diag([1e-4] * 3).tolist(),
        }
        for t in truth.objects
    ]
    mapped = aligned_objects(entries, truth.box_frame_from_world)
    scores = object_scores(mapped, truth.objects, 1.5)
    assert scores["matched"] == 12 and scores["false"] == 0 and scores["median_centroid_error_m"] < 1e-6
    rows = per_object(mapped, truth, 1.5, entries)
    assert [r["mapped"] for r in rows["true"]] == [100 + t.id for t in truth.objects] and rows["false"] == []
    assert object_scores(aligned_objects(entries, np.eye(4)), truth.objects, 1.5)["matched"] < 12  # frame matters
    plain = tmp_path / "objects_gt.json"  # the synthetic scenes' format: a list, in the world frame
    plain.write_text(json.dumps([{"id": 1, "label": "cup", "center": [1, 2, 0.1], "size": [0.1, 0.1, 0.1]}]))
    listed = read_object_truth(plain)
    assert listed.objects[0].yaw == 0.0 and np.array_equal(listed.box_frame_from_world, np.eye(4))


@requires_redkitchen
def test_the_boxes_hold_the_depth_of_their_marked_pixels():
    """In every marked view, the median of the polygon's back-projected depth pixels lies in the box (3 cm), and
    the box, projected with the reference pose, covers most of the polygon."""
    from evaluation.box_annotation import registered_depth, view_points

    dataset = open_dataset(str(REDKITCHEN))
    poses = truth_per_frame(dataset)
    R = np.asarray(GT["box_frame_from_world"])
    boxes = _boxes()
    for entry in ANNOTATION["objects"]:
        box = boxes[entry["id"]]
        for v in entry["views"]:
            depth = registered_depth(dataset.frame(v["frame"]).depth_m(), dataset.camera)
            polygon = np.asarray([p[:2] for p in v["polygon"]], float)
            points = view_points(View(v["frame"], depth, poses[v["frame"]], polygon), dataset.camera) @ R.T
            assert len(points) > 100, (entry["id"], v["frame"])
            assert box.contains(np.median(points, axis=0)[None], margin=0.03)[0], (entry["id"], v["frame"])
            corners = project(box.corners() @ R, poses[v["frame"]], dataset.camera)[:, :2]
            hull = np.zeros((HEIGHT, WIDTH), np.uint8)
            cv2.fillConvexPoly(hull, cv2.convexHull(np.rint(corners).astype(np.int32)), 1)
            marked = np.zeros_like(hull)
            cv2.fillPoly(marked, [np.rint(polygon).astype(np.int32)], 1)
            covered = (hull & marked).sum() / marked.sum()
            assert covered > 0.8, (entry["id"], v["frame"], covered)


@requires_redkitchen
def test_the_measurement_reproduces_the_file_and_eval_finds_it_by_the_reference_trajectory(tmp_path):
    script = _script()
    dataset = open_dataset(str(REDKITCHEN))
    frames = script.Frames(dataset)
    R, floor = script.upright(ANNOTATION, frames, np.loadtxt(REDKITCHEN / "gravity-direction.txt"))
    measured, _ = script.measure(ANNOTATION, frames, R, floor)
    assert np.allclose(measured["box_frame_from_world"], GT["box_frame_from_world"], atol=1e-6)
    for new, old in zip(measured["objects"], GT["objects"], strict=True):
        assert new["label"] == old["label"]
        assert np.allclose(
            new["center"] + new["size"] + [new["yaw"]], old["center"] + old["size"] + [old["yaw"]], atol=2e-3
        )
    found = bundled_object_truth(dataset)
    assert found is not None and found.source.endswith("7scenes_redkitchen_1000/objects_gt.json")
    assert object_truth_for(dataset) is not None
    teddy = REDKITCHEN.parent / "tum_fr3_teddy_200"
    if teddy.is_dir():
        assert bundled_object_truth(open_dataset(str(teddy))) is None


@requires_redkitchen
def test_eval_scores_a_run_directory_against_the_annotation(tmp_path):
    """A run whose trajectory is the reference and whose objects are the true boxes (in the dataset's world
    frame, shifted 2 cm) scores 12 of 12 matched, none false, 2 cm centroid error, in the eval report."""
    from service.evaluate import evaluate_run

    truth = read_object_truth(DATA / "objects_gt.json")
    R = truth.box_frame_from_world[:3, :3]
    shift = np.array([0.02, 0.0, 0.0])
    objects = [
        {
            "id": t.id,
            "label": t.label,
            "mean": list(R.T @ (np.asarray(t.center) + shift)),
            "cov": (R.T @ np.diag(np.square(np.asarray(t.size)) / 12) @ R).tolist(),
        }
        for t in truth.objects
    ]
    (tmp_path / "objects.json").write_text(json.dumps(objects))
    (tmp_path / "trajectory.tum").write_text((REDKITCHEN / "groundtruth.txt").read_text())
    section = evaluate_run(tmp_path, str(REDKITCHEN))
    scores = json.loads((tmp_path / "metrics.json").read_text())["objects"]
    assert scores["ground_truth"] == 12 and scores["matched"] == 12 and scores["false"] == 0
    assert scores["median_centroid_error_m"] == pytest.approx(0.02, abs=1e-3) and scores["mean_iou"] > 0.5
    assert "left wall monitor" in section and scores["truth"].endswith("objects_gt.json")
    other = tmp_path / "other.json"
    other.write_text(json.dumps([{"id": 1, "label": "cup", "center": [9.0, 9.0, 9.0], "size": [0.1, 0.1, 0.1]}]))
    evaluate_run(tmp_path, str(REDKITCHEN), other)
    scores = json.loads((tmp_path / "metrics.json").read_text())["objects"]
    assert scores["ground_truth"] == 1 and scores["matched"] == 0 and scores["false"] == 12
