"""Ground-truth object boxes measured from hand-marked pixels, a dataset's depth and its reference poses.

An object is marked by a polygon (colour pixels) in a few frames. The depth pixels inside each polygon
(depth registered to colour) are back-projected with the reference pose; a point is kept when at least two
of the object's marked views see it (depth agrees at its pixel) inside their polygon and no more of them see
it outside (``carve``): background seen through a gap of one view's polygon is seen outside the others, or by
none of them. The largest connected part of what remains, above the supporting plane, gets a box upright in
the floor's frame (``fit_box``): yaw from the footprint (smallest box area) or from the highest points (a
chair's back), extents between percentiles, bottom on the supporting plane. ``complete`` grows a side that no
view's depth could reach (a chair's seat under a table, a screen's depth) to a stated length.

Used by ``scripts/annotate_kitchen.py`` (which writes ``evaluation/data/*/objects_gt.json``) and its tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from perception.camera import pixels_to_points, points_to_pixels
from perception.frame import CameraModel
from perception.registration import depth_in_color


@dataclass(frozen=True)
class View:
    """One marked view: the frame's depth registered to colour (metres, NaN = none), its reference pose
    (camera-to-world, of the depth camera as the dataset's poses are) and the object's polygon (N, 2); in
    ``cut``, the vertices that are not on the object's outline (where an occluder or an unsure edge cuts it)."""

    frame: int
    depth: np.ndarray
    pose: np.ndarray
    polygon: np.ndarray
    cut: np.ndarray | None = None

    def mask(self) -> np.ndarray:
        return polygon_mask(self.polygon, *self.depth.shape)


@dataclass(frozen=True)
class Box:
    """An upright box (z up, the floor normal): centre, size along (yaw, yaw + 90 deg, up), yaw about up."""

    center: np.ndarray
    size: np.ndarray
    yaw: float

    def corners(self) -> np.ndarray:
        """The 8 corners (8, 3): bit 2 of the index is +x, bit 1 +y, bit 0 +z (in the box's own axes)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        local = signs * self.size / 2
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return self.center + local @ R.T

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Which of ``points`` (N, 3) lie inside the box grown by ``margin``."""
        d = points - self.center
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
        return np.all(np.abs(local) <= self.size / 2 + margin, axis=1)


BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def upright_frame(up: np.ndarray) -> np.ndarray:
    """The rotation from the dataset's world frame to an upright one: its z is ``up`` (a direction in the
    world frame), its x the world's x made horizontal, its y completes a right-handed frame."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    x = np.array([1.0, 0.0, 0.0]) - up[0] * up
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up])


def floor_plane(
    points: np.ndarray, gravity: np.ndarray, keep: float = 0.01, rounds: int = 5
) -> tuple[np.ndarray, float]:
    """(unit up normal, height along it) of the plane fitted to world ``points`` of the floor: least squares,
    refitted ``rounds`` times to the points within ``keep`` m of the last fit; the normal's sign is the one
    against ``gravity``."""
    down = np.asarray(gravity, float) / np.linalg.norm(gravity)
    inliers = points
    normal, height = -down, float(np.median(points @ -down))
    for _ in range(rounds):
        centre = inliers.mean(0)
        _, _, vt = np.linalg.svd(inliers - centre, full_matrices=False)
        normal = vt[2] if vt[2] @ down < 0 else -vt[2]
        height = float(centre @ normal)
        inliers = points[np.abs(points @ normal - height) < keep]
    return normal, height


def polygon_mask(polygon: np.ndarray, height: int, width: int) -> np.ndarray:
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [np.rint(np.asarray(polygon)).astype(np.int32)], 1)
    return mask.astype(bool)


def registered_depth(depth_m: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Depth at the colour pixels (metres, NaN = none), in the colour camera's frame."""
    return depth_in_color(depth_m, camera)


def view_points(view: View, camera: CameraModel, step: int = 2) -> np.ndarray:
    """World points (N, 3) of every ``step``-th depth pixel inside the view's polygon."""
    m = view.mask() & np.isfinite(view.depth) & (view.depth > 0)
    grid = np.zeros_like(m)
    grid[::step, ::step] = True
    v, u = np.nonzero(m & grid)
    in_color = pixels_to_points(u.astype(float), v.astype(float), view.depth[v, u].astype(float), camera.color)
    T = view.pose @ _color_to_depth(camera)
    return in_color @ T[:3, :3].T + T[:3, 3]


def project(points: np.ndarray, pose: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Colour pixels and depths (N, 3: u, v, z) of world ``points`` seen from ``pose`` (the depth camera's)."""
    T = np.linalg.inv(pose @ _color_to_depth(camera))
    local = points @ T[:3, :3].T + T[:3, 3]
    z = local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = points_to_pixels(local, camera.color)
    return np.stack([u, v, z], axis=1)


def votes(points: np.ndarray, views: list[View], camera: CameraModel, tol: float = 0.03, rel: float = 0.02):
    """Per point: how many views see it inside their polygon, and how many see it outside (a view sees a
    point when its depth at the point's pixel is within max(tol, rel * z) of the point's depth)."""
    inside_votes = np.zeros(len(points), int)
    outside_votes = np.zeros(len(points), int)
    for view in views:
        px = project(points, view.pose, camera)
        h, w = view.depth.shape
        with np.errstate(invalid="ignore"):
            u, v = np.rint(px[:, 0]), np.rint(px[:, 1])
            ok = (px[:, 2] > 0.1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        uu = np.where(ok, u, 0).astype(int)
        vv = np.where(ok, v, 0).astype(int)
        d = view.depth[vv, uu]
        with np.errstate(invalid="ignore"):
            seen = ok & np.isfinite(d) & (np.abs(px[:, 2] - d) < np.maximum(tol, rel * px[:, 2]))
        inside = view.mask()[vv, uu]
        inside_votes += seen & inside
        outside_votes += seen & ~inside
    return inside_votes, outside_votes


def carve(views: list[View], camera: CameraModel, step: int = 2) -> np.ndarray:
    """The object's world points: those of all views that two views see inside their polygons and no more
    views see outside."""
    points = np.concatenate([view_points(v, camera, step) for v in views])
    inside, outside = votes(points, views, camera)
    return points[(inside >= 2) & (outside <= inside)]


def largest_component(points: np.ndarray, voxel: float = 0.03) -> np.ndarray:
    """The points of the largest 26-connected group of occupied ``voxel`` cells."""
    if len(points) == 0:
        return points
    q = np.floor((points - points.min(0)) / voxel).astype(int)
    grid = np.zeros(q.max(0) + 1, bool)
    grid[tuple(q.T)] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    if n <= 1:
        return points
    of_point = labels[tuple(q.T)]
    counts = np.bincount(of_point)
    counts[0] = 0
    return points[of_point == np.argmax(counts)]


def fit_box(
    points: np.ndarray,
    bottom: float | None = None,
    yaw_from: str = "footprint",
    top: str = "max",
    percentile: float = 0.5,
) -> Box:
    """An upright box around upright-frame ``points``: horizontal extents between the ``percentile`` and
    100 - ``percentile`` percentiles along the yaw axes; yaw of the smallest such footprint (``footprint``)
    or along the highest tenth of the points (``top``: a chair's back rail, a screen); bottom at ``bottom``
    (the supporting plane) or the lowest points; top at the highest points (``max``, the 99.5th percentile)
    or at the most populated height (``plane``: a table top under the things on it)."""
    xy = points[:, :2]
    if yaw_from == "top":
        high = xy[points[:, 2] >= np.percentile(points[:, 2], 90)]
        _, vecs = np.linalg.eigh(np.cov((high - high.mean(0)).T))
        yaws = np.array([np.arctan2(vecs[1, 1], vecs[0, 1]) % np.pi])
    elif yaw_from == "footprint":
        yaws = np.radians(np.arange(0.0, 90.0, 0.5))
    else:
        raise ValueError(f"yaw_from must be 'footprint' or 'top', not {yaw_from!r}")
    best: tuple[float, float, np.ndarray, np.ndarray] | None = None
    for yaw in yaws:
        c, s = np.cos(yaw), np.sin(yaw)
        along = np.percentile(xy @ np.array([c, s]), [percentile, 100 - percentile])
        across = np.percentile(xy @ np.array([-s, c]), [percentile, 100 - percentile])
        area = float(np.ptp(along) * np.ptp(across))
        if best is None or area < best[0]:
            best = (area, float(yaw), along, across)
    assert best is not None
    _, yaw, along, across = best
    c, s = np.cos(yaw), np.sin(yaw)
    mid = along.mean() * np.array([c, s]) + across.mean() * np.array([-s, c])
    z = points[:, 2]
    if top == "plane":
        hist, edges = np.histogram(z, bins=np.arange(z.min(), z.max() + 0.01, 0.005))
        z_top = float(edges[np.argmax(hist)] + 0.0025)
    else:
        z_top = float(np.percentile(z, 99.5))
    z_bottom = float(np.percentile(z, 0.5)) if bottom is None else bottom
    return Box(
        np.array([mid[0], mid[1], (z_top + z_bottom) / 2]),
        np.array([np.ptp(along), np.ptp(across), z_top - z_bottom]),
        yaw,
    )


def complete(box: Box, axis: int, length: float, toward: np.ndarray) -> Box:
    """``box`` with its horizontal side ``axis`` (0: along the yaw, 1: across) grown to ``length`` (when
    shorter) towards the point ``toward`` (x, y), the opposite face kept: the depth of a chair whose seat is
    under the table, the width of one whose end no view's depth reached, the depth of a screen on a wall."""
    grow = length - box.size[axis]
    if grow <= 0:
        return box
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    direction = np.array([c, s]) if axis == 0 else np.array([-s, c])
    sign = 1.0 if float(np.dot(np.asarray(toward, float)[:2] - box.center[:2], direction)) >= 0 else -1.0
    size = box.size.copy()
    size[axis] = length
    center = box.center.copy()
    center[:2] += sign * grow / 2 * direction
    return Box(center, size, box.yaw)


def outline_box(views: list[View], camera: CameraModel, R: np.ndarray, points: np.ndarray, border: float = 2.0) -> Box:
    """The box of a flat upright object (a screen) whose depth is too sparse for its extents: the vertical
    plane of its upright-frame ``points`` (yaw along their footprint, offset at their median), and the
    extents of the polygon vertices that are not on the image border nor cut, their rays cut with that plane
    (``R``: upright frame from world). Zero thickness; ``complete`` gives it one."""
    xy = points[:, :2]
    _, vecs = np.linalg.eigh(np.cov((xy - xy.mean(0)).T))
    along = vecs[:, 1]
    normal = np.array([-along[1], along[0]])
    offset = float(np.median(xy @ normal))
    a, z = [], []
    for view in views:
        h, w = view.depth.shape
        poly = np.asarray(view.polygon, float)
        u, v = poly[:, 0], poly[:, 1]
        on_outline = (u > border) & (u < w - 1 - border) & (v > border) & (v < h - 1 - border)
        inner = poly[on_outline if view.cut is None else on_outline & ~view.cut]
        if len(inner) == 0:
            continue
        T = R @ (view.pose @ _color_to_depth(camera))[:3]  # upright frame from the colour camera
        rays = pixels_to_points(inner[:, 0], inner[:, 1], np.ones(len(inner)), camera.color) @ T[:, :3].T
        t = (offset - T[:2, 3] @ normal) / (rays[:, :2] @ normal)
        hits = T[:, 3] + t[:, None] * rays
        a += list(hits[:, :2] @ along)
        z += list(hits[:, 2])
    if not a:
        raise ValueError("no polygon vertex off the image border")
    a_mid, z_mid = (min(a) + max(a)) / 2, (min(z) + max(z)) / 2
    centre = a_mid * along + offset * normal
    return Box(
        np.array([centre[0], centre[1], z_mid]),
        np.array([max(a) - min(a), 0.0, max(z) - min(z)]),
        float(np.arctan2(along[1], along[0])),
    )


def _color_to_depth(camera: CameraModel) -> np.ndarray:
    """The transform from the colour camera's frame to the depth camera's (identity when registered)."""
    return np.eye(4) if camera.depth_to_color is None else np.linalg.inv(camera.depth_to_color)
