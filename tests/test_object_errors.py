"""Per-object error vectors of ``objslam eval``: in the world, in the viewing cameras' frames, along the rays."""

from __future__ import annotations

import json

import numpy as np

from evaluation.object_metrics import MappedObject, error_summary, error_vectors, viewing_poses
from perception.camera import Intrinsics
from service.evaluate import evaluate_run
from service.outputs import tum_text
from sources import Trajectory, open_dataset
from sources.base import ObjectTruth
from sources.scene import look_rotation

K = Intrinsics(100.0, 100.0, 49.5, 39.5)
SPEC = "synthetic:room?seed=1&frames=60&width=160&height=120"


def camera_at(position: tuple[float, float, float], yaw: float) -> np.ndarray:
    """A level camera-to-world pose at ``position`` looking along heading ``yaw``."""
    T = np.eye(4)
    T[:3, :3] = look_rotation(np.array([yaw]), np.zeros(1), np.zeros(1))[0]
    T[:3, 3] = position
    return T


def test_viewing_poses_are_those_whose_image_holds_the_centre_else_the_nearest() -> None:
    poses = np.stack(
        [
            camera_at((0.0, 0.0, 1.0), 0.0),  # looks at it along +x, 2 m away
            camera_at((0.0, 0.0, 1.0), np.pi),  # turned away
            camera_at((0.0, 0.0, 1.0), np.pi / 2),  # it is 90 degrees to the side, out of the frame
            camera_at((-6.0, 0.0, 1.0), 0.0),  # in the frame but 8 m away
        ]
    )
    centre = np.array([2.0, 0.0, 1.0])
    assert viewing_poses(centre, poses, K, 100, 80).tolist() == [0]
    assert viewing_poses(centre, poses[1:], K, 100, 80).tolist() == [0]  # none sees it: the nearest


def test_error_vectors_in_the_world_the_camera_and_along_the_ray() -> None:
    truth = [ObjectTruth(7, "cup", (2.0, 0.0, 1.0), (0.1, 0.1, 0.1), 0.0)]
    poses = np.stack([camera_at((0.0, 0.0, 1.0), 0.0)])  # camera x = world -y, y = -z, z = +x
    offset = np.array([-0.05, 0.02, 0.01])  # 5 cm towards the camera, 2 cm to its left, 1 cm up
    mapped = [MappedObject("cup", np.asarray(truth[0].center) + offset, None, 3)]
    (e,) = error_vectors(mapped, truth, poses, K, 100, 80)
    assert e["truth_id"] == 7 and e["id"] == 3 and e["label"] == "cup" and e["views"] == 1
    assert np.allclose(e["world_m"], offset) and np.isclose(e["error_m"], np.linalg.norm(offset))
    assert np.allclose(e["camera_m"], [-0.02, -0.01, -0.05])
    assert np.isclose(e["along_ray_m"], -0.05) and np.isclose(e["across_ray_m"], np.hypot(0.02, 0.01))
    summary = error_summary([e, {**e, "world_m": [0.0, 0.0, 0.0], "camera_m": [0.0, 0.0, 0.0], "along_ray_m": 0.0}])
    assert np.allclose(summary["mean_world_error_m"], offset / 2) and np.isclose(summary["median_along_ray_m"], -0.025)
    assert error_summary([])["median_along_ray_m"] is None


def test_an_offset_seen_from_all_sides_averages_out_along_the_rays_but_not_in_the_world() -> None:
    truth = [ObjectTruth(1, "chair", (0.0, 0.0, 0.45), (0.5, 0.5, 0.9), 0.0)]
    angles = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    poses = np.stack([camera_at((-2.0 * np.cos(a), -2.0 * np.sin(a), 0.45), a) for a in angles])
    offset = np.array([0.1, 0.0, 0.0])
    (e,) = error_vectors([MappedObject("chair", np.asarray(truth[0].center) + offset)], truth, poses, K, 100, 80)
    assert e["views"] == 8 and np.allclose(e["world_m"], offset) and abs(e["along_ray_m"]) < 1e-12
    assert np.isclose(e["across_ray_m"], 0.05)  # the mean across-ray part: half the offset (cos^2 averages 1/2)


def test_eval_writes_each_object_s_error_vector_and_their_common_part(tmp_path) -> None:
    data = open_dataset(SPEC)
    gt = data.ground_truth
    assert gt is not None and data.objects
    (tmp_path / "trajectory.tum").write_text(tum_text(Trajectory(gt.timestamps, gt.poses)))
    offset = np.array([0.03, -0.02, 0.01])
    entries = [
        {"id": 100 + t.id, "label": t.label, "mean": list(np.asarray(t.center) + offset), "cov": np.eye(3).tolist()}
        for t in data.objects
    ]
    (tmp_path / "objects.json").write_text(json.dumps(entries))
    section = evaluate_run(tmp_path, SPEC)
    objects = json.loads((tmp_path / "metrics.json").read_text())["objects"]
    rows = objects["per_object"]
    assert len(rows) == len(data.objects) == objects["matched"]
    assert all(r["id"] == 100 + r["truth_id"] and np.allclose(r["world_m"], offset, atol=1e-6) for r in rows)
    # a mean of the offset turned into each view's frame: no longer than the offset
    assert all(r["views"] >= 1 and np.linalg.norm(r["camera_m"]) <= np.linalg.norm(offset) + 1e-9 for r in rows)
    assert np.allclose(objects["mean_world_error_m"], offset, atol=1e-6)
    assert "| true id | label | error (m) | world dx, dy, dz (m)" in section
    assert "| all | | | mean +0.030, -0.020, +0.010 |" in section
    assert section.count("\n| ") >= len(rows) + 4  # the scores' table and one row per matched object
