"""The floor under the map and furniture standing on it (``perception.floor``; issue 24, centroid error).

A chair near a camera that looks down has its legs cut off by the image's lower edge in every view: its
visible part alone puts its centre too high. Rendered with exact depth (``tests/test_object_geometry.py``'s
room), the floor is found from the keyframes and the chair reaches down to it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.amodal import vertical_extent
from perception.floor import (
    SCREEN_ASPECT,
    Floor,
    FloorConfig,
    ends_seen,
    level_plane,
    on_floor,
    screen_span,
    vertical_span,
    with_span,
    world_floor_view,
)
from perception.frame import Detection
from perception.object_map import ObjectMapper
from sources.base import ObjectTruth
from sources.raycast import Renderer
from tests.test_object_geometry import CHAIR, CUP, TABLE, H, K, W, looking_at, mask_box, surfaces


def chair_views(angles_deg: np.ndarray, radius: float = 1.2, height: float = 1.4) -> np.ndarray:
    """Poses on an arc around the chair aimed at its top (0.95 m): the image's lower edge cuts its legs."""
    target = (CHAIR.center[0], CHAIR.center[1], 0.95)
    return looking_at(target, np.radians(angles_deg), radius, height)


def map_chair(poses: np.ndarray, floor: FloorConfig) -> tuple[list, Floor | None, int]:
    """The objects ObjectMapper makes of the chair seen from ``poses`` (exact depth, boxes from the mask), its
    floor, and how many views had the chair's box cut by the lower edge."""
    renderer = Renderer(surfaces([TABLE, CUP, CHAIR]), K, W, H)
    mapper = ObjectMapper(floor=floor)
    cut = 0
    for i, pose in enumerate(poses):
        r = renderer.render(pose)
        depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
        box = mask_box(r.ids == CHAIR.id)
        cut += box[3] >= H - 1
        mapper.add_keyframe(i, [Detection("chair", 0.9, box)], depth, K, pose)
    return mapper.finish(), mapper.floor, cut


def test_the_floor_of_a_rendered_view_is_found_in_its_lower_half() -> None:
    pose = chair_views(np.array([20.0]))[0]
    r = Renderer(surfaces([TABLE, CUP, CHAIR]), K, W, H).render(pose)
    plane = level_plane(np.where(r.depth > 0, r.depth, np.nan).astype(np.float32), K, FloorConfig())
    assert plane is not None
    normal, foot = world_floor_view(plane, pose)
    assert np.degrees(np.arccos(normal[2])) < 1.0  # up is world z
    assert abs(foot[2]) < 0.01  # the floor is z = 0
    assert np.allclose(foot[:2], pose[:2, 3], atol=0.02)  # under the camera


def test_the_floor_is_the_lowest_height_many_keyframes_agree_on() -> None:
    rng = np.random.default_rng(0)
    heights = [0.75] * 30 + [0.002 * k for k in range(-4, 5)] + [-0.3, -0.31]
    # table tops fill more images than the floor; two planes below the floor are too few to be it
    feet = np.column_stack([rng.uniform(0, 5, (len(heights), 2)), heights])
    normals = np.tile([0.0, 0.0, 1.0], (len(heights), 1))
    estimate = Floor.estimate(normals, feet, FloorConfig())
    assert estimate is not None and abs(estimate.height) < 0.005 and estimate.support == 9
    assert Floor.estimate(normals[:4], feet[:4], FloorConfig()) is None  # fewer than min_keyframes
    # a table seen by many more keyframes than the floor (the 7-Scenes kitchen: 77 against 14)
    kitchen = [0.7 + 0.0005 * k for k in range(-38, 39)] + [0.002 * k for k in range(-7, 7)]
    feet_k = np.column_stack([rng.uniform(0, 5, (len(kitchen), 2)), kitchen])
    floor = Floor.estimate(np.tile([0.0, 0.0, 1.0], (len(kitchen), 1)), feet_k, FloorConfig())
    assert floor is not None and abs(floor.height) < 0.01 and floor.support == 14
    # the same planes in a turned and moved world: the same floor, turned and moved
    R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t = np.array([2.0, -1.0, 0.5])
    moved = Floor.estimate(normals @ R.T, feet @ R.T + t, FloorConfig())
    assert moved is not None and np.allclose(moved.up, R @ estimate.up)
    assert np.isclose(moved.height, estimate.height + moved.up @ t)


def test_a_chair_whose_legs_every_view_cuts_off_reaches_down_to_the_floor() -> None:
    poses = chair_views(np.linspace(-60.0, 60.0, 16))
    objects, floor, cut = map_chair(poses, FloorConfig())
    assert cut == len(poses)  # the failure this guards against: no view sees the chair's bottom
    assert floor is not None and abs(floor.height) < 0.01
    chairs = [o for o in objects if o.label == "chair"]
    assert len(chairs) == 1
    assert abs(chairs[0].mean[2] - CHAIR.center[2]) < 0.03
    assert np.linalg.norm(chairs[0].mean - np.asarray(CHAIR.center)) < 0.06
    # without the floor (never enough keyframes), the visible part alone places it well above its centre
    unfloored, none, _ = map_chair(poses, FloorConfig(min_keyframes=10**6))
    assert none is None
    assert unfloored[0].mean[2] - CHAIR.center[2] > 0.06


