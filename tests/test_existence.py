"""An object that stood in view far more often than it was detected is not kept (``perception.existence``)."""

from __future__ import annotations

import numpy as np
import pytest

from perception.camera import Intrinsics
from perception.existence import MAX_KEPT, MIN_LOOKS, MIN_RATE, Looks, exists, judged

K = Intrinsics(500.0, 500.0, 320.0, 240.0)
SIZE = (640, 480)


def camera_at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    """A camera-to-world pose at (x, 0, 0), looking along +z turned by ``yaw_deg`` about y."""
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    T[0, 3] = x
    return T


def backed(z: float) -> np.ndarray:
    """A camera-to-world pose at (0, 0, -z), looking along +z."""
    T = np.eye(4)
    T[2, 3] = -z
    return T


def ball(half: float) -> np.ndarray:
    """The covariance of an object ``half`` metres across each way (uniform: half = sqrt(3) std)."""
    return np.eye(3) * half**2 / 3.0


def judge(centres: list[list[float]], halves: list[float], seen: list[set[int]], poses: np.ndarray) -> list[bool]:
    covs = np.stack([ball(h) for h in halves])
    return judged(np.array(centres), covs, seen, np.arange(len(poses)), poses, (K, SIZE))


def test_an_object_seen_in_few_of_the_keyframes_that_looked_at_it_is_not_kept() -> None:
    poses = np.stack([camera_at(0.02 * i) for i in range(50)])
    centre = [0.3, 0.1, 2.5]
    assert judge([centre], [0.1], [{0, 10, 20, 30, 40}], poses) == [False]  # 5 of 50
    assert judge([centre], [0.1], [set(range(0, 50, 3))], poses) == [True]  # 17 of 50
    assert judge([centre], [0.1], [set()], poses) == [True]  # never detected here: not judged
    assert exists(0, 0) and exists(1, MIN_LOOKS - 1)  # too few looks to judge
    assert exists(int(np.ceil(MIN_RATE * 40)), 40) and not exists(int(np.ceil(MIN_RATE * 40)) - 1, 40)


def test_a_keyframe_looks_at_what_is_inside_its_image_in_front_and_within_reach() -> None:
    centre = [0.0, 0.0, 2.0]
    seen = {0, 1}  # from straight ahead, 2 m away
    ahead = [camera_at(0.0)] * 2
    for away, looks in [
        ([camera_at(0.0)], True),
        ([camera_at(0.0, 180.0)], False),  # looking away
        ([camera_at(0.0, 60.0)], False),  # 60 degrees off its axis: outside a 65-degree-wide image
        ([camera_at(1.9)], False),  # x / z = -0.95 -> -155 px, left of the image
        ([camera_at((640 - 3 - 320) / 500.0 * 2.0)], False),  # 3 px inside the image's side: within the margin
        ([backed(3.0)], False),  # 5 m away: farther than any keyframe that detected it
    ]:
        poses = np.stack(ahead + away * 60)
        # a pose that looks at it makes 62 looks, so it needs ceil(0.25 * 62) = 16 detections; one that does
        # not leaves 2 looks, too few to judge: kept as it is
        assert judge([centre], [0.1], [seen], poses) == [not looks], away


def test_a_keyframe_in_which_another_object_stands_in_front_did_not_look() -> None:
    poses = np.stack([camera_at(0.0)] * 10 + [camera_at(0.005 * i) for i in range(50)])
    back, front = [0.0, 0.0, 3.0], [0.0, 0.0, 1.5]
    # the back object was detected 10 times; alone, the 50 other keyframes looked at it
    assert judge([back], [0.2], [set(range(10))], poses) == [False]
    # with an object 0.3 m wide standing in front of it in all of them, they did not
    assert judge([back, front], [0.2, 0.15], [set(range(10)), set(range(60))], poses) == [True, True]
    # an object beside the sight lines, not on them, hides nothing
    assert judge([back, [0.6, 0.0, 1.5]], [0.2, 0.15], [set(range(10)), set(range(60))], poses) == [False, True]


