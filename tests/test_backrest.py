"""A chair seen across a table shows its backrest, its far side (``perception.backrest``; issue 24).

Rendered exactly: a table and a chair at its far side facing it, the chair as the scene family renders chairs
(seat, legs, backrest: ``sources.family_render.chair_parts``), the detector's box from the instance mask.
"""

from __future__ import annotations

import numpy as np
import pytest

from perception.amodal import detection_feature
from perception.backrest import NEARER_M, hidden_below, seat_below, seated, seen_over
from perception.camera import Intrinsics
from perception.features import FeatureConfig, FeatureVector, depth_points
from perception.frame import Detection
from perception.object_map import ObjectMapper
from sources.base import ObjectTruth
from sources.family_render import chair_parts
from sources.raycast import Renderer, box_surfaces, object_texture, room_surfaces, surface_texture
from sources.scene import look_rotation

W, H = 640, 480
K = Intrinsics(525.0, 525.0, (W - 1) / 2.0, (H - 1) / 2.0)
TABLE = ObjectTruth(1, "dining table", (4.5, 4.5, 0.375), (1.6, 0.8, 0.75), 0.0)
CHAIR = ObjectTruth(2, "chair", (4.5, 5.19, 0.45), (0.44, 0.46, 0.9), np.pi)  # faces -y: the table


def _renderer(objects: list[ObjectTruth]) -> Renderer:
    light = np.array([4.5, 4.5, 2.4])
    out = room_surfaces((9.0, 9.0, 2.6), light, lambda k, w, h: surface_texture(np.random.default_rng([5, k]), w, h))
    rng = np.random.default_rng(5)
    for o in objects:
        texture = object_texture(rng, max(o.size), rng.uniform(60.0, 200.0, 3))
        for part in chair_parts(o) if o.label == "chair" else [o]:
            out += box_surfaces(part, texture, light, rng)
    return Renderer(out, K, W, H)


def _pose(position: tuple[float, float, float], target: tuple[float, float, float] = CHAIR.center) -> np.ndarray:
    d = np.asarray(target) - np.asarray(position)
    pose = np.eye(4)
    yaw, pitch = np.arctan2(d[1], d[0]), np.arctan2(d[2], np.hypot(d[0], d[1]))
    pose[:3, :3] = look_rotation(np.array([yaw]), np.array([pitch]), np.zeros(1))[0]
    pose[:3, 3] = position
    return pose


def _errors(
    depth: np.ndarray, box: tuple[float, float, float, float], pose: np.ndarray, chair: ObjectTruth = CHAIR
) -> tuple[float, float]:
    """The level distance of a chair view's completed centre from the chair's true centre, with the floor known and
    without it."""
    up = pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    errors = []
    for floor in (-float(pose[2, 3]), None):  # the floor's height along up in the camera frame
        f = detection_feature(depth, K, box, "chair", 0, FeatureConfig(), up, floor=floor)
        assert f is not None
        world = pose[:3, :3] @ f.mean + pose[:3, 3]
        errors.append(float(np.linalg.norm(world[:2] - np.asarray(chair.center[:2]))))
    return errors[0], errors[1]


def _view(
    objects: list[ObjectTruth], position: tuple[float, float, float], chair: ObjectTruth = CHAIR
) -> tuple[bool, float, float]:
    """(whether the chair's view is a backrest seen over something, its completed centre's level distance from
    the chair's true centre with the floor known, and without it)."""
    pose = _pose(position)
    r = _renderer(objects).render(pose)
    depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
    v, u = np.nonzero(r.ids == chair.id)
    box = (float(u.min()), float(v.min()), float(u.max() + 1), float(v.max() + 1))
    up = pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    floor = -float(pose[2, 3])  # the floor's height along up in the camera frame
    over = seen_over(depth_points(depth, K, v, u), up, floor, depth, box, K)
    return (over, *_errors(depth, box, pose, chair))


@pytest.mark.parametrize("side", [-0.6, 0.0, 0.5])
def test_a_chair_seen_across_its_table_lies_in_front_of_its_backrest(side: float) -> None:
    over, error, as_box = _view([TABLE, CHAIR], (4.5 + side, 2.6, 1.4))
    assert over
    assert as_box > 0.2  # completed as a box: a chair's depth too far
    assert error < 0.08