def test_an_object_far_above_the_floor_is_not_stretched_to_it() -> None:
    floor = Floor(np.array([0.0, 0.0, 1.0]), 0.0, 10)
    shelf = ObjectTruth(9, "suitcase", (0.0, 0.0, 2.0), (0.4, 0.2, 0.5), 0.0)
    cov = np.diag([0.4**2, 0.2**2, 0.5**2]) / 12.0
    views = (np.array([shelf.center, shelf.center]), np.stack([cov, cov]), np.ones(2))
    assert on_floor(np.asarray(shelf.center), cov, views, floor, FloorConfig()) is None
    low = np.asarray(shelf.center) - [0.0, 0.0, 1.5]  # a suitcase whose visible part ends 0.25 m above the floor
    stretched = on_floor(low, cov, (views[0] - [0.0, 0.0, 1.5], views[1], views[2]), floor, FloorConfig())
    assert stretched is not None
    mean, new_cov = stretched
    assert np.isclose(mean[2], 0.375) and np.isclose(new_cov[2, 2], 0.75**2 / 12.0)


def test_a_view_s_vertical_extent_is_its_points_span_down_to_the_surface_it_stands_on() -> None:
    up = np.array([0.0, 0.0, 1.0])
    # a box seen from above: its top face holds most points (at 0.9), its front face the rest (0.76-0.9)
    heights = np.r_[np.full(300, 0.9), np.linspace(0.76, 0.9, 100)]
    table = np.r_[up, -0.75]  # the plane z = 0.75 under it; the support removal took the 1 cm band above it
    # percentiles (2nd, 98th), not moments: the mean and sqrt(3) std would span 0.82-0.94
    assert np.allclose(vertical_extent(heights, np.zeros(3), up, None), (0.76, 0.9), atol=0.012)
    assert np.allclose(vertical_extent(heights, np.zeros(3), up, table), (0.75, 0.9), atol=0.001)
    # a plane far below the lowest point is not what the object stands on
    assert np.allclose(vertical_extent(heights, np.zeros(3), up, np.r_[up, 0.0]), (0.76, 0.9), atol=0.012)


def test_a_cup_seen_from_above_is_centred_at_its_true_height() -> None:
    # 1.2 m from the cup, 0.75 m above its middle, looking down at it on a 90 degree arc: the camera sees its
    # rim and near side; completed along the tilted ray its centre went down and towards the camera together
    poses = looking_at(CUP.center, np.radians(np.linspace(-45.0, 45.0, 12)), 1.2, 1.55)
    renderer = Renderer(surfaces([TABLE, CUP]), K, W, H)
    mapper = ObjectMapper()
    for i, pose in enumerate(poses):
        r = renderer.render(pose)
        depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
        mapper.add_keyframe(i, [Detection("cup", 0.9, mask_box(r.ids == CUP.id))], depth, K, pose)
    cups = mapper.finish()
    assert mapper.floor is not None  # the views' level planes gave the world's up
    assert len(cups) == 1
    error = cups[0].mean - np.asarray(CUP.center)
    assert abs(error[2]) < 0.005, error
    assert np.linalg.norm(error) < 0.02, error


def test_a_wall_screen_whose_top_most_views_cut_off_keeps_the_top_the_others_see() -> None:
    # a screen from 1.0 to 1.6 m: 8 views cut at the image's top edge see it only up to 1.45 m, 4 see it whole
    up = np.array([0.0, 0.0, 1.0])
    cov_whole = np.diag([0.3, 0.001, 0.6**2 / 12.0])
    cov_cut = np.diag([0.3, 0.001, 0.45**2 / 12.0])
    means = np.array([[0.0, 0.0, 1.3]] * 4 + [[0.0, 0.0, 1.225]] * 8)
    covs = np.stack([cov_whole] * 4 + [cov_cut] * 8)
    cut = np.array([[False, False]] * 4 + [[True, False]] * 8)
    bottom, top = vertical_span(means, covs, np.ones(12), up, cut)
    assert np.isclose(bottom, 1.0, atol=0.01) and np.isclose(top, 1.6, atol=0.01)
    mean, cov = with_span(means.mean(axis=0), covs.mean(axis=0), up, bottom, top)
    assert np.isclose(mean[2], 1.3, atol=0.01) and np.isclose(cov[2, 2], 0.6**2 / 12.0, atol=1e-3)
    # every view cut at the top: the highest tops (90th percentile), not their median
    _, top_all_cut = vertical_span(means[4:], covs[4:], np.ones(8), up, np.array([[True, False]] * 8))
    assert np.isclose(top_all_cut, 1.45, atol=0.01)


