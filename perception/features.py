"""Back-projection of detections and object feature vectors f = {X, Y, Z, S} (Sec. 2.4.4, SPEC 6.5).

Depth images are float metres with NaN where invalid; boxes are [x1, y1, x2, y2] in pixels; poses are
camera-to-world 4x4 (OpenCV camera axes); ``K`` is the camera's ``Intrinsics``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from perception.camera import Intrinsics, pixels_to_points
from perception.coco import FLOOR_CLASSES

log = logging.getLogger(__name__)

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class FeatureConfig:
    """How a detection's depth pixels become world points."""

    anchor_fraction: float = 0.5
    """Central fraction (per side) of the box whose median depth anchors the object's depth segment."""
    min_centre_depth: float = 0.5
    """A box whose central ``anchor_fraction`` has depth in less than this share of its pixels gives no view: its
    object lies beyond the sensor's range (or returns no depth), and the box's pixels that have depth are the
    floor in front of it or a neighbour (development scenes: 95 % of such views showed mostly another object's
    pixels, which placed false objects on nearer surfaces)."""
    gap_m: float = 0.05
    """A jump larger than this between sorted box depths separates the object from its background."""
    pixels: int | None = 10000
    """A box's pixels are taken on a grid coarse enough to give at most about this many (None: every pixel)."""
    max_points: int = 400
    """Back-projected points kept per detection (deterministic stride), so every view weighs alike."""
    cut_weight: float = 0.25
    """A view whose box the image border cuts shows part of the object: its points weigh this much in the pooled
    Gaussians (``ObjectMapper``), so whole views place and size the object (`objslam bench objects`)."""
    support_tilt_deg: float | None = 45.0
    """Drop the pixels of the surface an object stands on (``split_support``): the dominant plane of the ring
    around the box, when its normal lies within this angle of the camera's vertical axis (a roughly upright
    camera: a floor or a table top, not a wall). None keeps them."""
    support_tolerance_m: float = 0.015
    """Object pixels within this distance of the support plane belong to it."""
    amodal: float | None = float(np.sqrt(3.0))
    """Amodal completion of a view (``complete_amodal``): the object's centre lies this many horizontal
    standard deviations behind its near side (sqrt(3): half the width of a uniform extent, as for a box seen
    face on); None uses the visible points as they are. `objslam bench objects` measures both."""
    near_radius: int = 2
    """The near and far sides of a view (``complete_amodal``) are measured on its depth averaged over each object
    pixel's object neighbours within this many grid steps (``local_mean_depth``), so that the sensor's noise does
    not pull the near side, a 10th percentile, towards the camera (by about 1.3 sigma: a cup 3.5 m away seen
    through twice the Kinect model's noise landed 3.6 cm towards the camera); 0 measures them on the raw depth."""


@dataclass(frozen=True)
class FeatureVector:
    """Per-axis Gaussian of an object's world points plus its class (Sec. 2.4.4's f = {X, Y, Z, S}).

    ``cov`` keeps the full 3x3 second moment (its diagonal is the per-axis variance the clustering
    distance uses; the off-diagonal terms orient the object's ellipse); ``n`` is the point count.
    ``sources`` names the keyframe observations pooled into it (ids of ``ObjectMapper``'s observation
    store), so the vector can be recomputed exactly when the poses of those keyframes change.
    """

    mean: np.ndarray
    cov: np.ndarray
    n: int
    label: str
    track_id: int = -1
    sources: tuple[int, ...] = ()

    @property
    def var(self) -> np.ndarray:
        """Per-axis variances (X, Y, Z)."""
        return np.diag(self.cov).copy()


def box_window(shape: tuple[int, ...], box: Box, fraction: float = 1.0) -> tuple[int, int, int, int] | None:
    """Integer pixel window (y1, y2, x1, x2) of the central ``fraction`` of a box, clipped; None if empty."""
    h, w = shape[:2]
    cx, cy = (box[0] + box[2]) / 2.0, (box[1] + box[3]) / 2.0
    hw, hh = (box[2] - box[0]) * fraction / 2.0, (box[3] - box[1]) * fraction / 2.0
    x1, x2 = max(int(np.floor(cx - hw)), 0), min(int(np.ceil(cx + hw)), w)
    y1, y2 = max(int(np.floor(cy - hh)), 0), min(int(np.ceil(cy + hh)), h)
    return (y1, y2, x1, x2) if x2 > x1 and y2 > y1 else None


