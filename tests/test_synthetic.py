"""The synthetic RGB-D scene: determinism, geometric consistency of depth / masks / detections, loops (its rendering
speed: ``objslam bench throughput``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from graph.geometry import inverse, relative, rotation_angle
from sources.base import DatasetError
from sources.synthetic import SyntheticDataset, parse_synthetic_spec

SMALL = "synthetic:room?seed=0&frames=300&width=320&height=240"


@pytest.fixture(scope="module")
def small() -> SyntheticDataset:
    return parse_synthetic_spec(SMALL)


@pytest.fixture(scope="module")
def full() -> SyntheticDataset:
    return parse_synthetic_spec("synthetic:room?seed=0&frames=300")


def backproject(ds: SyntheticDataset, depth_m: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) of the valid depth pixels and their flat pixel indices."""
    K = ds.camera.color
    v, u = np.nonzero(np.isfinite(depth_m))
    z = depth_m[v, u]
    cam = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=1)
    return cam @ pose[:3, :3].T + pose[:3, 3], v * depth_m.shape[1] + u


def mask_box(mask: np.ndarray) -> tuple[float, float, float, float]:
    """Bounding box [x1, y1, x2, y2) of a boolean mask in pixel-edge coordinates."""
    rows, cols = np.nonzero(mask.any(1))[0], np.nonzero(mask.any(0))[0]
    return float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)


def iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_same_spec_is_deterministic_in_any_order_and_seed_changes_everything(small: SyntheticDataset) -> None:
    other = parse_synthetic_spec(SMALL)
    late, early = other.frame(40), other.frame(3)  # reverse order, fresh instance
    for i, f2 in ((3, early), (40, late)):
        f1 = small.frame(i)
        assert np.array_equal(f1.rgb, f2.rgb) and np.array_equal(f1.depth, f2.depth)
        assert f1.detections == f2.detections and np.array_equal(f1.odometry, f2.odometry)
        assert np.array_equal(small.instance_mask(i), other.instance_mask(i))
    seeded = parse_synthetic_spec(SMALL.replace("seed=0", "seed=1"))
    g = seeded.frame(3)
    assert not np.array_equal(g.rgb, early.rgb) and not np.array_equal(g.depth, early.depth)
    assert not np.allclose(seeded.ground_truth.poses, small.ground_truth.poses)
    assert [o.center for o in seeded.objects] != [o.center for o in small.objects]


