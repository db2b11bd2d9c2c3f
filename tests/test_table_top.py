"""A table's view from its top (perception.table_top): the top's extent, not its chairs' or its completion's."""

from __future__ import annotations

import numpy as np

from perception.table_top import top_height, top_view

FX, W, H = 525.0, 640, 480


def camera_looking_down(pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotation camera -> world (camera x right, y down, z forward; world x right, y up, z ahead) of a camera
    pitched down by ``pitch_deg``, and the world's up in the camera frame."""
    a = np.radians(pitch_deg)
    # the camera's forward axis points ahead and down, its down axis ahead-down-ish
    R = np.array([[1.0, 0.0, 0.0], [0.0, -np.cos(a), -np.sin(a)], [0.0, -np.sin(a), np.cos(a)]])
    return R, R.T @ np.array([0.0, 1.0, 0.0])


def rendered(R: np.ndarray, eye: np.ndarray, hit) -> np.ndarray:
    """Camera-frame points of every pixel whose ray ``hit`` (world origin, world direction) -> world point or
    None meets a surface."""
    u, v = np.meshgrid(np.arange(0, W, 2) + 0.5, np.arange(0, H, 2) + 0.5)
    rays = np.stack([(u - W / 2) / FX, (v - H / 2) / FX, np.ones_like(u)], -1).reshape(-1, 3)
    out = []
    for ray in rays:
        p = hit(eye, R @ ray)
        if p is not None:
            out.append(R.T @ (p - eye))
    return np.array(out)


def table_and_chair(size=(0.8, 2.0), centre=(0.0, 2.5), height=0.75, chair=(0.55, 2.0)):
    """A ray caster for a table top (x across, z along) and a chair back beside it, 0.5 m wide, 0.45-0.95 m
    high, standing across the ray at ``chair``; world y up, floor at 0."""

    def hit(eye, d):
        best = None
        if d[1] < 0:  # the top, from above
            t = (height - eye[1]) / d[1]
            p = eye + t * d
            if abs(p[0] - centre[0]) <= size[0] / 2 and abs(p[2] - centre[1]) <= size[1] / 2:
                best = (t, p)
        if abs(d[2]) > 1e-9:  # the chair's back: the plane z = chair[1]
            t = (chair[1] - eye[2]) / d[2]
            p = eye + t * d
            if t > 0 and abs(p[0] - chair[0]) <= 0.25 and 0.45 <= p[1] <= 0.95 and (best is None or t < best[0]):
                best = (t, p)
        return None if best is None else best[1]

    return hit


def test_a_table_seen_along_its_length_is_its_top_long_and_wide_not_its_chair_and_not_its_pixels_density():
    R, up = camera_looking_down(30.0)
    eye = np.array([0.0, 1.4, 0.6])
    points = rendered(R, eye, table_and_chair())
    assert len(points) > 1000
    mean, cov = top_view(points, up)
    world_mean = R @ mean + eye
    for axis, lo, hi in ((np.array([1.0, 0.0, 0.0]), -0.4, 0.4), (np.array([0.0, 0.0, 1.0]), 1.5, 3.5)):
        a = R.T @ axis  # the world axis in the camera frame
        half = np.sqrt(3.0 * a @ cov @ a)
        centre = float(axis @ world_mean)
        assert abs(centre - half - lo) < 0.05 and abs(centre + half - hi) < 0.05, (axis, centre - half, centre + half)
    # the same points' own moments: the near end, densest in the image, pulls the centre to the camera
    plain = points.mean(axis=0)
    assert float(np.array([0.0, 0.0, 1.0]) @ (R @ plain + eye)) < 2.3


def test_the_top_is_the_highest_full_band_not_the_fullest():
    rng = np.random.default_rng(0)
    seat = rng.normal(0.45, 0.005, 3000)  # a chair's seat below the top, more of it in view
    top = rng.normal(0.75, 0.005, 2000)
    bottle = rng.normal(0.9, 0.05, 100)  # things on the table: high but sparse
    assert abs(top_height(np.concatenate([seat, top, bottle])) - 0.75) < 0.015


def test_a_view_that_shows_no_top_is_left_to_the_completion():
    R, up = camera_looking_down(5.0)
    eye = np.array([0.0, 0.7, 0.6])  # a low robot's camera, below the top: the chair's back alone in view
    points = rendered(R, eye, table_and_chair())
    assert len(points) > 1000
    assert top_view(points, up) is None  # the back's upper edge is its highest full band, and a line
    assert top_view(rendered(R, np.array([0.0, 1.4, 0.6]), table_and_chair()), up) is not None
