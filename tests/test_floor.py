"""The floor under the map and furniture standing on it (``perception.floor``; issue 24, centroid error).

A chair near a camera that looks down has its legs cut off by the image's lower edge in every view: its
visible part alone puts its centre too high. Rendered with exact depth (``tests/test_object_geometry.py``'s
room), the floor is found from the keyframes and the chair reaches down to it.
"""

from __future__ import annotations

import numpy as np

from perception.floor import Floor, FloorConfig, level_plane, on_floor, world_plane
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
    world = world_plane(plane, pose)
    assert np.degrees(np.arccos(world[2] / np.linalg.norm(world[:3]))) < 1.0  # up is world z
    assert abs(world[3]) < 0.01  # the floor is z = 0


def test_the_floor_is_the_lowest_height_many_keyframes_agree_on() -> None:
    up = np.array([0.0, 0.0, 1.0])
    table = [np.r_[up, -0.75]] * 30  # table tops fill more images than the floor
    floor = [np.r_[up, 0.002 * k] for k in range(-4, 5)]
    noise = [np.r_[up, 0.3], np.r_[up, 0.31]]  # two planes below the floor: too few to be it
    estimate = Floor.estimate(np.array(table + floor + noise), FloorConfig())
    assert estimate is not None and abs(estimate.height) < 0.005 and estimate.support == len(floor)
    assert Floor.estimate(np.array(table[:4]), FloorConfig()) is None  # fewer than min_keyframes


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
    means = np.array([shelf.center, shelf.center])
    assert on_floor(means, np.stack([cov, cov]), np.ones(2), floor, FloorConfig()) is None
    low = means - [0.0, 0.0, 1.5]  # a suitcase whose visible part ends 0.25 m above the floor
    stretched = on_floor(low, np.stack([cov, cov]), np.ones(2), floor, FloorConfig())
    assert stretched is not None
    mean, new_cov = stretched
    assert np.isclose(mean[2], 0.375) and np.isclose(new_cov[2, 2], 0.75**2 / 12.0)