def test_frame_fields_camera_and_ground_truth(small: SyntheticDataset) -> None:
    f = small.frame(42)
    assert f.frame_id == "synthetic/room/000042" and f.seq == 42 and f.index == 42
    assert f.timestamp == pytest.approx(42 / 30.0)
    assert f.rgb.shape == (240, 320, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (240, 320) and f.depth.dtype == np.uint16
    cam = small.camera
    assert cam.registered and cam.depth_scale == 1000.0
    assert (cam.color.fx, cam.color.fy, cam.color.cx, cam.color.cy) == (262.5, 262.5, 159.5, 119.5)
    assert small.frame(0).odometry is not None  # the frames carry (drifting) odometry
    assert len(small) == 300 and small.timestamps[-1] == pytest.approx(299 / 30.0)
    gt = small.ground_truth
    assert gt.poses.shape == (300, 4, 4) and np.allclose(gt.poses[:, 3], [0, 0, 0, 1])
    assert [o.id for o in small.objects] == list(range(1, len(small.objects) + 1))
    assert len(small.objects) >= 12 and sum(o.label == "cup" for o in small.objects) == 3


def test_depth_reprojects_into_frame_i_plus_5_within_1_percent(small: SyntheticDataset) -> None:
    poses = small.ground_truth.poses
    K = small.camera.color
    for i in (10, 150, 260):
        pts, _ = backproject(small, small.frame(i).depth_m(), poses[i])
        cam = (pts - poses[i + 5][:3, 3]) @ poses[i + 5][:3, :3]
        u = np.rint(cam[:, 0] / cam[:, 2] * K.fx + K.cx).astype(int)
        v = np.rint(cam[:, 1] / cam[:, 2] * K.fy + K.cy).astype(int)
        inside = (cam[:, 2] > 0.1) & (u >= 0) & (u < 320) & (v >= 0) & (v < 240)
        target = small.frame(i + 5).depth_m()[v[inside], u[inside]]
        ok = np.isfinite(target)
        rel = np.abs(target[ok] - cam[inside, 2][ok]) / target[ok]
        unoccluded = rel < 0.05
        print(f"frame {i}->{i + 5}: unoccluded {unoccluded.mean():.3f}, median rel {np.median(rel):.4f}")
        assert inside.sum() > 0.6 * len(pts) and unoccluded.mean() > 0.9
        assert np.median(rel[unoccluded]) < 0.01 and np.median(rel) < 0.01


def test_mask_pixels_backproject_inside_their_true_boxes(small: SyntheticDataset) -> None:
    poses = small.ground_truth.poses
    objects = {o.id: o for o in small.objects}
    checked = 0
    for i in (0, 90, 120, 200, 240):
        pts, flat = backproject(small, small.frame(i).depth_m(), poses[i])
        ids = small.instance_mask(i).ravel()[flat]
        for oid in np.unique(ids[ids > 0]):
            o = objects[int(oid)]
            c, s = np.cos(o.yaw), np.sin(o.yaw)
            d = pts[ids == oid] - np.array(o.center)
            local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
            inside = np.all(np.abs(local) <= np.array(o.size) / 2 + 0.05, axis=1)
            assert inside.mean() >= 0.95, (i, o.label, inside.mean())
            checked += 1
    assert checked >= 10


def test_detections_match_visible_instances_with_iou_0_7(small: SyntheticDataset) -> None:
    labels = {o.id: o.label for o in small.objects}
    visible, detected, true_dets, false_dets = 0, 0, 0, 0
    for i in range(0, 300, 12):
        f, mask = small.frame(i), small.instance_mask(i)
        inst = small.detection_instance_ids(i)  # ground truth from the dataset, never from the frame
        assert len(inst) == len(f.detections)
        for det, oid in zip(f.detections, inst, strict=True):
            x1, y1, x2, y2 = det.box
            assert 0 <= x1 < x2 <= 320 and 0 <= y1 < y2 <= 240 and 0.4 <= det.score <= 0.99
            if oid == 0:
                false_dets += 1
                continue
            true_dets += 1
            assert det.label == labels[oid] and iou(det.box, mask_box(mask == oid)) >= 0.7
        for oid in np.unique(mask[mask > 0]):
            m = mask == oid
            box = mask_box(m)
            if m.sum() >= 2 * small.min_pixels and min(box[2] - box[0], box[3] - box[1]) >= 2 * small.min_side:
                visible += 1
                detected += int(oid) in inst
    print(f"visible {visible}, detected {detected}, true detections {true_dets}, false positives {false_dets}")
    assert visible >= 40 and detected / visible >= 0.8
    noisy = SyntheticDataset(width=320, height=240, frames=300, fp_rate=2.0, miss_rate=1.0)
    fps = [d for i in range(5) for d in noisy.frame(i).detections]
    assert len(fps) >= 3 and {d.label for d in fps} <= set(labels.values())


def test_default_scene_has_true_loops(full: SyntheticDataset) -> None:
    loops = full.loops
    poses = full.ground_truth.poses
    print(f"loop pairs: {len(loops)}")
    assert len(loops) >= 50 and loops == sorted(loops)
    for i, j in loops[:: max(1, len(loops) // 50)]:
        t, r = np.linalg.norm(relative(poses[i], poses[j])[:3, 3]), rotation_angle(relative(poses[i], poses[j])[:3, :3])
        assert j - i >= 100 and t <= 0.3 and np.degrees(r) <= 20.0


def footprint(o) -> np.ndarray:
    c, s = np.cos(o.yaw), np.sin(o.yaw)
    hx, hy = o.size[0] / 2, o.size[1] / 2
    return np.array(o.center[:2]) + np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) @ [[c, s], [-s, c]]


def boxes_overlap(a, b) -> bool:
    """True when two yawed boxes share volume (separating axes on the footprints, then z)."""
    if (
        min(a.center[2] + a.size[2] / 2, b.center[2] + b.size[2] / 2)
        - max(a.center[2] - a.size[2] / 2, b.center[2] - b.size[2] / 2)
        <= 1e-6
    ):
        return False
    pa, pb = footprint(a), footprint(b)
    for poly in (pa, pb):
        e = np.roll(poly, -1, axis=0) - poly
        for n in np.stack([-e[:, 1], e[:, 0]], axis=1):
            if (pa @ n).max() <= (pb @ n).min() + 1e-9 or (pb @ n).max() <= (pa @ n).min() + 1e-9:
                return False
    return True


def test_objects_do_not_overlap_and_stay_in_the_room() -> None:
    for seed in range(5):
        objects = SyntheticDataset(seed=seed, width=64, height=48).objects
        for k, a in enumerate(objects):
            fp = footprint(a)
            assert fp.min() > 0 and (fp < [6.0, 5.0]).all() and 0 <= a.center[2] - a.size[2] / 2 < 2.6
            assert not any(boxes_overlap(a, b) for b in objects[k + 1 :]), (seed, a.label)
        cups = [o for o in objects if o.label == "cup"]
        table = next(o for o in objects if o.label == "dining table")
        assert all(abs(c.center[2] - c.size[2] / 2 - table.size[2]) < 1e-9 for c in cups)


def test_camera_stays_clear_of_objects_and_near_depth_is_rare(small: SyntheticDataset) -> None:
    cams = small.ground_truth.poses[:, :3, 3]
    steps = np.linalg.norm(np.diff(cams, axis=0), axis=1)
    assert cams[:, 2].min() >= 1.2 and cams[:, 2].max() <= 1.6 and steps.max() < 0.05
    for o in small.objects:
        c, s = np.cos(o.yaw), np.sin(o.yaw)
        d = cams[:, :2] - o.center[:2]
        local = np.abs(np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1))
        assert np.linalg.norm(np.maximum(local - np.array(o.size[:2]) / 2, 0), axis=1).min() >= 0.5, o.label
    near = [np.mean(small.frame(i).depth_m() < 0.5) for i in range(0, 300, 25)]
    assert max(near) < 0.02


def test_odometry_starts_true_and_drifts_slowly(small: SyntheticDataset) -> None:
    gt = small.ground_truth.poses
    odo = np.array([small.frame(i).odometry for i in (0, 1, 150, 299)])
    assert np.allclose(odo[0], gt[0])
    step_err = relative(relative(gt[0], gt[1]), relative(odo[0], odo[1]))
    assert np.linalg.norm(step_err[:3, 3]) < 0.01 and np.degrees(rotation_angle(step_err[:3, :3])) < 0.3
    end = relative(gt[299], odo[3])
    assert 0.01 < np.linalg.norm(end[:3, 3]) < 1.0 and 1.0 < np.degrees(rotation_angle(end[:3, :3])) < 20.0
    exact = SyntheticDataset(width=64, height=48, frames=300, odom_drift=0.0)
    assert np.allclose(exact.frame(299).odometry, exact.ground_truth.poses[299], atol=1e-9)


def test_parse_spec_defaults_params_and_errors() -> None:
    ds = parse_synthetic_spec("synthetic:room?frames=20&width=64&height=48")
    assert ds.name == "synthetic/room" and len(ds) == 20 and ds.seed == 0 and ds.fps == 30.0
    assert ds.miss_rate == 0.05 and ds.fp_rate == 0.05 and (ds.camera.width, ds.camera.height) == (64, 48)
    ds = parse_synthetic_spec(
        "synthetic:room?seed=7&frames=30&width=80&height=60&fps=15&miss_rate=0.2&fp_rate=0&loop_gap=10&revolutions=2"
    )
    assert (ds.seed, len(ds), ds.fps, ds.miss_rate, ds.fp_rate, ds.loop_gap) == (7, 30, 15.0, 0.2, 0.0, 10)
    assert all(j - i >= 10 for i, j in ds.loops) and len(ds.loops) > 0
    assert ds.frame(3).timestamp == pytest.approx(0.2)
    default = parse_synthetic_spec("synthetic:room")
    assert len(default) == 300 and (default.camera.width, default.camera.height) == (640, 480)
    bad = [
        "synthetic:kitchen",
        "synthetic:room?frames=abc",
        "synthetic:room?frames=0",
        "synthetic:room?width=-5",
        "synthetic:room?miss_rate=1.5",
        "synthetic:room?seed=-1",
        "synthetic:room?colour=red",
        "synthetic:room?seed=1&seed=2",
        "synthetic:room?seed",
        "synthetic:room?fps=nan",
        "synthetic:room?revolutions=0",
    ]
    for spec in bad:
        with pytest.raises(DatasetError) as err:
            parse_synthetic_spec(spec)
        assert "\n" not in str(err.value) and str(err.value)


def test_orb_pnp_recovers_true_relative_pose_over_3_frames(full: SyntheticDataset) -> None:
    poses, K = full.ground_truth.poses, full.camera.color
    orb = cv2.ORB_create(1000)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    for i in (30, 150, 240):
        f0, f1 = full.frame(i), full.frame(i + 3)
        k0, d0 = orb.detectAndCompute(cv2.cvtColor(f0.rgb, cv2.COLOR_RGB2GRAY), None)
        k1, d1 = orb.detectAndCompute(cv2.cvtColor(f1.rgb, cv2.COLOR_RGB2GRAY), None)
        depth = f0.depth_m()
        obj, img = [], []
        for m in matcher.match(d0, d1):
            u, v = k0[m.queryIdx].pt
            z = depth[round(v), round(u)]
            if np.isfinite(z):
                obj.append([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z])
                img.append(k1[m.trainIdx].pt)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            np.array(obj), np.array(img), K.matrix(), None, reprojectionError=2.0, iterationsCount=200
        )
        est = np.eye(4)
        est[:3, :3], est[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        err = est @ inverse(relative(poses[i + 3], poses[i]))  # est maps frame-i points into frame i+3
        t_err, r_err = np.linalg.norm(err[:3, 3]), np.degrees(rotation_angle(err[:3, :3]))
        print(f"frames {i}->{i + 3}: {len(obj)} matches, {len(inliers)} inliers, {t_err * 100:.2f} cm, {r_err:.3f} deg")
        assert ok and len(inliers) >= 50 and t_err < 0.02 and r_err < 1.0