def test_a_chair_pushed_in_under_its_table_lies_in_front_of_its_backrest() -> None:
    """Pushed in until its backrest stands 3 cm behind the table's far edge (the table, a solid box, hides its
    seat): what hides its lower part is only a few centimetres nearer than its backrest."""
    pushed = ObjectTruth(2, "chair", (4.5, 4.9 - 0.23 + 0.26, 0.45), (0.44, 0.46, 0.9), np.pi)
    over, error, as_box = _view([TABLE, pushed], (4.5, 2.6, 1.4), pushed)
    assert over
    assert as_box > 0.2
    assert error < 0.08


def test_only_what_stands_above_the_floor_under_a_box_hides_it() -> None:
    """A level camera 1.4 m above the floor; under a box at 5 m, the floor (nearer, as it always is just under a
    box when the camera looks down) does not hide what the box holds; a table top 0.75 m high, as near, does."""
    up, floor = np.array([0.0, -1.0, 0.0]), -1.4  # up . p == floor on the floor
    v = np.arange(H, dtype=float)[:, None] - K.cy
    box = (200.0, 250.0, 440.0, 400.0)
    with np.errstate(divide="ignore"):
        on_floor = np.where(v > 0, 1.4 * K.fy / v, np.nan) * np.ones((1, W))
        on_table = np.where(v > 0, 0.65 * K.fy / v, np.nan) * np.ones((1, W))
    assert np.nanmax(on_floor[400:430]) < 5.0 - NEARER_M and np.nanmax(on_table[400:430]) < 5.0 - NEARER_M
    assert not hidden_below(on_floor.astype(np.float32), K, box, 5.0, up, floor)
    assert hidden_below(on_table.astype(np.float32), K, box, 5.0, up, floor)
    assert not hidden_below(on_table.astype(np.float32), K, box, 1.5, up, floor)  # farther than the object
    # a table's far edge 6-18 cm nearer than the backrest, the wall 8 m away through the gap above it: half the strip
    gap = on_table.copy()
    gap[400:411] = 8.0
    assert hidden_below(gap.astype(np.float32), K, box, 2.05, up, floor)
    assert np.median(gap[400:422, 260:380]) > 2.05 - 0.1  # the strip's median alone is not 10 cm nearer


def test_a_chair_seen_from_behind_or_with_its_seat_in_view_is_completed_as_a_box() -> None:
    behind, error, as_box = _view([TABLE, CHAIR], (4.5, 7.4, 1.4))
    assert not behind and error == as_box and error < 0.1
    front, error, as_box = _view([CHAIR], (4.5, 2.6, 1.4))  # no table: its seat and legs show
    assert not front and error == as_box and error < 0.1


def test_a_rendered_chair_fills_its_box_to_every_face_with_its_backrest_at_its_back() -> None:
    parts = chair_parts(ObjectTruth(7, "chair", (2.0, 3.0, 0.45), (0.44, 0.46, 0.9), 0.3))
    c, s = np.cos(0.3), np.sin(0.3)
    lows, highs = [], []
    for p in parts:
        assert p.id == 7 and p.yaw == 0.3
        d = np.asarray(p.center) - np.array([2.0, 3.0, 0.45])
        local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])  # in the chair's frame
        lows.append(local - np.asarray(p.size) / 2.0)
        highs.append(local + np.asarray(p.size) / 2.0)
    half = np.array([0.22, 0.23, 0.45])
    assert np.all(np.min(lows, axis=0) >= -half - 1e-9) and np.all(np.max(highs, axis=0) <= half + 1e-9)
    np.testing.assert_allclose(np.min(lows, axis=0), -half, atol=1e-9)  # the box is the chair's truth
    np.testing.assert_allclose(np.max(highs, axis=0), half, atol=1e-9)
    back = max(range(len(parts)), key=lambda k: parts[k].size[2])  # the tallest part: the backrest
    assert highs[back][1] < -0.15 and highs[back][2] == pytest.approx(0.45)  # at -y (the chair faces +y), on top


@pytest.mark.parametrize(
    ("position", "target"), [((4.5, 4.7, 1.5), (4.5, 5.45, 0.8)), ((4.5, 4.6, 1.6), (4.5, 5.5, 0.85))]
)
def test_a_chair_whose_seat_front_the_image_cuts_lies_in_front_of_its_backrest(
    position: tuple[float, float, float], target: tuple[float, float, float]
) -> None:
    """Seen from its front and from above, close: the image's bottom edge cuts the seat's front, so the nearest
    points it shows are the seat's back half. Completed as a box, the chair lies a fifth of a metre beyond its
    centre; placed by its backrest and seat (``seated``), within 3 cm."""
    pose = _pose(position, target)
    r = _renderer([CHAIR]).render(pose)
    depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
    v, u = np.nonzero(r.ids == CHAIR.id)
    box = (float(u.min()), float(v.min()), float(u.max() + 1), float(v.max() + 1))
    assert box[3] == H  # cut by the image's bottom
    error, as_box = _errors(depth, box, pose)
    assert as_box > 0.15
    assert error < 0.03


