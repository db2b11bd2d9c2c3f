"""A chair seen from its front over something nearer shows its backrest: its far side (issue 24).

The completion behind a view's visible surface (``amodal.complete_amodal``) puts an object's centre half its
depth behind the nearest points it shows. That holds for a box from every side, and for a chair seen from
behind (its backrest is its near side) or from its front with its seat in view (the seat's front edge is). A
chair at a table, seen across the table, shows its backrest alone: the table hides its seat and legs, and its
backrest is the chair's back. Completed as a box, it lies a chair's depth too far from the camera: the 7-Scenes
chairs across the table lay 0.19-0.24 m too far along the ray, and on the development scenes, once chairs were
rendered as chairs (``sources.family_render.chair_parts``), a tenth of the chairs lay 0.18 m or more towards
their backs.

A chair's view is taken as its backrest seen from the front (``seen_over``) when both hold:

- its lowest visible point lies above ``BACK_ONLY`` of its highest one over the floor: no seat shows (a chair's
  seat is at about half its height);
- just under its box, a share of the image (``HIDING_SHARE``) shows something nearer than the chair
  (``NEARER_M``) and well above the floor (``RAISED_M``): what hides its lower part stands in front of it. A chair
  seen from behind has its table behind it; a chair with its seat hidden by its own backrest has the floor or the
  seat under the box, not nearer. A chair pushed in under its table shows its backrest a few centimetres behind
  the table's far edge (the 7-Scenes chair on the table's far side by the red cabinets: 6-7 cm in the views looked
  at, with the wall showing through the gap above the table in part of the strip), which a margin of 10 cm on the
  strip's median missed; the floor, always nearer just under a box when the camera looks down, is what the height
  test leaves out.

Or when its lowest point lies above ``SEAT_TOP`` of its top and the strip under its box shows the chair's own
seat reaching out in front of its backrest (``seat_below``). The detector's box may hold the backrest alone, the
seat in view just under it: the 7-Scenes chair at the left end of the table in frames 48-68, seen from its
front-left (the seat at a seat's height in 52-93 % of the strip, 5 cm or more in front of the backrest; 0 % under
the other chairs' boxes). Its backrest's views, completed as a box, lay 0.2-0.3 m beyond it and made a second
chair. Seen from behind, the strip under a backrest shows its lower edge, the legs and what lies beyond.

Its centre then lies half its depth in front of the backrest's back (``facing_camera``).

A chair whose view shows both its backrest and its seat is placed by them (``seated``): the backrest is a thin
upright plate at its back, the seat lies on one side of it, and the chair's centre lies half its depth from the
plate on that side, whatever the view's nearest points are. A view completed less than half that from the plate
(or beyond it) took the wrong side and is moved out to it. Seen from its front and from above, with the image's
bottom edge cutting its seat's front, the 7-Scenes chair at the left end of the table, completed as a box, lay
0.24 m beyond its centre along the ray.

Pure computation, no I/O.
"""

from __future__ import annotations

import numpy as np

from perception.camera import Intrinsics, pixels_to_points
from perception.features import Box, FeatureVector
from perception.footprint import level_basis

BACKREST_CLASSES: frozenset[str] = frozenset({"chair"})
"""Classes whose upper part is a backrest standing at their back."""

BACK_ONLY = 0.55
"""A view shows its backrest only when its lowest point lies above this share of its top's height over the
floor (a chair's seat lies at about half its height)."""

SEAT_TOP = 0.5
"""A view whose lowest point lies above this share of its top's height over the floor holds no seat, whose top
lies at about half a chair's height (``seat_below``: the seat may show under its box)."""

NEARER_M = 0.02
"""Under the box, what lies this much nearer than the view's nearest points (and ``RAISED_M`` above the floor)
hides the object's lower part."""

RAISED_M = 0.25
"""...and this far above the floor: a table top, a couch, a counter, not the floor."""

STRIP_SHARE = 0.15
"""The strip under a box that is looked at: this share of the box's height (at least ``STRIP_PX`` rows)..."""

STRIP_PX = 4

VALID_SHARE = 0.3
"""...of which at least this share of pixels must have depth, and of those at least ``HIDING_SHARE`` must hide
the object (between a backrest and the table before it, the strip may show the wall through the gap)."""

HIDING_SHARE = 0.3

BACKREST_M = 0.05
"""A backrest's thickness: its visible front lies this much in front of the chair's back."""


SEAT_BAND = (0.35, 0.62)
"""A chair's seat lies between these shares of its top's height over the floor (``seated``)..."""

BACK_BAND = 0.8
"""...and its backrest above this share (above armrests)."""

