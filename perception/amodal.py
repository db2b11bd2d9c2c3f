"""Amodal completion of a detection's view: where the unseen part of an object lies (SPEC 6.5, issue 24).

A depth camera sees the near side of an object, often only part of it (the image border, the sensor's range and
occluders cut it). ``detection_feature`` turns a detection into its camera-frame feature vector with the
object's centre and extent completed behind the visible surface (``complete_amodal``), bounded by the free depth
behind it (``room_behind``), and, where the world's up is known, completed level with the floor and measured
vertically by its points' span down to the surface it stands on (``vertical_extent``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt, uniform_filter

from perception.backrest import BACKREST_CLASSES, facing_camera, seated, seen_over
from perception.camera import Intrinsics, pixels_to_points
from perception.features import (
    PANEL_DEPTH_M,
    Box,
    DepthSegment,
    FeatureConfig,
    FeatureVector,
    Segmented,
    depth_points,
    feature_from_points,
    object_pixels,
    ring_windows,
    stride_subsample,
)
from perception.floor import view_ends, with_span
from perception.footprint import LARGE_CLASSES
from perception.pixel_grid import grid_of
from perception.support import split_support
from perception.table_top import TOP_CLASSES, top_view

NO_RETURN_SHARE = 0.2
"""A ring around a box with more than this share of pixels without depth does not bound the room behind the object
(``room_behind``). Chairs 4-5 m away with the synthetic sensor's 4 m range had their far side bounded by the
floor's farthest returns and lay 0.12 m too near the camera (development scenes with laps looking inward)."""


