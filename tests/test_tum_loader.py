"""TUM-format directories: index files, association, camera.json, odometry and detections; 7-Scenes quirks."""

from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pytest

from graph.trajectory import nearest_timestamps
from service.config import load_settings
from sources import DatasetError, open_dataset
from tests.conftest import REDKITCHEN, requires_redkitchen


def _write_tum(root, n=5, camera=True, odometry=True, detections=True):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines, odo_lines, det_lines = [], [], [], []
    for i in range(n):
        t = 100.0 + i * 0.033
        img = np.full((48, 64, 3), i * 10, np.uint8)
        depth = np.full((48, 64), 5000 + i, np.uint16)
        depth[0, 0] = 65535
        cv2.imwrite(str(root / f"rgb/{i}.png"), img)
        cv2.imwrite(str(root / f"depth/{i}.png"), depth)
        rgb_lines.append(f"{t:.6f} rgb/{i}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{i}.png")  # depth stamped slightly later, as in TUM
        odo_lines.append(f"{t:.6f} {0.1 * i} 0 0 0 0 0 1")
        det_lines.append(json.dumps({"t": t, "detections": [{"label": "cup", "score": 0.8, "box": [1, 2, 10, 20]}]}))
    (root / "rgb.txt").write_text("# rgb\n" + "\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("# depth\n" + "\n".join(depth_lines) + "\n")
    if odometry:
        (root / "odometry.txt").write_text("\n".join(odo_lines) + "\n")
    if detections:
        (root / "detections.jsonl").write_text("\n".join(det_lines[:-1]) + "\n")  # last frame: none
    if camera:
        (root / "camera.json").write_text(
            json.dumps({"fx": 50, "fy": 51, "cx": 32, "cy": 24, "width": 64, "height": 48, "depth_scale": 1000})
        )


def test_nearest_timestamps_picks_nearest_within_tolerance():
    a = np.array([0.0, 1.0, 2.0, 5.0])
    b = np.array([0.005, 0.99, 2.5, 4.999, 1.02])
    np.testing.assert_array_equal(nearest_timestamps(a, b, 0.02), [0, 1, -1, 3])


def test_tum_directory_with_extensions_loads_frames_odometry_and_detections(tmp_path):
    _write_tum(tmp_path)
    ds = open_dataset(str(tmp_path))
    assert len(ds) == 5 and ds.frame(0).odometry is not None
    f = ds.frame(2)
    assert f.camera.depth_scale == 1000 and f.camera.color.fy == 51 and f.camera.registered
    assert f.rgb.shape == (48, 64, 3) and f.depth.dtype == np.uint16
    assert f.depth[0, 0] == 0  # 65535 marks invalid and is normalised to 0
    assert f.depth_m()[1, 1] == pytest.approx(5.002)
    np.testing.assert_allclose(f.odometry[:3, 3], [0.2, 0, 0])
    assert f.detections[0].label == "cup" and f.detections[0].box == (1, 2, 10, 20)
    assert ds.frame(4).detections == []  # a detections file is present: frames without a line have none
    assert ds.ground_truth is None


def test_views_drop_the_odometry_or_replace_it_with_the_ground_truth(tmp_path):
    from sources import TruthAsOdometry, WithoutOdometry

    _write_tum(tmp_path)
    with pytest.raises(DatasetError, match="no ground truth"):
        TruthAsOdometry(open_dataset(str(tmp_path)))
    (tmp_path / "groundtruth.txt").write_text(
        "".join(f"{100.0 + i * 0.033:.6f} 0 {0.5 * i} 0 0 0 0 1\n" for i in range(4))
    )
    with pytest.raises(DatasetError, match="1 frames have no ground-truth pose"):
        TruthAsOdometry(open_dataset(str(tmp_path)))
    (tmp_path / "groundtruth.txt").write_text(
        "".join(f"{100.0 + i * 0.033:.6f} 0 {0.5 * i} 0 0 0 0 1\n" for i in range(5))
    )
    ds = open_dataset(str(tmp_path))
    truth, without = TruthAsOdometry(ds), WithoutOdometry(ds)
    assert len(truth) == len(without) == 5 and all(without.frame(i).odometry is None for i in range(5))
    np.testing.assert_allclose(truth.frame(3).odometry[:3, 3], [0, 1.5, 0])
    assert without.frame(3).odometry is None and without.frame(3).detections[0].label == "cup"
    assert np.array_equal(truth.ground_truth.poses, ds.ground_truth.poses)


def test_without_camera_json_tum_defaults_and_flags_apply(tmp_path):
    _write_tum(tmp_path, camera=False, odometry=False, detections=False)
    ds = open_dataset(str(tmp_path))
    assert ds.camera.depth_scale == 5000 and ds.camera.color.fx == 525
    assert ds.frame(0).detections is None and ds.frame(0).odometry is None
    ds = open_dataset(str(tmp_path), {"depth_scale": 1000.0, "fx": 300.0})
    assert ds.camera.depth_scale == 1000 and ds.camera.color.fx == 300


def test_configured_camera_defaults_apply_without_camera_files_and_flags_override_them(tmp_path):
    _write_tum(tmp_path / "d", camera=False, odometry=False, detections=False)
    (tmp_path / "objslam.yaml").write_text("camera:\n  fx: 600.0\n  depth_scale: 1000.0\n")
    defaults = load_settings(tmp_path / "objslam.yaml").camera.model_dump()
    ds = open_dataset(str(tmp_path / "d"), None, defaults)
    assert (ds.camera.color.fx, ds.camera.color.fy, ds.camera.depth_scale) == (600, 525, 1000)
    ds = open_dataset(str(tmp_path / "d"), {"fx": 300.0}, defaults)
    assert (ds.camera.color.fx, ds.camera.depth_scale) == (300, 1000)


def test_flags_a_camera_file_makes_moot_are_reported(tmp_path, caplog):
    _write_tum(tmp_path, odometry=False, detections=False)  # with camera.json
    with caplog.at_level(logging.WARNING, logger="sources.tum"):
        ds = open_dataset(str(tmp_path), {"fx": 300.0, "depth_scale": 1000.0}, {"fx": 700.0})
    assert ds.camera.color.fx == 50 and "--depth-scale, --fx not applied" in caplog.text


def test_missing_and_malformed_directories_give_clear_errors(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        open_dataset(str(tmp_path / "nope"))
    with pytest.raises(DatasetError, match=r"associations\.txt"):
        open_dataset(str(tmp_path))
    _write_tum(tmp_path / "d")
    (tmp_path / "d" / "camera.json").write_text('{"fx": 1}')
    with pytest.raises(DatasetError, match=r"camera\.json"):
        open_dataset(str(tmp_path / "d"))


@requires_redkitchen
def test_7scenes_redkitchen_loads_with_mm_depth_and_unregistered_camera():
    ds = open_dataset(str(REDKITCHEN))
    assert len(ds) == 1000 and ds.frame(0).odometry is None
    cam = ds.camera
    assert cam.depth_scale == 1000.0 and not cam.registered
    assert cam.depth.fx == 585 and (cam.depth.cx, cam.depth.cy) == (320, 240)
    assert cam.color.fx == pytest.approx(526.5)
    assert cam.depth_to_color[0, 3] == pytest.approx(-0.027, abs=2e-3)
    f = ds.frame(0)
    assert f.timestamp == 0.0 and ds.frame(999).timestamp == pytest.approx(33.3)
    assert f.rgb.shape == (480, 640, 3) and f.depth.shape == (480, 640)
    valid = f.depth_m()
    assert np.nanmin(valid) >= 0.8 and np.nanmax(valid) <= 4.0  # mm scale: 801..3975 raw
    assert 0.05 < np.isnan(valid).mean() < 0.3 and not np.any(f.depth == 65535)
    gt = ds.ground_truth
    assert len(gt) == 1000 and np.allclose(gt.poses[:, 3], [0, 0, 0, 1])
    steps = np.linalg.norm(np.diff(gt.poses[:, :3, 3], axis=0), axis=1)
    assert steps.sum() == pytest.approx(7.42, abs=0.05)


@requires_redkitchen
def test_7scenes_depth_reprojects_consistently_with_ground_truth():
    """Depth camera K=585 and mm depth with the GT poses: frame 0 reprojected into frame 10 agrees (<1 %)."""
    ds = open_dataset(str(REDKITCHEN))
    gt = ds.ground_truth
    a, b = ds.frame(0), ds.frame(10)
    K = ds.camera.depth.matrix()
    za = a.depth_m()
    v, u = np.nonzero(np.isfinite(za))
    pts = np.linalg.inv(K) @ np.vstack([u, v, np.ones_like(u)]) * za[v, u]
    T = np.linalg.inv(gt.poses[10]) @ gt.poses[0]
    pb = T[:3, :3] @ pts + T[:3, 3:4]
    uv = K @ pb
    ub, vb = np.round(uv[0] / uv[2]).astype(int), np.round(uv[1] / uv[2]).astype(int)
    ok = (ub >= 0) & (ub < 640) & (vb >= 0) & (vb < 480)
    zb = b.depth_m()[vb[ok], ub[ok]]
    rel = np.abs(zb - pb[2, ok]) / pb[2, ok]
    assert np.nanmedian(rel) < 0.01
