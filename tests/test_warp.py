"""Depth warping (Sec. 2.4.3, eq. 2.16) and robust box back-projection (Sec. 2.4.4)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from graph.geometry import inverse
from perception.amodal import detection_feature
from perception.camera import Intrinsics
from perception.features import (
    FeatureConfig,
    depth_segment,
    dominant_depth_mask,
    feature_from_points,
    hidden_by_twin,
    in_front,
)
from perception.support import backproject_detection, object_points, support_plane
from perception.warp import needs_warp, warp_box, warp_depth
from sources import open_dataset

K = Intrinsics(100.0, 100.0, 39.5, 29.5)


def _pose(t: tuple[float, float, float], rotvec: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _plane_depth(z: float, shape: tuple[int, int] = (60, 80)) -> np.ndarray:
    return np.full(shape, z, np.float32)


def test_warping_a_fronto_parallel_plane_matches_its_depth_from_the_new_pose() -> None:
    T_new_old = inverse(_pose((0.1, 0.0, 0.3)))  # the new camera stands 0.1 m right and 0.3 m forward
    warped = warp_depth(_plane_depth(2.0), K, T_new_old, splat=2)
    valid = np.isfinite(warped)
    assert valid.mean() > 0.95  # the old view covers the new one; 2x2 splats close the magnification cracks
    np.testing.assert_allclose(warped[valid], 1.7, atol=1e-5)


def test_z_buffer_keeps_the_nearest_surface() -> None:
    depth = _plane_depth(3.0)
    depth[20:40, 30:50] = 1.0  # a near square in front of a wall
    warped = warp_depth(depth, K, inverse(_pose((-0.2, 0.0, 0.0))))  # camera moves left: near square moves right
    # the square shifts by 100 * 0.2 / 1 = 20 px, the wall by ~7 px: wall points also land there but lose
    assert np.nanmax(warped[22:38, 52:68]) == pytest.approx(1.0)
    assert np.nanmin(warped[22:38, 5:20]) == pytest.approx(3.0)


def test_warping_exact_synthetic_depth_with_the_true_pose_agrees_with_the_later_frame() -> None:
    data = open_dataset("synthetic:room?seed=3&frames=300&width=320&height=240&depth_noise=0")
    K_s = data.camera.color
    poses = data.ground_truth.poses
    i, j = 40, 46
    older, newer = data.frame(i).depth_m(), data.frame(j).depth_m()
    warped = warp_depth(older, K_s, inverse(poses[j]) @ poses[i])
    both = np.isfinite(warped) & np.isfinite(newer)
    err = np.abs(warped[both] - newer[both])
    assert both.mean() > 0.6  # 12 cm and 8 degrees apart: most of the view is shared
    # residuals come from rounding each point to the nearest pixel on slanted surfaces (they halve
    # when the resolution doubles) plus the mm quantisation of the depth
    assert np.median(err) < 0.002
    assert np.mean(err < 0.01 * newer[both]) > 0.99


def test_needs_warp_uses_translation_or_rotation_thresholds() -> None:
    assert not needs_warp(_pose((0.03, 0.0, 0.0)), tau=0.05, phi=0.05)
    assert needs_warp(_pose((0.06, 0.0, 0.0)), tau=0.05, phi=0.05)
    assert needs_warp(_pose((0.0, 0.0, 0.0), (0.0, 0.06, 0.0)), tau=0.05, phi=0.05)


def test_warped_box_moves_by_the_parallax_of_its_object() -> None:
    depth = _plane_depth(3.0)
    depth[20:40, 30:50] = 1.0
    moved = warp_box((28.0, 18.0, 52.0, 42.0), depth, K, inverse(_pose((-0.1, 0.0, 0.0))))
    assert moved is not None
    np.testing.assert_allclose(moved, (40.0, 20.0, 60.0, 40.0), atol=1.01)  # object pixels only, +10 px
    assert warp_box((28.0, 18.0, 52.0, 42.0), depth, K, inverse(_pose((5.0, 0.0, 0.0)))) is None


def test_dominant_depth_segment_excludes_the_background_behind_an_object() -> None:
    depths = np.r_[np.linspace(1.0, 1.3, 200), np.linspace(2.5, 2.6, 80)]
    mask = dominant_depth_mask(depths, anchor=1.1, gap_m=0.05)
    assert mask[:200].all() and not mask[200:].any()


def test_back_projected_feature_is_the_object_and_not_its_background() -> None:
    depth = _plane_depth(3.0)
    depth[20:40, 30:50] = 1.0
    T_wc = _pose((1.0, 2.0, 0.5))
    pts = backproject_detection(depth, K, T_wc, (25.0, 15.0, 55.0, 45.0), FeatureConfig())
    f = feature_from_points(pts, "cup")
    assert f is not None and len(pts) == 400
    np.testing.assert_allclose(f.mean, [1.0, 2.0, 1.5], atol=1e-6)
    assert f.var[2] < 1e-9 and f.var[0] == pytest.approx(0.2**2 / 12, rel=0.05)


def test_amodal_completion_puts_a_face_on_box_centre_behind_its_visible_face() -> None:
    """A 0.4 m wide box seen face on at 2 m: its centre is half its width behind the face, its depth spread that
    of a 0.4 m extent, whatever the floor pixels joined to its depth segment below it add."""
    depth = _plane_depth(4.0)
    depth[20:40, 30:50] = 2.0  # the face: 20 px at fx 100 and 2 m = 0.4 m
    depth[40:45, 25:55] = np.linspace(1.97, 2.03, 5)[:, None]  # a floor joined to the face's depth segment
    f = detection_feature(depth, K, (30.0, 20.0, 50.0, 45.0), "box", 3, FeatureConfig())
    assert f is not None and f.track_id == 3
    assert f.mean[2] == pytest.approx(2.2, abs=0.03)
    assert f.var[2] == pytest.approx(0.4**2 / 12, rel=0.1)
    plain = detection_feature(depth, K, (30.0, 20.0, 50.0, 45.0), "box", 3, FeatureConfig(amodal=None))
    assert plain.mean[2] < 2.05  # without completion the centre sits on the visible face


def test_a_tall_box_cut_by_the_image_side_is_completed_as_deep_as_tall_not_as_its_visible_width() -> None:
    """A 1 m tall box at 2 m with a wall 2 m behind it, of which the right image border shows only 0.2 m of
    width: its visible width understates it, so the depth prior takes its height; away from the border the same
    sliver is a whole, thin object."""
    depth = _plane_depth(4.0)
    depth[5:55, 70:] = 2.0  # 50 rows = 1 m at fx 100 and 2 m; columns 70-79 = 0.2 m, cut by the right border
    cut = detection_feature(depth, K, (70.0, 5.0, 80.0, 55.0), "refrigerator", 1, FeatureConfig())
    assert cut is not None and cut.mean[2] > 2.4 and cut.var[2] > 0.6**2 / 12
    inner = _plane_depth(4.0)
    inner[5:55, 60:70] = 2.0
    whole = detection_feature(inner, K, (60.0, 5.0, 70.0, 55.0), "refrigerator", 1, FeatureConfig())
    assert whole is not None and whole.mean[2] < 2.15


def test_amodal_depth_is_bounded_by_the_wall_behind_a_flat_object() -> None:
    """A 0.4 m wide screen 5 cm in front of a wall cannot be 0.4 m deep: the wall around it bounds it."""
    depth = _plane_depth(2.05)
    depth[20:40, 30:50] = 2.0
    f = detection_feature(depth, K, (30.0, 20.0, 50.0, 40.0), "tv", 1, FeatureConfig(gap_m=0.02))
    assert f is not None
    assert 2.0 < f.mean[2] <= 2.026 and f.var[2] <= 0.05**2 / 12 + 1e-9


def _pitched_plane_depth(z0: float, slope: float, shape: tuple[int, int] = (60, 80)) -> np.ndarray:
    """Depth of the plane z = z0 + slope * y (camera frame: a wall seen by a camera pitched down), ray by ray."""
    v = (np.arange(shape[0]) - K.cy) / K.fy
    return np.tile((z0 / (1.0 - slope * v)).astype(np.float32)[:, None], (1, shape[1]))


def test_amodal_depth_of_a_screen_on_a_wall_seen_from_below_is_bounded_by_the_wall_just_behind_it() -> None:
    """A wide screen 4 cm in front of a wall that the camera sees pitched by 30 degrees: the wall below the screen
    lies ~0.3 m behind the screen's nearest row, but only ~5 cm behind the screen itself, so the completed depth
    along the ray is the screen's own visible depth span plus that gap, not the screen's width."""
    slope, gap = np.tan(np.radians(30.0)), 0.04 / np.cos(np.radians(30.0))
    depth = _pitched_plane_depth(2.0, slope)
    depth[10:40, 10:70] = _pitched_plane_depth(2.0 - gap, slope)[10:40, 10:70]
    box = (10.0, 10.0, 70.0, 40.0)
    f = detection_feature(depth, K, box, "tv", 1, FeatureConfig())
    plain = detection_feature(depth, K, box, "tv", 1, FeatureConfig(amodal=None))
    assert f is not None and plain is not None
    ray = plain.mean / np.linalg.norm(plain.mean)
    visible_sd, completed_sd = np.sqrt(ray @ plain.cov @ ray), np.sqrt(ray @ f.cov @ ray)
    assert completed_sd <= visible_sd + 0.03
    assert 0.0 <= (f.mean - plain.mean) @ ray < 0.05  # the centre moves back by less than the gap to the wall


def test_the_floor_an_object_stands_on_is_dropped_from_its_pixels() -> None:
    """A cube standing on the floor, its box holding the floor around its foot, joined to its depth segment: the
    floor (the ring's dominant plane, horizontal for an upright camera) leaves the object's pixels, so the
    object's vertical extent is its own; a wall (a vertical plane) around a screen is not taken for a support."""
    depth = np.full((60, 80), 4.0, np.float32)  # a far wall above the floor
    height = 0.21  # the floor below the camera: depth f * h / (row - cy) = 2.0 m at row 40, the cube's foot
    depth[40:] = (K.fy * height / (np.arange(40, 60) - K.cy))[:, None]
    depth[20:40, 30:50] = 2.0  # the cube's face
    box = (28.0, 18.0, 52.0, 46.0)
    config = FeatureConfig(gap_m=0.25)  # coarse pixels: the floor's depth steps up to 0.2 m
    kept = object_points(depth, K, box, config)
    joined = object_points(depth, K, box, replace(config, support_tilt_deg=None))
    assert (joined[0] >= 41).any()  # without the support check the floor joins the cube's segment
    assert len(kept[0]) and kept[0].max() <= 40 and kept[1].min() >= 30 and kept[1].max() < 50
    plane = support_plane(depth, K, box, 45.0)
    assert plane is not None and abs(plane[1]) > 0.99 and abs(plane[3]) == pytest.approx(height, abs=0.01)
    wall = np.full((60, 80), 2.05, np.float32)
    wall[20:40, 30:50] = 2.0
    assert support_plane(wall, K, (30.0, 20.0, 50.0, 40.0), 45.0) is None


def test_a_box_behind_another_detection_leaves_out_its_pixels_and_keeps_its_own_centre() -> None:
    """Two 0.46 m faces in a row seen at a slant: the near one (2.0 m) and its side cover the left part of the far
    one's box (2.3 m), the side's depths joining the two. Taking the near one's pixels put the far one's near
    side, and its completed centre, 0.26 m too near; without them its centre is within the few cm its hidden
    part costs, and the near one, in front, keeps all of its own."""
    alone = _plane_depth(4.0)
    alone[20:40, 30:50] = 2.3  # the far face alone: 20 px at fx 100 = 0.46 m at 2.3 m
    depth = alone.copy()
    depth[22:42, 12:32] = 2.0  # the near face
    depth[22:42, 32:38] = np.linspace(2.04, 2.26, 6)[None, :]  # its side, receding to the far face's depth
    far_box, near_box = (30.0, 20.0, 50.0, 42.0), (12.0, 22.0, 38.0, 42.0)
    cfg = FeatureConfig()
    near_segment, far_segment = (depth_segment(depth, b, cfg)[2] for b in (near_box, far_box))
    assert near_segment is not None and far_segment is not None
    reference = detection_feature(alone, K, (30.0, 20.0, 50.0, 40.0), "chair", 1, cfg)
    mixed = detection_feature(depth, K, far_box, "chair", 1, cfg)
    clean = detection_feature(depth, K, far_box, "chair", 1, cfg, occluders=[near_segment])
    assert reference is not None and mixed is not None and clean is not None
    assert mixed.mean[2] < reference.mean[2] - 0.2  # the near face's pixels pull it forward
    assert abs(clean.mean[2] - reference.mean[2]) < 0.1 and clean.mean[2] > mixed.mean[2] + 0.15
    near = detection_feature(depth, K, near_box, "chair", 2, cfg)
    near_with = detection_feature(depth, K, near_box, "chair", 2, cfg, occluders=[far_segment])
    assert near is not None and near_with is not None and np.allclose(near.mean, near_with.mean)


def test_a_detection_held_by_a_larger_box_in_front_keeps_its_pixels() -> None:
    """A cup on the far part of a table: the table's box holds the cup's and its anchor is nearer, but a box
    around another is not in front of it (``AROUND``), nor is one far larger (``LARGER``): the cup and a bottle
    keep their pixels; a box about the table's size behind it does not."""
    depth = _plane_depth(4.0)
    depth[30:50, 10:70] = np.linspace(1.8, 2.6, 20)[:, None]  # a table top receding from 1.8 to 2.6 m
    depth[22:30, 50:56] = 2.5  # a cup standing on its far part
    table, cup = (10.0, 22.0, 70.0, 50.0), (50.0, 22.0, 56.0, 31.0)
    cfg = FeatureConfig()
    segments = {name: depth_segment(depth, b, cfg)[2] for name, b in (("table", table), ("cup", cup))}
    assert segments["table"] is not None and segments["cup"] is not None
    assert segments["table"].anchor < segments["cup"].anchor - cfg.gap_m
    rows, cols, _ = depth_segment(depth, cup, cfg)
    assert not in_front(depth[rows, cols], rows, cols, segments["cup"], [segments["table"]], cfg.gap_m).any()
    # a bottle standing above the table's box is held by it only in part, but the table's box is far larger
    depth[8:30, 50:56] = 2.5
    bottle = (50.0, 8.0, 56.0, 31.0)
    rows, cols, mine = depth_segment(depth, bottle, cfg)
    assert mine is not None and len(rows) > 100
    assert not in_front(depth[rows, cols], rows, cols, mine, [segments["table"]], cfg.gap_m).any()
    # the same table in front of a box not much smaller than its own takes its pixels from it
    wide = (20.0, 8.0, 70.0, 31.0)
    depth[8:30, 20:70] = 2.5
    rows, cols, mine = depth_segment(depth, wide, cfg)
    assert mine is not None
    assert in_front(depth[rows, cols], rows, cols, mine, [segments["table"]], cfg.gap_m).any()


def test_a_wall_the_support_joined_to_a_small_object_leaves_it_with_the_support() -> None:
    """A bottle 7 cm wide on a table against a wall: the table top runs on from the bottle's foot to the wall, so
    the wall beside the bottle joins its depth segment. Without the table, the wall is apart from the bottle:
    its pixels leave, and the bottle's width and centre are its own (the wall's doubled its width)."""
    cam = Intrinsics(300.0, 300.0, 159.5, 119.5)
    rows = np.arange(240, dtype=np.float32)[:, None]
    with np.errstate(divide="ignore"):
        table = np.where(rows > cam.cy, cam.fy * 0.5 / (rows - cam.cy), np.inf)  # 0.5 m below the camera
    depth = np.tile(np.minimum(table, 2.5), (1, 320)).astype(np.float32)  # the wall 2.5 m away above it
    depth[154:188, 155:165] = 2.2  # the bottle: 10 px = 7.3 cm at 2.2 m, its foot on the table at row 188
    box = (153.0, 152.0, 167.0, 190.0)
    kept_rows, kept_cols = object_points(depth, cam, box, FeatureConfig())
    assert len(kept_cols) > 50 and kept_cols.min() >= 155 and kept_cols.max() < 165
    assert depth[kept_rows, kept_cols].max() < 2.3
    f = detection_feature(depth, cam, box, "bottle", 1, FeatureConfig())
    assert f is not None
    true_x = (160.0 - cam.cx) * 2.2 / cam.fx  # the bottle's columns 155-164 centre on column 159.5 + 0.5
    assert abs(f.mean[0] - true_x) < 0.01
    assert np.sqrt(12.0 * f.cov[0, 0]) == pytest.approx(10 * 2.2 / cam.fx, rel=0.15)


SLANT_CAM = Intrinsics(300.0, 300.0, 159.5, 119.5)
SLANT = np.array([np.cos(np.radians(40.0)), np.sin(np.radians(40.0))])  # a line turned 40 degrees in (x, z)


def _slanted_line_depth(point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each column's ray of ``SLANT_CAM`` (x/z = ray_x) meets the line point + s * ``SLANT``: its depth and
    s, which solves (px + s dx) = ray_x (pz + s dz)."""
    ray_x = (np.arange(320) - SLANT_CAM.cx) / SLANT_CAM.fx
    s = (ray_x * point[1] - point[0]) / (SLANT[0] - ray_x * SLANT[1])
    return point[1] + s * SLANT[1], s


def test_a_screen_seen_at_a_slant_is_a_panel_not_as_deep_as_it_is_wide() -> None:
    """A 1 m wide screen 3 m away turned 40 degrees, nothing behind it nearby: completed as deep as it is wide, a
    chair's view would make it a 0.7 m square; a screen keeps its slanted face, 10 cm deep."""
    depth = np.full((240, 320), 6.0, np.float32)
    direction = SLANT  # along the screen in the camera's (x, z) plane
    centre = np.array([0.0, 3.0])
    screen_depth, s = _slanted_line_depth(centre)
    on = np.abs(s) <= 0.5
    depth[100:140, on] = screen_depth[on].astype(np.float32)
    box = (float(np.flatnonzero(on).min()), 100.0, float(np.flatnonzero(on).max() + 1), 140.0)
    screen = detection_feature(depth, SLANT_CAM, box, "tv", 1, FeatureConfig())
    chair = detection_feature(depth, SLANT_CAM, box, "chair", 1, FeatureConfig())
    assert screen is not None and chair is not None
    plane = np.ix_([0, 2], [0, 2])
    vals, vecs = np.linalg.eigh(screen.cov[plane])
    assert np.sqrt(12.0 * vals[0]) < 0.15 and np.sqrt(12.0 * vals[1]) == pytest.approx(1.0, rel=0.15)
    assert abs(vecs[:, 1] @ direction) > np.cos(np.radians(5.0))  # its long axis is the screen's
    assert np.linalg.norm(screen.mean[[0, 2]] - centre) < 0.08
    assert np.sqrt(12.0 * np.linalg.eigvalsh(chair.cov[plane])[0]) > 0.4  # completed as deep as it is wide


def test_a_box_that_shows_mostly_a_nearer_object_of_its_class_is_hidden_by_it() -> None:
    """The second chair of a row seen at a slant: its visible box lies inside the first chair's and its centre,
    where its segment is anchored, shows the first chair: its view would be the first chair's. A cup inside a
    table's box, or a chair beside the first, anchored on its own surface, is not hidden."""
    depth = _plane_depth(4.0)
    depth[15:50, 10:40] = 2.0  # the first chair
    depth[15:30, 38:44] = 2.5  # the second one's back, showing beside it
    cfg = FeatureConfig()
    first = depth_segment(depth, (10.0, 15.0, 40.0, 50.0), cfg)[2]
    second = depth_segment(depth, (25.0, 15.0, 44.0, 48.0), cfg)[2]
    assert first is not None and second is not None and abs(second.anchor - first.anchor) < cfg.gap_m
    assert hidden_by_twin(second, [first], cfg.gap_m)
    assert not hidden_by_twin(first, [second], cfg.gap_m)  # the larger, holding one keeps its view
    depth[15:50, 50:70] = 2.5  # a chair of its own beside the first, its box overlapping the first's edge
    beside = depth_segment(depth, (36.0, 15.0, 70.0, 50.0), cfg)[2]
    assert beside is not None and not hidden_by_twin(beside, [first], cfg.gap_m)


def test_a_ring_without_depth_beyond_the_sensor_range_does_not_bound_the_depth_behind_an_object() -> None:
    """A 0.4 m wide face 3.7 m away with a sensor that returns nothing beyond 4 m: the floor beside it reaches up
    to 4 m, but the missing returns above are no wall, so the face is completed as deep as wide (its centre 0.2 m
    behind it), not to the floor's farthest returns; with a wall 5 cm behind it, it stays bounded."""
    depth = np.full((60, 80), np.nan, np.float32)  # nothing within range above the floor
    depth[45:] = np.linspace(3.7, 3.99, 15)[:, None]  # the floor beside and below the face, up to the range
    depth[20:45, 35:46] = 3.7  # the face: 11 px at fx 100 and 3.7 m = 0.41 m
    box = (35.0, 20.0, 46.0, 45.0)
    f = detection_feature(depth, K, box, "chair", 1, FeatureConfig(support_tilt_deg=None))
    assert f is not None and f.mean[2] == pytest.approx(3.7 + 0.2, abs=0.04)
    walled = depth.copy()
    walled[:45] = 3.75
    walled[20:45, 35:46] = 3.7
    g = detection_feature(walled, K, box, "chair", 1, FeatureConfig(support_tilt_deg=None, gap_m=0.02))
    assert g is not None and g.mean[2] < 3.74


def test_a_box_whose_centre_has_no_depth_gives_no_view() -> None:
    """A chair beyond the sensor's range: its box holds only the floor in front of it with depth, which would place
    it there; with depth over its centre (the chair within range) it is seen."""
    depth = np.full((60, 80), np.nan, np.float32)
    depth[45:] = np.linspace(3.7, 3.99, 15)[:, None]  # the floor in front, up to the range
    box = (30.0, 20.0, 50.0, 50.0)
    assert depth_segment(depth, box, FeatureConfig())[2] is None
    assert detection_feature(depth, K, box, "chair", 1, FeatureConfig()) is None
    depth[20:45, 30:50] = 3.9
    assert detection_feature(depth, K, box, "chair", 1, FeatureConfig()) is not None
    # a screen's glass returns no depth: its frame and the wall around it place it
    wall = _plane_depth(2.0)
    wall[22:38, 32:48] = np.nan
    screen = (30.0, 20.0, 50.0, 40.0)
    assert detection_feature(wall, K, screen, "chair", 1, FeatureConfig()) is None
    tv = detection_feature(wall, K, screen, "tv", 1, FeatureConfig())
    assert tv is not None and tv.mean[2] == pytest.approx(2.0, abs=0.06)


def test_a_chair_seen_from_its_side_is_centred_on_its_footprint_not_on_its_back() -> None:
    """An armchair's side 2 m away, its back at the right end of its 0.4 m footprint: many visible points are the
    back's, so their mean lies 4 cm towards it; the centre across the ray is the middle of the points' extent."""
    depth = _plane_depth(4.0)
    depth[10:30, 45:50] = 2.0  # the back, 0.4 m above the seat
    depth[30:46, 30:50] = 2.0  # the seat's side, 0.3 m deep
    depth[46:60, 30] = depth[46:60, 49] = 2.0  # two legs down to the image's lower edge
    box, up = (30.0, 10.0, 50.0, 60.0), np.array([0.0, -1.0, 0.0])
    f = detection_feature(depth, K, box, "chair", 1, FeatureConfig(support_tilt_deg=None), up=up)
    plain = detection_feature(depth, K, box, "chair", 1, FeatureConfig(amodal=None))
    assert f is not None and plain is not None
    middle = ((30 + 49) / 2 - K.cx) * 2.0 / K.fx
    assert plain.mean[0] - middle > 0.03
    assert abs(f.mean[0] - middle) < 0.02


def test_a_chair_whose_left_part_returns_no_depth_is_centred_on_its_box() -> None:
    """A chair 2 m away whose left third (dark fabric) returns no depth: its points are the right two thirds, so
    the middle of their extent lies 7 cm right of the chair's middle; the box holds the whole chair, and its edges'
    rays at the depth of the points nearest them give its ends across the ray."""
    depth = _plane_depth(4.0)
    depth[20:50, 30:50] = 2.0  # the chair: 20 px at fx 100 = 0.4 m at 2 m
    depth[20:50, 30:37] = np.nan  # its left third without depth
    box, up = (30.0, 20.0, 50.0, 50.0), np.array([0.0, -1.0, 0.0])
    cfg = FeatureConfig(support_tilt_deg=None)
    f = detection_feature(depth, K, box, "chair", 1, cfg, up=up)
    assert f is not None
    middle = ((box[0] + box[2]) / 2 - K.cx) * 2.0 / K.fx
    points = detection_feature(depth, K, box, "chair", 1, FeatureConfig(amodal=None))
    assert points is not None and points.mean[0] - middle > 0.05  # what the points alone say
    assert abs(f.mean[0] - middle) < 0.01


def test_a_chair_whose_left_part_returns_no_depth_is_as_deep_as_its_box_is_wide() -> None:
    """The same chair: its points span two thirds of it, so a depth taken from their spread is 0.26 m and its
    centre 0.13 m behind its face; the box's width (0.4 m at 2 m) gives it its depth, the centre 0.2 m behind."""
    depth = _plane_depth(4.0)
    depth[20:50, 30:50] = 2.0
    depth[20:50, 30:37] = np.nan
    box, up = (30.0, 20.0, 50.0, 50.0), np.array([0.0, -1.0, 0.0])
    f = detection_feature(depth, K, box, "chair", 1, FeatureConfig(support_tilt_deg=None), up=up)
    assert f is not None
    assert abs(f.mean[2] - 2.2) < 0.01
    assert abs(np.sqrt(12.0 * f.cov[2, 2]) - 0.4) < 0.02


def test_a_screen_on_a_wall_is_as_deep_as_it_stands_off_the_wall() -> None:
    """A 1 m wide screen 5 cm deep hung on a wall 3 m away, both turned 40 degrees: the screen's slanted face
    reaches 0.6 m along the ray, which is no depth behind it; the free depth behind the face is the wall's 5 cm.
    Its centre is half that behind the face, its thin side about that thick."""
    normal = np.array([-SLANT[1], SLANT[0]])  # into the wall, away from the camera
    face, thick = np.array([0.0, 3.0]), 0.05
    wall, _ = _slanted_line_depth(face + thick * normal)
    screen, s = _slanted_line_depth(face)
    depth = np.tile(wall.astype(np.float32), (240, 1))
    on = np.abs(s) <= 0.5
    depth[100:140, on] = screen[on].astype(np.float32)
    box = (float(np.flatnonzero(on).min()), 100.0, float(np.flatnonzero(on).max() + 1), 140.0)
    f = detection_feature(depth, SLANT_CAM, box, "tv", 1, FeatureConfig())
    assert f is not None
    plane = np.ix_([0, 2], [0, 2])
    thin = np.sqrt(12.0 * np.linalg.eigvalsh(f.cov[plane])[0])
    assert thin < 0.07  # the depth prior's 10 cm, behind a face seen at a slant, would be 8 cm thick here
    assert np.linalg.norm(f.mean[[0, 2]] - (face + thick / 2 * normal)) < 0.02


def test_a_screen_whose_glass_returns_depth_only_low_down_reaches_its_box_s_top() -> None:
    """A screen 2 m away whose box spans rows 10-40 (0.6 m), of which only rows 25-40 return depth (glass): its
    view reaches from the box's bottom edge to its top edge at its depth, not from the returns' bottom to their
    top; without an up it stays as its points are."""
    depth = _plane_depth(2.1)
    depth[25:40, 20:60] = 2.0  # the lower half of the screen returns depth
    depth[10:25, 20:60] = np.nan  # its upper half, glass, none
    up = np.array([0.0, -1.0, 0.0])
    f = detection_feature(depth, K, (20.0, 10.0, 60.0, 40.0), "tv", 1, FeatureConfig(support_tilt_deg=None), up=up)
    assert f is not None
    top, bottom = -(10 - K.cy) / K.fy * f.mean[2], -(40 - K.cy) / K.fy * f.mean[2]
    assert f.mean @ up == pytest.approx((top + bottom) / 2, abs=0.02)
    assert np.sqrt(12 * up @ f.cov @ up) == pytest.approx(top - bottom, abs=0.03)
    plain = detection_feature(depth, K, (20.0, 10.0, 60.0, 40.0), "tv", 1, FeatureConfig(support_tilt_deg=None))
    assert plain is not None and np.sqrt(12 * plain.cov[1, 1]) < 0.4