def room_behind(
    depth_m: np.ndarray,
    box: Box,
    rows: np.ndarray,
    cols: np.ndarray,
    ring: float = 0.15,
    step: int = 4,
    share: float | None = None,
) -> float:
    """Free depth behind an object's visible surface (its pixels ``rows``, ``cols``): the ``share`` percentile
    (default ``ROOM_SHARE``) of how far the pixels of a ring around its box (``ring`` of the box size wide) lie
    behind the nearest object pixel, counting only those behind it (a floor or table beside the object lies partly
    behind it too); inf when none are. Measured against the nearest pixel of the surface rather than its nearest
    point, so a screen on a wall seen from below or at a slant is bounded by the wall just behind it. Pixels on a
    ``step`` grid. A ring with more than ``NO_RETURN_SHARE`` of its pixels without depth bounds nothing (inf): what
    lies behind is beyond the sensor's range, and the farthest returns (the floor beside the object up to that
    range) are no wall.
    """
    windows = ring_windows(depth_m.shape, box, ring)
    if windows is None or len(rows) == 0:
        return np.inf
    (y1, y2, x1, x2), inner = windows
    patch = depth_m[y1:y2:step, x1:x2:step].copy()
    surface = np.full(patch.shape, np.nan, np.float32)
    some = stride_subsample(len(rows), surface.size)  # enough to mark most cells the object covers
    r, c = rows[some], cols[some]
    surface[(r - y1) // step, (c - x1) // step] = depth_m[r, c]
    # the first grid cell at or after each edge of the box
    iy1, iy2, ix1, ix2 = (-(-(v - o) // step) for v, o in zip(inner, (y1, y1, x1, x1), strict=True))
    in_ring = np.ones(patch.shape, bool)
    in_ring[iy1:iy2, ix1:ix2] = False
    patch[~in_ring] = np.nan  # the ring only
    is_surface = np.isfinite(surface)
    if not is_surface.any() or np.isnan(patch[in_ring]).mean() > NO_RETURN_SHARE:
        return np.inf
    around = np.isfinite(patch)
    _, (ny, nx) = distance_transform_edt(~is_surface, return_indices=True)  # each cell's nearest surface cell
    gap = patch[around] - surface[ny[around], nx[around]]
    behind = gap[gap > 0.01]
    return float(np.percentile(behind, ROOM_SHARE if share is None else share)) if behind.size else np.inf


ROOM_SHARE = 90.0
"""The free depth behind an object (``room_behind``) is this percentile of the ring's, unless told otherwise."""

PANEL_ROOM_SHARE = 50.0
"""A panel's free depth behind it (``room_behind``) is this percentile of the ring's: a screen on a wall stands off
it by the same depth all round, and the wall beside the far end of a screen seen at a slant recedes."""


BORDER_PX = 4
"""A box within this many pixels of the image border is cut by it..."""

BORDER_SHARE = 0.05
"""...or within this share of its own width (height) of the left or right (top or bottom) border: a detector's box
is off by a few percent of its size, so the box of an object the border cuts can end a few pixels inside it. On
14 of the development seeds (0, 3, 8, 11, 15, 17, 19, 22, 24, 27, 30, 32, 34, 35; views of every class whose
depth segment is mostly their object's), the top edge of the boxes whose
object's box projects above the image lay 8.4 px (0.04 of the box's height) below it at the 90th percentile; of
724 such views 170 were taken as uncut with ``BORDER_PX`` alone, 44 with this, and 31 of 11170 uncut views were
taken as cut (20 with ``BORDER_PX`` alone)."""


def _margins(box: Box) -> tuple[float, float]:
    """How near the image border a box's side (left or right, top or bottom) must lie to be cut by it."""
    return max(BORDER_PX, BORDER_SHARE * (box[2] - box[0])), max(BORDER_PX, BORDER_SHARE * (box[3] - box[1]))


def cut_by_border(box: Box, width: int, height: int) -> tuple[bool, bool]:
    """Whether the image border cuts ``box`` on the left or right, and at the top or bottom."""
    x1, y1, x2, y2 = box
    mx, my = _margins(box)
    return (x1 < mx or x2 > width - mx), (y1 < my or y2 > height - my)


def cut_vertically(box: Box, height: int) -> tuple[bool, bool]:
    """Whether the image's top edge and its bottom edge cut ``box``."""
    my = _margins(box)[1]
    return box[1] < my, box[3] > height - my


def complete_amodal(
    points: np.ndarray,
    label: str,
    track_id: int,
    shift: float,
    room: float = np.inf,
    cut_sideways: bool = False,
    reference: np.ndarray | None = None,
    up: np.ndarray | None = None,
    support: np.ndarray | None = None,
    edges: BoxSides | None = None,
) -> FeatureVector | None:
    """A camera-frame view's feature vector completed behind its visible surface.

    A depth camera sees the near side of an object. Assuming it is about as deep as it is wide (horizontally,
    camera x), its depth is sqrt(12) times the horizontal standard deviation of the points, bounded by how deep
    the visible surface already reaches along the viewing ray (10th to 90th percentile) plus the free depth
    ``room`` behind it (a screen on a wall cannot extend into the wall). Along the viewing ray the centre lies
    ``shift`` standard deviations behind the near side (10th percentile), at most half the depth, and the spread
    is that of a uniform extent of that depth; across the ray the points' own statistics stay. Pixels of a
    supporting surface that join the object's depth segment then no longer stretch it. A panel (``PANEL_DEPTH_M``:
    a screen, a wall clock) is not as deep as it is wide: its visible face stays as it is (``panel``), and it is
    no deeper than the free depth ``room`` behind that face (a screen on a wall is as deep as it stands off the
    wall, ``PANEL_ROOM_SHARE``; the face's own reach along a slanted ray is its slant, not depth behind it: adding
    it left screens 10 cm deep where they are 5-7 cm, 2 cm into the wall on the development seeds).

    ``cut_sideways``: the image border cuts the box on the left or right, so the points' horizontal spread
    understates the object's width; the depth prior then takes the larger of the horizontal and vertical
    spreads (still bounded by the surface's reach plus the free depth behind it).

    ``reference``: the same points (same order) with less depth noise, whose spread along the ray gives the near
    and far sides (``detection_feature`` passes them with locally averaged depth); default ``points``.

    ``up``: the world's up in the camera frame (``ObjectMapper``: the floor's normal). The completion then runs
    along the level part of the ray (a camera looking down at a chair sees its top and front: completing along
    the slanted ray moved its centre down and towards the camera together), and the vertical extent is the
    points' (``vertical_extent``: percentiles, not moments, since the top face of an object seen from above
    holds many points at one height; down to the ``support`` plane ``(n, d)`` it stands on, when given).

    A table (``TOP_CLASSES``) seen from above, with ``up`` known, is the part of its top the view shows
    (``table_top.top_view``) rather than its points completed; its height is completed as any view's.

    ``edges``: the sides of the object's box (``box_edges``); across the level ray the centre is then the middle
    of these (``BoxSides.span``) rather than of the points' own extent, and the object is as deep as the box is
    wide (``BoxSides.span`` at the points' median depth), its centre half that behind its nearest points (their
    2nd percentile along the ray).
    For a box-shaped object this holds from every side: seen face-on the box is its face's width, and seen at a
    slant its nearest point is a corner, half the box's width in front of the centre. The points' own spread,
    which the completion uses without the box, is their density's: the nearer face of a chair seen at a slant
    holds more of them (development seeds 0-35: chairs 0.044 -> 0.033 m, the scenes' median error 0.036 -> 0.030
    m; cups and bottles, 0.003-0.004 m before, 0.006-0.013 m, until the box's sides were taken as planes:
    ``BoxSides.span``).
    """
    f = feature_from_points(points, label, track_id)
    if f is None:
        return None
    ray = f.mean / np.linalg.norm(f.mean)
    level = False
    if up is not None:  # complete along the level part of the ray: the object's unseen back is level with it
        flat = ray - (ray @ up) * up
        if np.linalg.norm(flat) > 0.3:  # not looking (nearly) straight down or up at it
            ray, level = flat / np.linalg.norm(flat), True
    smooth = points if reference is None else reference
    nearest, near, far = np.percentile(smooth @ ray, [2, 10, 90])
    low, high = (0.0, 0.0) if up is None else (float(v) for v in np.percentile(smooth @ up, [2, 98]))
    heights = (low, high)  # along up, from the camera
    top = top_view(smooth, up) if up is not None and level and label in TOP_CLASSES else None
    if label in PANEL_DEPTH_M:
        mean, cov = panel(feature_from_points(smooth, label), ray, min(PANEL_DEPTH_M[label], room))
    elif top is not None:  # a table: the part of its top the view shows
        mean, cov = top
    else:
        if edges is not None and level:
            assert up is not None
            lo, hi = edges.span(np.cross(up, ray), ray, up, heights, float(np.median(smooth @ ray)))
            width = max(hi - lo, 0.0)
            depth = min(width, float(far - near) + room)
            centre = float(nearest) + depth / 2.0
        else:
            sx = float(np.sqrt(f.cov[0, 0] if not cut_sideways else max(f.cov[0, 0], f.cov[1, 1])))
            depth = min(np.sqrt(12.0) * sx, float(far - near) + room)
            centre = float(near) + min(shift * sx, depth / 2.0)
        P = np.eye(3) - np.outer(ray, ray)
        mean = P @ f.mean + centre * ray
        cov = P @ f.cov @ P + depth**2 / 12.0 * np.outer(ray, ray)
    if level:
        assert up is not None
        side = np.cross(up, ray)
        if edges is None and top is None:
            mean = centred_across(mean, smooth, side)
        elif edges is not None:  # the middle of the two ends
            mean = mean + (float(np.mean(edges.span(side, ray, up, heights))) - mean @ side) * side
        mean, cov = with_span(mean, cov, up, *vertical_extent(smooth @ up, mean - (mean @ up) * up, up, support))
    return FeatureVector(mean, cov, f.n, label, track_id, f.sources)


def centred_across(mean: np.ndarray, points: np.ndarray, side: np.ndarray) -> np.ndarray:
    """``mean`` moved along the unit ``side`` to the middle of the points' extent across it (2nd to 98th
    percentile): an object's centre is the middle of its extent, and the mean of its visible points leans to
    where most of them are (a chair seen from its side, to its back)."""
    lo, hi = np.percentile(points @ side, [2, 98])
    return mean + ((lo + hi) / 2.0 - mean @ side) * side


EDGES_OWN: frozenset[str] = frozenset(PANEL_DEPTH_M) | LARGE_CLASSES
"""Classes whose views keep their points' own ends across the ray (``box_edges`` is not used): panels, whose
face the points show whole, and the large classes, whose views are parts of the object
(``footprint.union_footprint``). Development seeds 0-35 with the box's edges for every class: couches' median
error 0.127 -> 0.169 m, the scene figures 0.001 m worse than without these."""

EDGE_SHARE = 0.1
"""The points within this share of a box's width of a view's leftmost (rightmost) point give the depth of its
left (right) edge (``box_edges``)."""


@dataclass(frozen=True)
class BoxSides:
    """A box's left and right sides as seen from the camera: each a plane through the camera (``normals`` (2, 3),
    camera frame) and a point on it (``points`` (2, 3): on the ray through the side's middle row, at the depth of
    the view's points nearest that side)."""

    points: np.ndarray
    normals: np.ndarray

    def span(
        self,
        side: np.ndarray,
        ray: np.ndarray,
        up: np.ndarray,
        heights: tuple[float, float],
        depth: float | None = None,
    ) -> tuple[float, float]:
        """The object's extent along the unit ``side`` (across the level ``ray``) between the two planes, at each
        plane's point's depth along ``ray`` (or at ``depth``): where each plane cuts the object's bottom and top
        ``heights`` (along ``up``), the inner of the two. A camera that looks down sees an object's upright
        edges converge, and a tall object off the image's centre touches its box's side at its top or its
        bottom only. Taken as the rays through the sides' middle rows, the box of a bottle 24 degrees off the
        image's centre was 10-12 cm wide for 7-9 (``tests/test_object_geometry.py``); on the development seeds
        0-35, bottles' median error 0.013 -> 0.004 m, vases' 0.014 -> 0.004 m, potted plants' 0.037 -> 0.022 m,
        the scenes' 0.0316 -> 0.0277 m; chairs', whose face-on views the widening had put farther, 0.033 ->
        0.036 m."""
        ends = []
        for point, n in zip(self.points, self.normals, strict=True):
            d = float(point @ ray) if depth is None else depth
            ends.append([-(d * (n @ ray) + h * (n @ up)) / (n @ side) for h in heights])
        lo, hi = sorted(ends, key=lambda e: float(np.mean(e)))
        return max(lo), min(hi)


def box_edges(box: Box, K: Intrinsics, cols: np.ndarray, depth: np.ndarray) -> BoxSides:
    """A box's sides (``BoxSides``), each at the depth of the view's points (columns ``cols``, depths ``depth``)
    nearest it: the object's ends across the image, whatever of its middle the depth segment caught or missed (a
    neighbour's pixels, an occluder, a part without depth). A view's centre across its ray from these rather than
    from its points' 2nd and 98th percentiles: on development seeds 0-11, chair views 0.029 -> 0.020 m off across
    the ray in the median (the image's sides not cutting them), potted plants' 0.025 -> 0.021 m, suitcases' 0.035
    -> 0.018 m; on seeds 0-35 chairs' median error 0.054 -> 0.044 m. A box's edges are pixel edges, half a pixel
    outside the centres of its outermost pixels."""
    reach = EDGE_SHARE * (box[2] - box[0])
    z = [float(np.median(depth[sel])) for sel in (cols <= cols.min() + reach, cols >= cols.max() - reach)]
    u = np.array(box[::2], float) - 0.5
    points = pixels_to_points(u, np.full(2, 0.5 * (box[1] + box[3]) - 0.5), np.array(z), K)
    normals = np.column_stack([np.ones(2), np.zeros(2), -(u - K.cx) / K.fx])  # the planes x = z (u - cx) / fx
    return BoxSides(points, normals / np.linalg.norm(normals, axis=1, keepdims=True))


def panel(face: FeatureVector | None, ray: np.ndarray, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre and covariance of a panel from its visible face's points' Gaussian: the face as it is (a screen
    seen at a slant keeps its slant), moved back half of ``depth`` along ``ray`` and thickened by it."""
    assert face is not None
    return face.mean + depth / 2.0 * ray, face.cov + depth**2 / 12.0 * np.outer(ray, ray)


SUPPORT_GAP_M = 0.05
"""An object's lowest visible point within this of its support plane stands on it (``vertical_extent``)."""


def vertical_extent(
    heights: np.ndarray, level_point: np.ndarray, up: np.ndarray, support: np.ndarray | None
) -> tuple[float, float]:
    """Bottom and top (along ``up``) of a view's object from its points' ``heights``: their 2nd and 98th
    percentiles, the bottom moved down to the support plane ``(n, d)`` under ``level_point`` when the lowest
    point lies within ``SUPPORT_GAP_M`` of it (the band the support removal took off the object's foot)."""
    bottom, top = (float(v) for v in np.percentile(heights, [2, 98]))
    if support is not None and abs(support[:3] @ up) > 0.9:
        base = -(support[3] + support[:3] @ level_point) / (support[:3] @ up)
        if bottom - SUPPORT_GAP_M <= base < bottom:
            bottom = float(base)
    return bottom, top


def local_mean_depth(depth_m: np.ndarray, rows: np.ndarray, cols: np.ndarray, radius: int) -> np.ndarray:
    """Depth (N, float64) at each of the pixels (rows, cols) averaged over those of them within ``radius`` steps
    of their grid (a box's pixels lie on a regular grid, ``box_pixels``): inside a surface (2r+1)^2 pixels, so
    the noise's standard deviation is 2r+1 times smaller; fewer at its rim. ``radius`` 0: the depth itself."""
    z = depth_m[rows, cols].astype(np.float64)
    if radius <= 0 or len(rows) < 2:
        return z
    gr, gc = grid_of(rows, cols)[3:]
    total, count = np.zeros((2, int(gr.max()) + 1, int(gc.max()) + 1))
    total[gr, gc], count[gr, gc] = z, 1.0
    size = 2 * radius + 1  # the filters' common normalisation cancels in the ratio
    return uniform_filter(total, size, mode="constant")[gr, gc] / uniform_filter(count, size, mode="constant")[gr, gc]


def detection_feature(
    depth_m: np.ndarray,
    K: Intrinsics,
    box: Box,
    label: str,
    track_id: int,
    config: FeatureConfig,
    up: np.ndarray | None = None,
    occluders: Sequence[DepthSegment] = (),
    segmented: Segmented | None = None,
    floor: float | None = None,
) -> FeatureVector | None:
    """The camera-frame feature vector of a detection (amodally completed when configured, its near and far sides
    on locally averaged depth: ``FeatureConfig.near_radius``), its pixels without those of the other detections
    in front of it (``occluders``: ``features.in_front``; ``segmented``: its own ``features.depth_segment``, when
    the caller has it), centred across its ray between its box's edges when the image's sides do not cut it
    (``box_edges``); None when too few points. ``floor``: the floor's height along ``up`` (camera frame), when
    known: a chair's backrest seen over a table is then its back (``perception.backrest``)."""
    pixels = object_pixels(depth_m, box, config, occluders, segmented, label)
    rows, cols, support = split_support(depth_m, K, box, *pixels, config)
    idx = stride_subsample(len(rows), config.max_points)
    points = depth_points(depth_m, K, rows[idx], cols[idx])
    if config.amodal is None or len(points) < 3:
        return feature_from_points(points, label, track_id)
    smooth = local_mean_depth(depth_m, rows, cols, config.near_radius)[idx]
    reference = pixels_to_points(cols[idx], rows[idx], smooth, K)
    sideways = cut_by_border(box, depth_m.shape[1], depth_m.shape[0])[0]
    f = complete_amodal(
        points,
        label,
        track_id,
        config.amodal,
        room_behind(depth_m, box, rows, cols, share=PANEL_ROOM_SHARE if label in PANEL_DEPTH_M else None),
        sideways,
        reference=reference,
        up=up,
        support=support,
        edges=None if sideways or label in EDGES_OWN else box_edges(box, K, cols[idx], smooth),
    )
    if f is not None and up is not None and floor is not None and label in BACKREST_CLASSES:
        if seen_over(reference, up, floor, depth_m, box, K):
            return facing_camera(f, up)
        moved = None if sideways else seated(f, reference, up, floor)  # the image's side cuts the plate's width
        return moved if moved is not None else f
    if f is None or up is None or label not in PANEL_DEPTH_M:
        return f
    return FeatureVector(*spanning_box(f.mean, f.cov, box, K, up), f.n, f.label, f.track_id, f.sources)


def spanning_box(
    mean: np.ndarray, cov: np.ndarray, box: Box, K: Intrinsics, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A panel's camera-frame Gaussian reaching along ``up`` at least from its box's bottom edge to its top edge,
    at its centre's depth: a screen's glass returns no depth over much of it (the 7-Scenes monitors: their upper
    part, so that their views' points end below their tops and the monitors lay 0.16-0.19 m low), while the
    detector's box holds the whole screen."""
    middle = np.full(2, 0.5 * (box[0] + box[2]))
    edges = pixels_to_points(middle, np.array(box[1::2], float), np.full(2, mean[2]), K) @ up
    (top,), (bottom,) = view_ends(mean[None], cov[None], up)
    return with_span(mean, cov, up, min(float(bottom), *edges), max(float(top), *edges))