PLATE_M = 0.08
"""A backrest is a plate: 80 % of its points lie within this depth of each other across it..."""

PLATE_WIDTH_M = 0.25
"""...and it is at least this wide..."""

PLATE_FACING = 0.5
"""...and faces the camera within 60 degrees (the cosine): seen at a grazing angle, a backrest's pixels spread
along the ray (on the development scenes, chairs seen from their sides gave 'plates' 0.7-1.1 m wide)."""

SEAT_M = 0.1
"""The seat reaches this far to one side of the backrest's plate, and less than half that to the other."""

MIN_POINTS = 30
"""Points each of the seat and the backrest need."""

WRONG_SHARE = 0.5
"""A completed view is moved only when its centre lies less than this share of half the chair's depth from the
backrest towards the seat (or beyond the backrest): the side of the backrest the completion took is wrong. The
depth (``seated``) is a rough one; applied to every view nearer than the whole half-depth, it moved chairs seen
whole 1-5 cm towards their front (development seeds 0-35: the scenes' median error 0.029 -> 0.037 m)."""


def _under(depth_m: np.ndarray, K: Intrinsics, box: Box, whole: bool = False) -> np.ndarray | None:
    """The camera-frame points of the strip of the image under ``box`` (its middle half across): None when the box
    reaches the image's bottom (with ``whole``, when the image's bottom cuts the strip) or the strip has too few
    pixels with depth (``VALID_SHARE``)."""
    h, w = depth_m.shape[:2]
    x1, y1, x2, y2 = box
    top = int(np.ceil(y2))
    tall = max(STRIP_PX, round(STRIP_SHARE * (y2 - y1)))
    bottom = min(h, top + tall)
    left, right = max(int(x1 + 0.25 * (x2 - x1)), 0), min(int(np.ceil(x2 - 0.25 * (x2 - x1))), w)
    if top >= h or right <= left or (whole and bottom - top < tall):
        return None
    rows, cols = np.mgrid[top:bottom, left:right]
    z = depth_m[rows, cols].astype(np.float64)
    valid = np.isfinite(z) & (z > 0)
    if valid.sum() < VALID_SHARE * z.size or not valid.any():
        return None
    return pixels_to_points(cols[valid].astype(float), rows[valid].astype(float), z[valid], K)


def hidden_below(depth_m: np.ndarray, K: Intrinsics, box: Box, nearest_z: float, up: np.ndarray, floor: float) -> bool:
    """Whether the strip of the image under ``box`` (its middle half across) shows something ``NEARER_M`` nearer
    (camera z) than ``nearest_z`` and ``RAISED_M`` above the floor (``up``, ``floor``: camera frame): something in
    front hides the object's lower part. False when the box reaches the image's bottom or the strip has too few
    pixels with depth."""
    points = _under(depth_m, K, box)
    if points is None:
        return False
    hiding = (points[:, 2] < nearest_z - NEARER_M) & (points @ up - floor > RAISED_M)
    return float(hiding.mean()) >= HIDING_SHARE


def seat_below(depth_m: np.ndarray, K: Intrinsics, box: Box, points: np.ndarray, up: np.ndarray, floor: float) -> bool:
    """Whether the strip of the image under the box of a backrest's view (camera-frame ``points``) shows the
    chair's seat in front of the backrest, reaching out from it: of the strip's points at a seat's height
    (``SEAT_BAND`` of the view's top), a ``HIDING_SHARE`` of the strip lie ``NEARER_M`` nearer than the backrest's
    median, and the nearest 5 % of them within ``SEAT_M`` of it. Distances are level (camera z grows downwards at one
    distance when the camera looks down). Seen from behind, the strip under a backrest shows its own lower edge,
    the seat's back edge and the legs, as far as the backrest, or what lies beyond it; under a box that holds the
    seat, the seat's front edge, well in front of the backrest. Not judged on a strip the image's bottom cuts."""
    strip = _under(depth_m, K, box, whole=True)
    top = float(np.percentile(points @ up - floor, 98))
    if strip is None or top <= 0.0:
        return False
    height = strip @ up - floor
    seat_high = (height >= SEAT_BAND[0] * top) & (height <= SEAT_BAND[1] * top)
    if not seat_high.any():
        return False
    back = float(np.median(np.linalg.norm(points - np.outer(points @ up, up), axis=1)))
    before = back - np.linalg.norm(strip - np.outer(strip @ up, up), axis=1)  # how far in front of the backrest
    reaching = float(np.percentile(before[seat_high], 5)) < SEAT_M
    return reaching and float((seat_high & (before > NEARER_M)).mean()) >= HIDING_SHARE