def test_seated_needs_a_backrest_plate_and_a_seat_to_one_side() -> None:
    """A view of a backrest alone, or of a box (no plate), is left to the completion."""
    up, floor = np.array([0.0, -1.0, 0.0]), -1.4
    rng = np.random.default_rng(3)
    f = FeatureVector(np.array([0.0, 0.95, 3.3]), np.eye(3) * 0.01, 100, "chair")
    plate = np.column_stack(
        [rng.uniform(-0.22, 0.22, 400), -rng.uniform(0.0, 0.9, 400) + 1.4, 3.2 + rng.normal(0, 0.005, 400)]
    )
    assert seated(f, plate, up, floor) is None  # a backrest alone: no seat
    seat = np.column_stack([rng.uniform(-0.22, 0.22, 400), np.full(400, 1.4 - 0.45), rng.uniform(2.8, 3.2, 400)])
    moved = seated(f, np.vstack([plate, seat]), up, floor)  # the completion lies beyond the backrest
    assert moved is not None and moved.mean[2] == pytest.approx(3.2 - (0.44 - 0.05) / 2.0, abs=0.02)
    block = np.column_stack(
        [rng.uniform(-0.22, 0.22, 800), -rng.uniform(0.0, 0.9, 800) + 1.4, rng.uniform(2.8, 3.2, 800)]
    )
    assert seated(f, block, up, floor) is None  # solid: no plate


@pytest.mark.parametrize(
    ("position", "front"), [((4.5, 2.6, 1.4), True), ((4.9, 3.2, 1.5), True), ((4.5, 7.4, 1.4), False)]
)
def test_a_box_holding_a_backrest_alone_looks_under_it_for_the_seat(
    position: tuple[float, float, float], front: bool
) -> None:
    """The detector's box holds a chair's backrest alone (the pixels of its instance mask more than 0.47 m above
    the floor), the rest of the chair in view under it. Seen from the front, its seat shows under the box, in front
    of the backrest (``seat_below``): the chair lies in front of its backrest, where a box's completion puts it a
    chair's depth too far. Seen from behind, what shows under the box lies beyond the backrest: a box it is."""
    pose = _pose(position)
    r = _renderer([CHAIR]).render(pose)
    depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
    v, u = np.nonzero(r.ids == CHAIR.id)
    high = (depth_points(depth, K, v, u) @ pose[:3, :3].T + pose[:3, 3])[:, 2] > 0.47
    v, u = v[high], u[high]
    box = (float(u.min()), float(v.min()), float(u.max() + 1), float(v.max() + 1))
    up = pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    floor = -float(pose[2, 3])
    points = depth_points(depth, K, v, u)
    assert seat_below(depth, K, box, points, up, floor) == front
    assert not hidden_below(depth, K, box, float(np.percentile(points[:, 2], 2)), up, floor)  # nothing nearer
    error, as_box = _errors(depth, box, pose)
    if front:
        assert as_box > 0.2 and error < 0.08
    else:
        assert error == as_box < 0.1


def test_the_first_keyframes_place_a_chair_before_the_floor_is_agreed() -> None:
    """The floor needs several keyframes to agree on it (``FloorConfig.min_keyframes``); until then a keyframe's
    own level plane gives the backrest rules their floor (``ObjectMapper``): a chair seen across its table in the
    first keyframe lies in front of its backrest, not a chair's depth beyond it."""
    pose = _pose((4.5, 2.6, 1.4))
    r = _renderer([TABLE, CHAIR]).render(pose)
    depth = np.where(r.depth > 0, r.depth, np.nan).astype(np.float32)
    v, u = np.nonzero(r.ids == CHAIR.id)
    box = (float(u.min()), float(v.min()), float(u.max() + 1), float(v.max() + 1))
    mapper = ObjectMapper()
    mapper.add_keyframe(0, [Detection("chair", 0.9, box)], depth, K, pose)
    assert mapper.floor is None
    keyframe, view = mapper.observation(0)
    world = pose[:3, :3] @ view.mean + pose[:3, 3]
    assert keyframe == 0
    assert np.linalg.norm(world[:2] - np.asarray(CHAIR.center[:2])) < 0.08