def ring_windows(shape: tuple[int, ...], box: Box, ring: float) -> tuple[tuple[int, int, int, int], ...] | None:
    """The windows (y1, y2, x1, x2) of a box grown by ``ring`` of its size on each side and of the box itself,
    clipped to the image: the ring around the box lies between them. None when either is empty."""
    w, h = box[2] - box[0], box[3] - box[1]
    outer = box_window(shape, (box[0] - ring * w, box[1] - ring * h, box[2] + ring * w, box[3] + ring * h))
    inner = box_window(shape, box)
    return None if outer is None or inner is None else (outer, inner)


def box_pixels(
    depth_m: np.ndarray, box: Box, fraction: float = 1.0, most: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the valid depth pixels inside the central ``fraction`` of a box; with ``most``, on a
    regular grid coarse enough to give at most about that many (a large box's statistics need not every pixel)."""
    win = box_window(depth_m.shape, box, fraction)
    if win is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    y1, y2, x1, x2 = win
    step = max(1, int(np.ceil(np.sqrt((y2 - y1) * (x2 - x1) / most)))) if most else 1
    rows, cols = np.nonzero(np.isfinite(depth_m[y1:y2:step, x1:x2:step]))
    return rows * step + y1, cols * step + x1


def dominant_depth_mask(depths: np.ndarray, anchor: float, gap_m: float) -> np.ndarray:
    """Mask of the depths in the gap-free segment (sorted depths, no jump > ``gap_m``) around ``anchor``."""
    if len(depths) == 0 or not np.isfinite(anchor):
        return np.zeros(len(depths), bool)
    s = np.sort(depths)
    breaks = np.flatnonzero(np.diff(s) > gap_m)  # segment j spans (breaks[j-1], breaks[j]]
    seg = np.searchsorted(breaks, min(int(np.searchsorted(s, anchor)), len(s) - 1))
    lo = breaks[seg - 1] + 1 if seg > 0 else 0
    hi = breaks[seg] + 1 if seg < len(breaks) else len(s)
    # equal depths never straddle a break, so the segment is exactly the depths within its value range
    return (depths >= s[lo]) & (depths <= s[hi - 1])


PANEL_DEPTH_M: dict[str, float] = {"tv": 0.1, "clock": 0.06}
"""Classes that are panels (a screen, a wall clock): their visible face is the whole object but for this depth
behind it (flat screens and monitors are 3-10 cm deep; the 7-Scenes monitors were annotated 8 cm), so a view is
not completed as deep as it is wide (``amodal.complete_amodal``), and no deeper than the free depth behind it.
Their glass often returns no depth: they are seen without depth over the centre of their box
(``FeatureConfig.min_centre_depth``; the 7-Scenes monitors were lost without this)."""


@dataclass(frozen=True)
class DepthSegment:
    """A detection's depth segment (``object_pixels``): its box, the central median depth it is anchored at, and
    the depths it spans."""

    box: Box
    anchor: float
    near: float
    far: float


Segmented = tuple[np.ndarray, np.ndarray, "DepthSegment | None"]
"""A box's segment pixels (rows, columns) and their ``DepthSegment``, as ``depth_segment`` gives them."""


def object_pixels(
    depth_m: np.ndarray,
    box: Box,
    config: FeatureConfig,
    occluders: Sequence[DepthSegment] = (),
    segmented: Segmented | None = None,
    label: str = "",
) -> tuple[np.ndarray, np.ndarray]:
    """The box's valid pixels in the dominant depth segment anchored at the central median (SPEC 6.5), without
    those of the ``occluders`` in front of it (``in_front``); ``segmented``: the box's ``depth_segment``, when
    the caller has it already."""
    rows, cols, own = segmented if segmented is not None else depth_segment(depth_m, box, config, label)
    if own is None or not occluders:
        return rows, cols
    keep = ~in_front(depth_m[rows, cols], rows, cols, own, occluders, config.gap_m, label in FLOOR_CLASSES)
    return rows[keep], cols[keep]


def segment_anchor(depth_m: np.ndarray, box: Box, config: FeatureConfig, rows: np.ndarray, cols: np.ndarray) -> float:
    """The depth a box's segment is anchored at: the median of its central ``anchor_fraction``, else of the
    pixels (``rows``, ``cols``)."""
    cr, cc = box_pixels(depth_m, box, config.anchor_fraction, most=config.pixels)
    return float(np.median(depth_m[cr, cc])) if len(cr) else float(np.median(depth_m[rows, cols]))


def centre_depth(depth_m: np.ndarray, box: Box, config: FeatureConfig) -> float:
    """The share of the pixels in a box's central ``anchor_fraction`` that have depth (1 for an empty window)."""
    window = box_window(depth_m.shape, box, config.anchor_fraction)
    if window is None:
        return 1.0
    y1, y2, x1, x2 = window
    return float(np.isfinite(depth_m[y1:y2, x1:x2]).mean())


def depth_segment(depth_m: np.ndarray, box: Box, config: FeatureConfig, label: str = "") -> Segmented:
    """The pixels of ``object_pixels`` (no occluders) and their ``DepthSegment`` (None: no valid pixel, or too few
    in the box's centre, ``FeatureConfig.min_centre_depth``, unless ``label`` is a panel's)."""
    rows, cols = box_pixels(depth_m, box, most=config.pixels)
    if len(rows) == 0 or (label not in PANEL_DEPTH_M and centre_depth(depth_m, box, config) < config.min_centre_depth):
        return rows[:0], cols[:0], None
    return segment_at(depth_m, box, config, segment_anchor(depth_m, box, config, rows, cols), (rows, cols))


def segment_at(
    depth_m: np.ndarray, box: Box, config: FeatureConfig, anchor: float, pixels: tuple[np.ndarray, np.ndarray]
) -> Segmented:
    """The box's ``pixels`` (rows, cols) in the gap-free depth segment around ``anchor``, and its ``DepthSegment``
    (None when no pixel is in it)."""
    rows, cols = pixels
    depths = depth_m[rows, cols]
    keep = dominant_depth_mask(depths, anchor, config.gap_m)
    if not keep.any():
        return rows[keep], cols[keep], None
    kept = depths[keep]
    return rows[keep], cols[keep], DepthSegment(box, anchor, float(kept.min()), float(kept.max()))


AROUND = 0.9
"""Another detection's box holding this share of a box is around it, not in front of it (``in_front``)."""

LARGER = 4.0
"""Another detection's box this many times larger than a box is behind or under it, not in front of it
(``in_front``): a table's depth segment runs on across its top to the bottle standing on it."""

BEYOND = 2.0
"""A floor-standing object anchored this many ``FeatureConfig.gap_m`` beyond another detection lies behind that
one's object, whatever their boxes (``in_front``, ``anchoring.explains``): nothing stands under it."""


def in_front(
    depths: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    own: DepthSegment,
    occluders: Sequence[DepthSegment],
    margin_m: float,
    standing: bool = False,
) -> np.ndarray:
    """Which of a detection's pixels belong to another detection in front of it: inside that one's box and within
    its depth segment, when that one's anchor lies more than ``margin_m`` nearer than this one's. A box around an
    object behind another (a table behind a chair, the second chair of a row seen at a slant) holds the nearer
    one's pixels, joined to its own depth segment where they touch; they pulled its near side, and with it the
    completed centre, 0.3-0.5 m towards the camera. A box that holds most of this one (``AROUND``: a table
    under a cup, a couch behind a teddy bear) or is far larger (``LARGER``) is not in front of it, unless this one
    ``standing`` on the floor is anchored ``BEYOND`` it: a chair behind a couch; or anchored beyond it and beyond
    the far end of its depth segment, which nothing standing on it or in it is: a potted plant behind a table's
    corner, whose box held the corner's pixels (development seed 2: the plant's views 0.45 m towards the
    camera)."""
    out = np.zeros(len(depths), bool)
    for o in occluders:
        held, larger = overlap(own.box, o.box)
        behind = o.anchor < own.anchor - BEYOND * margin_m and (standing or own.anchor > o.far + margin_m)
        if o.anchor >= own.anchor - margin_m or ((held >= AROUND or larger >= LARGER) and not behind):
            continue
        out |= in_box(rows, cols, o.box) & (depths >= o.near) & (depths <= o.far)
    return out


def in_box(rows: np.ndarray, cols: np.ndarray, box: Box) -> np.ndarray:
    """Which pixels (rows, cols) lie inside ``box`` (x1 <= col < x2, y1 <= row < y2)."""
    x1, y1, x2, y2 = box
    return (cols >= x1) & (cols < x2) & (rows >= y1) & (rows < y2)


def overlap(box: Box, other: Box) -> tuple[float, float]:
    """The share of ``box`` that ``other`` holds, and how many times larger ``other`` is."""
    a1, b1, a2, b2 = box
    x1, y1, x2, y2 = other
    area = max((a2 - a1) * (b2 - b1), 1e-9)
    shared = max(0.0, min(a2, x2) - max(a1, x1)) * max(0.0, min(b2, y2) - max(b1, y1))
    return shared / area, (x2 - x1) * (y2 - y1) / area


TWIN_HELD = 0.3
"""A larger box of a detection's class holding this share of it, anchored on the same surface, hides it
(``hidden_by_twin``)."""


def hidden_by_twin(own: DepthSegment, twins: Sequence[DepthSegment], margin_m: float) -> bool:
    """Whether a detection's view shows another detection of its class rather than its own object: a larger box
    of that class holds ``TWIN_HELD`` of it and both are anchored on the same surface (within ``margin_m``). The
    second chair of a row seen at a slant shows mostly the first: its box's centre, where its segment is
    anchored, is the first chair's, and in development scenes with laps looking inward such views (about one
    chair view in six) put it 0.7 m too near the camera. Of the chair views there whose pixels were mostly
    another object's, 42 % are caught (65 % of those showing another detected chair); 2 % of those showing
    their own chair are lost."""
    for o in twins:
        held, larger = overlap(own.box, o.box)
        if held >= TWIN_HELD and larger > 1.0 and abs(o.anchor - own.anchor) <= margin_m:
            return True
    return False


def depth_points(depth_m: np.ndarray, K: Intrinsics, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3, float64) of the pixels (rows, cols) of a depth image."""
    return pixels_to_points(cols, rows, depth_m[rows, cols].astype(np.float64), K)


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) mapped by the 4x4 rigid transform T."""
    return points @ T[:3, :3].T + T[:3, 3]


def stride_subsample(n: int, k: int) -> np.ndarray:
    """Indices of at most ``k`` of ``n`` items, evenly spread (deterministic)."""
    if n <= k:
        return np.arange(n)
    return np.linspace(0, n - 1, k).round().astype(np.int64)


def feature_from_points(points: np.ndarray, label: str, track_id: int = -1) -> FeatureVector | None:
    """The feature vector (mean, covariance, class) of a set of world points, None when too few."""
    if len(points) < 3:
        return None
    mean = points.mean(axis=0)
    d = points - mean
    return FeatureVector(mean, d.T @ d / len(points), len(points), label, track_id)


def transform_feature(f: FeatureVector, T: np.ndarray) -> FeatureVector:
    """The feature vector of the same points moved by the rigid transform T (mean T m, covariance R C R^T)."""
    R = T[:3, :3]
    return FeatureVector(R @ f.mean + T[:3, 3], R @ f.cov @ R.T, f.n, f.label, f.track_id, f.sources)


def mixture(means: np.ndarray, covs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the mixture of Gaussians (N, 3) / (N, 3, 3) with ``weights`` (N,)."""
    w = np.asarray(weights, float) / np.sum(weights)
    mean = w @ means
    d = means - mean
    return mean, np.einsum("k,kij->ij", w, covs) + (d.T * w) @ d


def merge_features(features: Sequence[FeatureVector]) -> FeatureVector:
    """The pooled Gaussian of several feature vectors of one class (moments weighted by point count)."""
    n = np.array([f.n for f in features], float)
    mean, cov = mixture(np.stack([f.mean for f in features]), np.stack([f.cov for f in features]), n)
    sources = tuple(i for f in features for i in f.sources)
    return FeatureVector(mean, cov, int(n.sum()), features[0].label, features[0].track_id, sources)


def merge_track_runs(features: Sequence[FeatureVector], run: int) -> list[FeatureVector]:
    """Pool each track's consecutive feature vectors in runs of ``run`` (moment sums, vectorised)."""
    tracks = np.array([f.track_id for f in features])
    order = np.argsort(tracks, kind="stable")
    starts = np.r_[0, np.flatnonzero(np.diff(tracks[order])) + 1]
    position = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    _, group = np.unique(np.stack([tracks[order], position // run], axis=1), axis=0, return_inverse=True)
    group = group.ravel()
    n = np.array([features[i].n for i in order], float)
    mu = np.array([features[i].mean for i in order])
    g = int(group.max()) + 1
    s0, mean, cov = _pools(group, n, mu, np.array([features[i].cov for i in order]), g)
    first = np.unique(group, return_index=True)[1]
    sources: list[list[int]] = [[] for _ in range(g)]
    for k, i in zip(group, order, strict=True):
        sources[k].extend(features[i].sources)
    return [
        FeatureVector(
            mean[k],
            cov[k],
            int(s0[k]),
            features[order[first[k]]].label,
            features[order[first[k]]].track_id,
            tuple(sources[k]),
        )
        for k in range(g)
    ]


def _pools(
    group: np.ndarray, n: np.ndarray, mu: np.ndarray, cov: np.ndarray, g: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point counts, means and covariances of ``g`` pooled Gaussians: the Gaussian of row i (``n[i]`` points,
    ``mu[i]``, ``cov[i]``) goes into pool ``group[i]`` (moment sums; an empty pool's mean and cov are nan)."""
    s0 = np.bincount(group, n, minlength=g)
    s1 = np.stack([np.bincount(group, n * mu[:, a], minlength=g) for a in range(3)], axis=1)
    s2 = np.zeros((g, 3, 3))
    np.add.at(s2, group, n[:, None, None] * (cov + mu[:, :, None] * mu[:, None, :]))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / s0[:, None]
        return s0, mean, s2 / s0[:, None, None] - mean[:, :, None] * mean[:, None, :]


def repooled(
    features: Sequence[FeatureVector], means: np.ndarray, covs: np.ndarray, n: np.ndarray
) -> list[FeatureVector]:
    """``features`` pooled again from their sources, given each source's Gaussian (``means[i]``, ``covs[i]``,
    ``n[i]`` points of ``sources`` id i): what ``merge_features`` of the sources gives, in one pass of moment
    sums over every source (a map's re-placement pools tens of thousands). A single source is taken as it is;
    a vector without sources (from a snapshot before the observation store) stays as it was."""
    counts = [len(f.sources) for f in features]
    owner = np.repeat(np.arange(len(features)), counts)
    src = np.fromiter((i for f in features for i in f.sources), np.int64, len(owner))
    s0, mean, cov = _pools(owner, np.asarray(n, float)[src], means[src], covs[src], len(features))
    out = []
    for k, (f, c) in enumerate(zip(features, counts, strict=True)):
        if c == 0:
            out.append(f)
        elif c == 1:
            i = f.sources[0]
            out.append(FeatureVector(means[i], covs[i], int(n[i]), f.label, f.track_id, f.sources))
        else:
            out.append(FeatureVector(mean[k], cov[k], int(s0[k]), f.label, f.track_id, f.sources))
    return out