def seen_over(points: np.ndarray, up: np.ndarray, floor: float, depth_m: np.ndarray, box: Box, K: Intrinsics) -> bool:
    """Whether a view's camera-frame ``points`` are a backrest seen from the front over something nearer, or with
    its seat under its box (module docstring); ``floor``: the floor's height along the camera-frame ``up``
    (up . p == floor)."""
    low, high = (float(v) - floor for v in np.percentile(points @ up, [2, 98]))
    if high <= 0.0 or low < SEAT_TOP * high:
        return False
    if low >= BACK_ONLY * high and hidden_below(depth_m, K, box, float(np.percentile(points[:, 2], 2)), up, floor):
        return True
    return seat_below(depth_m, K, box, points, up, floor)


def facing_camera(f: FeatureVector, up: np.ndarray) -> FeatureVector:
    """A completed view (its centre half its depth behind its nearest points, along the level ray) turned into
    one whose nearest points are the back: the centre moves towards the camera by its depth less
    ``BACKREST_M``."""
    level = f.mean - (f.mean @ up) * up
    norm = float(np.linalg.norm(level))
    if norm == 0.0:
        return f
    ray = level / norm
    depth = float(np.sqrt(12.0 * max(float(ray @ f.cov @ ray), 0.0)))
    mean = f.mean - max(depth - BACKREST_M, 0.0) * ray
    return FeatureVector(mean, f.cov, f.n, f.label, f.track_id, f.sources)


def seated(f: FeatureVector, points: np.ndarray, up: np.ndarray, floor: float) -> FeatureVector | None:
    """A completed chair view ``f`` moved out to half the chair's depth from its backrest towards its seat (module
    docstring) when the completion put it on the wrong side (``WRONG_SHARE``), else None; None too when the view's
    camera-frame ``points`` do not show both a backrest plate facing the camera and a seat to one side of it. The
    depth is the larger of the plate's width (a chair is about as deep as it is wide) and the seat's reach from
    the plate; only the centre's distance from the plate changes."""
    heights = points @ up - floor
    top = float(np.percentile(heights, 98))
    if top <= 0.0:
        return None
    back = points[heights >= BACK_BAND * top]
    seat = points[(heights >= SEAT_BAND[0] * top) & (heights <= SEAT_BAND[1] * top)]
    if len(back) < MIN_POINTS or len(seat) < MIN_POINTS:
        return None
    level = level_basis(up)
    origin = np.median(back, axis=0)
    flat = (back - origin) @ level
    across, plate = _thinnest(flat)
    along = np.array([-across[1], across[0]])
    width_ends = np.percentile(flat @ along, [2, 98])
    ray = origin @ level
    facing = abs(float(across @ ray)) / max(float(np.linalg.norm(ray)), 1e-9)
    if plate[2] - plate[0] > PLATE_M or width_ends[1] - width_ends[0] < PLATE_WIDTH_M or facing < PLATE_FACING:
        return None
    reach = np.percentile((seat - origin) @ level @ across - plate[1], [10, 90])
    if reach[0] < -SEAT_M and reach[1] < SEAT_M / 2:
        side, depth = -1.0, float(max(width_ends[1] - width_ends[0], -reach[0]))
    elif reach[1] > SEAT_M and reach[0] > -SEAT_M / 2:
        side, depth = 1.0, float(max(width_ends[1] - width_ends[0], reach[1]))
    else:
        return None
    offset = side * (float((f.mean - origin) @ level @ across) - plate[1])  # from the plate towards the seat
    least = (depth - BACKREST_M) / 2.0
    if offset >= WRONG_SHARE * least:
        return None
    mean = f.mean + side * (least - offset) * (level @ across)
    return FeatureVector(mean, f.cov, f.n, f.label, f.track_id, f.sources)


PLATE_ANGLES = 36
"""Level directions (over half a turn) tried for a backrest plate's normal (``_thinnest``)."""


def _thinnest(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The level unit direction along which 2-D points ``flat`` lie thinnest (their 10th to 90th percentile),
    and their 10th, 50th and 90th percentiles along it: a backrest's normal. Robust where a least-squares fit is
    not: the pixels at a backrest's edges mix it with what lies behind, and spread along the ray."""
    angles = np.linspace(0.0, np.pi, PLATE_ANGLES, endpoint=False)
    normals = np.column_stack([np.cos(angles), np.sin(angles)])
    spread = np.percentile(flat @ normals.T, [10, 50, 90], axis=0)
    best = int(np.argmin(spread[2] - spread[0]))
    return normals[best], spread[:, best]