def test_a_long_low_object_in_front_hides_only_what_is_behind_it_not_what_shows_above_it() -> None:
    """A table 1.8 m long in front of a chair's back: the sight lines to the chair pass over the table top. The
    table's longest half size (0.9 m) as a ball around its centre would cover them."""
    poses = np.stack([camera_at(0.0)] * 10 + [camera_at(0.005 * i) for i in range(50)])
    chair = [0.0, -0.3, 3.0]  # camera frame: y down, so 0.3 m above the camera's height
    table = np.diag([0.9, 0.1, 0.45]) ** 2 / 3.0  # half sizes 0.9 x 0.1 x 0.45 m
    covs = np.stack([ball(0.2), table])
    seen = [set(range(10)), set(range(60))]
    below = judged(np.array([chair, [0.0, 0.3, 1.8]]), covs, seen, np.arange(60), poses, (K, SIZE))
    assert below == [False, True]  # the sight lines pass 0.48 m over the table's centre, 0.38 m over its top
    tall = np.stack([ball(0.2), np.diag([0.9, 0.6, 0.45]) ** 2 / 3.0])  # a top reaching 0.3 m above its centre
    assert judged(np.array([chair, [0.0, 0.3, 1.8]]), tall, seen, np.arange(60), poses, (K, SIZE)) == [True, True]
    # a couch 2 m deep around the chair, its centre 0.2 m behind the chair's: the chair stands inside its
    # ellipsoid, in front of its centre, and is not hidden by it
    couch = np.diag([1.0, 1.0, 1.0]) ** 2 / 3.0
    assert judged(
        np.array([chair, [0.0, -0.3, 3.2]]), np.stack([ball(0.2), couch]), seen, np.arange(60), poses, (K, SIZE)
    ) == [False, True]


def test_looks_keep_the_newest_keyframes_move_with_the_poses_and_survive_a_restart() -> None:
    looks = Looks()
    centre, cov = np.array([[0.0, 0.0, 2.0]]), ball(0.1)[None]
    assert looks.judged(centre, cov, [{0}]) == [True]  # nothing looked yet: every object is kept
    for k in range(60):
        looks.add(k, camera_at(0.01 * k), K, SIZE)
    assert looks.judged(centre, cov, [{0, 1, 2}]) == [False]
    assert looks.judged(centre, cov, [set(range(0, 60, 2))]) == [True]
    looks.moved({k: camera_at(0.01 * k, 180.0) for k in range(3, 60)})  # now the others look away
    assert looks.judged(centre, cov, [{0, 1, 2}]) == [True]
    again = Looks()
    again.restore(looks.state())
    assert list(again.poses) == list(looks.poses) and again.camera == looks.camera
    assert all(np.allclose(again.poses[k], looks.poses[k], atol=1e-6) for k in looks.poses)  # single precision
    assert again.judged(centre, cov, [{0, 1, 2}]) == [True]
    old = Looks()
    old.restore({})  # a state from before looks were kept
    assert old.camera is None and not old.poses


def test_looks_are_bounded() -> None:
    looks = Looks()
    for k in range(MAX_KEPT + 25):
        looks.add(k, np.eye(4), K, SIZE)
    assert len(looks.poses) == MAX_KEPT and min(looks.poses) == 25


@pytest.mark.parametrize("use_existence", [True, False])
def test_a_plant_made_of_a_plant_s_misplaced_views_is_not_mapped(use_existence: bool) -> None:
    """Development seed 20: seven views of a potted plant whose box centre showed a nearer surface (by a bottle,
    1.0 m in front of the plant) made a second "potted plant" there; that place was in view in about 48
    keyframes."""
    from bench.objects_family import FAMILY_FRAMES, keyframes
    from evaluation.object_metrics import match_objects
    from perception.keyframing import KeyframeSettings
    from perception.object_map import ObjectMapper
    from sources.synthetic import parse_synthetic_spec

    data = parse_synthetic_spec(f"synthetic:family?seed=20&frames={FAMILY_FRAMES}&width=640&height=480")
    poses = data.ground_truth.poses
    mapper = ObjectMapper()
    if not use_existence:
        mapper.clusterer.judge = None
    for i in sorted(keyframes(poses, KeyframeSettings())):
        frame = data.frame(i)
        mapper.add_keyframe(i, list(frame.detections or []), frame.depth_m(), data.camera.color, poses[i])
    objects = mapper.finish()
    matched = {a for a, _ in match_objects(objects, data.objects)}
    false_plants = [o for a, o in enumerate(objects) if a not in matched and o.label == "potted plant"]
    assert len(false_plants) == (0 if use_existence else 1)
    assert len(matched) >= 20
    # the clusterer still holds the object it did not show, and counts it (status: objects_unconfirmed)
    hidden = [o for o in mapper.clusterer.objects if o.id in mapper.clusterer.unkept]
    assert len(hidden) >= (1 if use_existence else 0) and not {o.id for o in hidden} & {o.id for o in objects}
    if use_existence:
        assert any(o.label == "potted plant" and np.linalg.norm(o.mean[:2] - [0.58, 5.55]) < 0.1 for o in hidden)
    restored = ObjectMapper()
    restored.restore(mapper.state())
    assert [o.id for o in restored.objects] == [o.id for o in objects]
