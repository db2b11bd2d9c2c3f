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

Its centre then lies half its depth in front of the backrest's back (``facing_camera``).

Pure computation, no I/O.
"""

from __future__ import annotations

import numpy as np

from perception.camera import Intrinsics, pixels_to_points
from perception.features import Box, FeatureVector

BACKREST_CLASSES: frozenset[str] = frozenset({"chair"})
"""Classes whose upper part is a backrest standing at their back."""

BACK_ONLY = 0.55
"""A view shows its backrest only when its lowest point lies above this share of its top's height over the
floor (a chair's seat lies at about half its height)."""

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


def hidden_below(depth_m: np.ndarray, K: Intrinsics, box: Box, nearest_z: float, up: np.ndarray, floor: float) -> bool:
    """Whether the strip of the image under ``box`` (its middle half across) shows something ``NEARER_M`` nearer
    (camera z) than ``nearest_z`` and ``RAISED_M`` above the floor (``up``, ``floor``: camera frame): something in
    front hides the object's lower part. False when the box reaches the image's bottom or the strip has too few
    pixels with depth."""
    h, w = depth_m.shape[:2]
    x1, y1, x2, y2 = box
    top = int(np.ceil(y2))
    bottom = min(h, top + max(STRIP_PX, round(STRIP_SHARE * (y2 - y1))))
    left, right = max(int(x1 + 0.25 * (x2 - x1)), 0), min(int(np.ceil(x2 - 0.25 * (x2 - x1))), w)
    if top >= h or right <= left:
        return False
    rows, cols = np.mgrid[top:bottom, left:right]
    z = depth_m[rows, cols].astype(np.float64)
    valid = np.isfinite(z) & (z > 0)
    if valid.sum() < VALID_SHARE * z.size or not valid.any():
        return False
    points = pixels_to_points(cols[valid].astype(float), rows[valid].astype(float), z[valid], K)
    hiding = (points[:, 2] < nearest_z - NEARER_M) & (points @ up - floor > RAISED_M)
    return float(hiding.mean()) >= HIDING_SHARE


def seen_over(points: np.ndarray, up: np.ndarray, floor: float, depth_m: np.ndarray, box: Box, K: Intrinsics) -> bool:
    """Whether a view's camera-frame ``points`` are a backrest seen from the front over something nearer
    (module docstring); ``floor``: the floor's height along the camera-frame ``up`` (up . p == floor)."""
    low, high = (float(v) - floor for v in np.percentile(points @ up, [2, 98]))
    if high <= 0.0 or low < BACK_ONLY * high:
        return False
    return hidden_below(depth_m, K, box, float(np.percentile(points[:, 2], 2)), up, floor)


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