def test_a_view_over_a_wide_table_finds_the_floor_beyond_it_not_the_table_top() -> None:
    """A camera at a person's height looking down over a wide table: its top fills most of the lower half, the
    floor shows only around it. The keyframe's floor is the lower surface, not the dominant one; when no lower
    surface is wide enough (20 m asked for), the table top stays."""
    wide = ObjectTruth(1, "dining table", (4.5, 4.5, 0.375), (1.6, 1.2, 0.75), 0.0)
    pose = looking_at((4.5, 4.5, 0.75), np.array([np.pi]), 1.4, 1.55)[0]
    r = Renderer(surfaces([wide]), K, W, H).render(pose)
    depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
    assert np.mean(r.ids[H // 2 :] == wide.id) > 0.25  # the table fills most of the lower half
    plane = level_plane(depth, K, FloorConfig())
    assert plane is not None
    foot = world_floor_view(plane, pose)[1]
    assert abs(foot[2]) < 0.02  # the floor, z = 0
    only_top = level_plane(depth, K, FloorConfig(lower_span_m=20.0))  # no lower surface is wide enough
    assert only_top is not None and abs(world_floor_view(only_top, pose)[1][2] - 0.75) < 0.02


def test_a_screen_whose_top_no_view_sees_is_as_tall_as_its_width_says_from_its_bottom() -> None:
    cut = np.array([[True, False]] * 5 + [[False, False]] * 2)  # the image's top edge cuts 5 of 7 views
    assert ends_seen(cut) == (False, True)
    assert screen_span((1.0, 1.3), ends_seen(cut), 0.6) == pytest.approx((1.0, 1.6))
    assert screen_span((1.0, 1.3), (True, False), 0.6) == pytest.approx((0.7, 1.3))  # only the top seen
    assert screen_span((1.0, 1.3), (True, True), 0.6) == (1.0, 1.3)  # both ends seen: as measured
    assert screen_span((1.0, 1.3), (False, False), 0.6) == (1.0, 1.3)  # neither: no end to start from
    assert screen_span((1.0, 1.7), (False, True), 0.6) == (1.0, 1.7)  # taller than the prior already
    assert SCREEN_ASPECT["tv"] == pytest.approx(9 / 16)


def test_a_wall_screen_above_every_view_s_top_edge_is_as_tall_as_a_screen_of_its_width() -> None:
    """A 1.2 m wide screen from 1.16 to 1.84 m on a wall, seen from 2.5 m by a camera at 1.5 m looking 22 degrees
    down: the image's top edge cuts it at about 1.6 m in every view, so no view sees its top. Its height is then
    its width's (``SCREEN_ASPECT``) from the bottom the views see, not the span of what they show."""
    screen = ObjectTruth(5, "tv", (4.5, 8.92, 1.5), (1.2, 0.06, 0.675), 0.0)
    renderer = Renderer(surfaces([screen]), K, W, H)
    mapper = ObjectMapper()
    poses = looking_at((4.5, 8.95, 0.5), np.radians(np.linspace(-110.0, -70.0, 12)), 2.5, 1.5)
    for i, pose in enumerate(poses):
        r = renderer.render(pose)
        depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
        box = mask_box(r.ids == screen.id)
        assert box[1] <= 1  # the image's top edge cuts the screen
        mapper.add_keyframe(i, [Detection("tv", 0.9, box)], depth, K, pose)
    objects = [o for o in mapper.finish() if o.label == "tv"]
    assert mapper.floor is not None and len(objects) == 1
    assert abs(objects[0].mean[2] - screen.center[2]) < 0.04
    height = np.sqrt(12.0 * objects[0].cov[2, 2])
    assert abs(height - 9.0 / 16.0 * 1.2) < 0.06


FRIDGE = ObjectTruth(5, "refrigerator", (4.5, 4.5, 0.9), (0.7, 0.7, 1.8), 0.3)


def test_a_refrigerator_whose_top_most_views_cut_off_is_as_tall_as_the_views_that_see_it() -> None:
    """Twenty-four views from 1.3 m, whose image top cuts the refrigerator's box, and four from 3 m that see it
    whole: the tops of the near views are the image's edge, 1.5 m up, and the median of all views' tops (weighed by
    their points, a cut view's scaled down by ``FeatureConfig.cut_weight``) put its top there."""
    target = (FRIDGE.center[0], FRIDGE.center[1], 1.0)
    near = looking_at(target, np.radians(np.linspace(-50.0, 50.0, 24)), 1.3, 1.4)
    far = looking_at(target, np.radians(np.linspace(-30.0, 30.0, 4)), 3.0, 1.4)
    renderer = Renderer(surfaces([FRIDGE]), K, W, H)
    mapper = ObjectMapper()
    cut = 0
    for i, pose in enumerate(np.concatenate([near, far])):
        r = renderer.render(pose)
        box = mask_box(r.ids == FRIDGE.id)
        cut += box[1] <= 0
        depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
        mapper.add_keyframe(i, [Detection("refrigerator", 0.9, box)], depth, K, pose)
    assert cut == len(near)  # the failure this guards against: most views' tops are the image's edge
    (fridge,) = mapper.finish()
    assert mapper.floor is not None
    top = fridge.mean[2] + np.sqrt(3.0 * fridge.cov[2, 2])
    assert abs(top - 1.8) < 0.05
    assert abs(fridge.mean[2] - FRIDGE.center[2]) < 0.03
