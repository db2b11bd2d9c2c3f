"""Density clustering of object feature vectors (Sec. 2.4.5-2.4.6, eq. 2.15, Algorithm 2, SPEC 6.6-6.7).

Feature vectors are clustered by HDBSCAN on a precomputed distance: the sum over the X, Y, Z axes of
the Bhattacharyya distance between univariate Gaussians plus a class-mismatch penalty g. A cluster is
an object, shown as an ellipsoid (mean, principal axes times ``axis_scale`` standard deviations).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field, replace

import hdbscan
import numpy as np

from perception.cannot_link import keyframe_sets, split_all
from perception.coincident import coincident_groups
from perception.features import FeatureVector, merge_features
from perception.track_retirement import compacted

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClusterConfig:
    """Clustering choices; defaults from `objslam bench objects` (docs/benchmarks.md)."""

    min_cluster_size: int = 3
    """HDBSCAN minimum cluster size, in (track-window) feature vectors."""
    min_samples: int | None = 3
    """HDBSCAN core-distance neighbour count (None = min_cluster_size)."""
    class_penalty: float = 100.0
    """g of Sec. 2.4.5: distance added between feature vectors of different classes."""
    var_floor: float = 1e-4
    """Per-axis variance floor (m^2) so flat faces do not make the Bhattacharyya distance explode."""
    per_class: bool = True
    """Cluster each class separately beside a far group (as g does in the global matrix); ~classes-times cheaper."""
    selection: str = "eom"
    """HDBSCAN cluster selection method: "eom" or "leaf"."""
    axis_scale: float = 1.5
    """Ellipsoid semi-axes in standard deviations. A uniform extent's half-width is sqrt(3) std, but the held-out
    scene family measured IoU 0.637 there against 0.646 at 1.5 (docs/benchmarks.md, 2026-12-04)."""
    fit_distance: float = 2.0
    """A new observation fits an object (set T of eq. 2.15) when its distance to the object is below this."""
    outlier_threshold: int = 12
    """Re-cluster once this many associated observations fitted no object (Sec. 2.4.6 count threshold)."""
    max_features: int = 800
    """Bound N on clustered vectors; above it, consecutive vectors of each track are pooled (keeps O(N^2) fast)."""
    merge_distance: float = 2.0
    """Same-class clusters whose pooled Gaussians are within this distance D are one object (partial views)."""
    coincident: float = 1.5
    """Same-class objects whose centres are closer than this many median standard deviations of the smaller
    one's extent are one (``perception.coincident``; its own measure, not ``axis_scale``), and so are objects of
    two labels the same size (``coincident.SAME_SIZE``); 0: never."""
    split_shared: bool = True
    """Cut a cluster that holds two views of one keyframe in many of its keyframes (``perception.cannot_link``)."""


@dataclass(frozen=True)
class ObjectEllipsoid:
    """A localized object: class, mean, covariance, semi-axis rows (direction x extent), support."""

    id: int
    label: str
    mean: np.ndarray
    cov: np.ndarray
    axes: np.ndarray
    n_observations: int
    tracks: frozenset[int] = field(default_factory=frozenset)


def bhattacharyya(mu_a: np.ndarray, var_a: np.ndarray, mu_b: np.ndarray, var_b: np.ndarray) -> float:
    """Sum over axes of the univariate Gaussian Bhattacharyya distance (Sec. 2.4.5)."""
    s = var_a + var_b
    return float(np.sum(0.25 * np.log(0.25 * (var_a / var_b + var_b / var_a + 2.0)) + 0.25 * (mu_a - mu_b) ** 2 / s))


def bhattacharyya_matrix(
    means: np.ndarray,
    variances: np.ndarray,
    labels: Sequence[str] | np.ndarray,
    penalty: float = 100.0,
    var_floor: float = 1e-4,
) -> np.ndarray:
    """D (N, N) of Sec. 2.4.5: per-axis Bhattacharyya distances summed, plus g for class mismatch (float32).

    Uses 1/4 log((va + vb)^2 / (4 va vb)) = 1/2 log(va + vb) - 1/4 (log va + log vb) - 1/2 log 2.
    """
    mu = np.ascontiguousarray(np.asarray(means, np.float32).T)
    var = np.ascontiguousarray(np.maximum(np.asarray(variances, np.float32), np.float32(var_floor)).T)
    n = mu.shape[1]
    D = np.zeros((n, n), np.float32)
    s, d = np.empty_like(D), np.empty_like(D)
    quarter_log = np.float32(0.25) * np.log(var)
    for a in range(3):
        np.add(var[a][:, None], var[a][None, :], out=s)
        np.subtract(mu[a][:, None], mu[a][None, :], out=d)
        np.multiply(d, d, out=d)
        np.divide(d, s, out=d)
        d *= np.float32(0.25)
        D += d
        np.log(s, out=s)
        s *= np.float32(0.5)
        D += s
        D -= quarter_log[a][:, None]
        D -= quarter_log[a][None, :]
    D -= np.float32(1.5 * np.log(2.0))
    codes = np.unique(np.asarray(labels, object), return_inverse=True)[1]
    D += np.where(codes[:, None] != codes[None, :], np.float32(penalty), np.float32(0.0))
    np.fill_diagonal(D, 0.0)
    return np.maximum(D, 0.0, out=D)


def hdbscan_labels(D: np.ndarray, config: ClusterConfig) -> np.ndarray:
    """HDBSCAN cluster labels (-1 = noise) on a precomputed distance matrix."""
    if len(D) < max(config.min_cluster_size, 2):
        return np.full(len(D), -1)
    model = hdbscan.HDBSCAN(
        metric="precomputed",
        min_cluster_size=config.min_cluster_size,
        min_samples=config.min_samples,
        cluster_selection_method=config.selection,
    )
    return model.fit(D.astype(np.float64)).labels_


def _with_far_group(D: np.ndarray, size: int, distance: float) -> np.ndarray:
    """D extended by ``size`` coincident points ``distance`` away from all others.

    Clustering one class beside a far group reproduces what the class penalty does in the global
    matrix: the class's points form a child of the root, so a class holding a single object is one
    ordinary cluster (hdbscan would otherwise not select the root, or label most of it noise).
    """
    n = len(D)
    out = np.full((n + size, n + size), distance, np.float32)
    out[:n, :n] = D
    out[n:, n:] = 0.0
    return out


def cluster_labels(features: Sequence[FeatureVector], config: ClusterConfig) -> np.ndarray:
    """Cluster index per feature vector (-1 = noise), over all classes at once or per class."""
    labels = np.array([f.label for f in features], object)
    means = np.array([f.mean for f in features]).reshape(-1, 3)
    variances = np.array([f.var for f in features]).reshape(-1, 3)
    if not config.per_class:
        return hdbscan_labels(
            bhattacharyya_matrix(means, variances, labels, config.class_penalty, config.var_floor), config
        )
    out, offset = np.full(len(features), -1), 0
    for label in sorted(set(labels)):
        idx = np.flatnonzero(labels == label)
        D = bhattacharyya_matrix(means[idx], variances[idx], labels[idx], config.class_penalty, config.var_floor)
        far = config.class_penalty + float(D.max(initial=0.0))
        size = config.min_cluster_size + (config.min_samples or config.min_cluster_size) + 1
        sub = hdbscan_labels(_with_far_group(D, size, far), config)[: len(idx)]
        kept = np.unique(sub[sub >= 0])
        out[idx[sub >= 0]] = np.searchsorted(kept, sub[sub >= 0]) + offset
        offset += len(kept)
    return out


def merge_overlapping(
    clusters: list[list[FeatureVector]], config: ClusterConfig, keyframe_of: Sequence[int] = ()
) -> list[list[FeatureVector]]:
    """Union same-class clusters whose pooled Gaussians are within ``merge_distance`` (SPEC 6.8 merges): partial
    views of one object. Never two clusters holding observations of one keyframe (``keyframe_of[s]``: the keyframe
    of observation ``s`` of ``FeatureVector.sources``): two detections of one image are two objects, however
    close (a row of chairs). Judged per observation, not per track, so a track that NPDA carried from one
    chair to its neighbour does not keep the views of either chair apart."""
    pooled = [merge_features(c) for c in clusters]
    parent = list(range(len(clusters)))
    frames = [set().union(*keyframe_sets(c, keyframe_of)) for c in clusters]

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(len(clusters)):
        for j in range(i + 1, len(clusters)):
            a, b = pooled[i], pooled[j]
            if (
                a.label == b.label
                and bhattacharyya(
                    a.mean, np.maximum(a.var, config.var_floor), b.mean, np.maximum(b.var, config.var_floor)
                )
                <= config.merge_distance
            ):
                ri, rj = root(i), root(j)
                if ri != rj and not frames[ri] & frames[rj]:
                    parent[rj] = ri
                    frames[ri] |= frames[rj]  # by root: the keyframes of its merged group
    groups: dict[int, list[FeatureVector]] = {}
    for i, c in enumerate(clusters):
        groups.setdefault(root(i), []).extend(c)
    return list(groups.values())


Locate = Callable[[Sequence[FeatureVector]], "tuple[np.ndarray, np.ndarray] | None"]
"""An object's centre and covariance from its cluster's members (``ObjectMapper``: ``robust_gaussian``, stretched
to the floor), or None to keep the pooled Gaussian's."""

Judge = Callable[[Sequence[Sequence[FeatureVector]], Sequence["ObjectEllipsoid"]], list[bool]]
"""Which of the objects of clusters are kept (given the clusters' members and their objects; ``ObjectMapper``:
those detected often enough where they stood in view, ``perception.existence``)."""


def ellipsoid(
    members: Sequence[FeatureVector], object_id: int, axis_scale: float, locate: Locate | None = None
) -> ObjectEllipsoid:
    """The object of a cluster: pooled mean and covariance (or ``locate``'s), semi-axes = eigenvector *
    sqrt(eigenvalue) * scale."""
    pooled = merge_features(members)
    located = locate(members) if locate is not None else None
    if located is not None:
        pooled = FeatureVector(located[0], located[1], pooled.n, pooled.label, pooled.track_id, pooled.sources)
    vals, vecs = np.linalg.eigh(pooled.cov)
    axes = (vecs * (np.sqrt(np.clip(vals, 0.0, None)) * axis_scale)).T
    return ObjectEllipsoid(
        object_id, pooled.label, pooled.mean, pooled.cov, axes, len(members), frozenset(f.track_id for f in members)
    )


def feature_distances(f: FeatureVector, objects: Sequence[ObjectEllipsoid], config: ClusterConfig) -> np.ndarray:
    """Distance D (Sec. 2.4.5) from one feature vector to each object's pooled Gaussian."""
    var_f = np.maximum(f.var, config.var_floor)
    out = np.empty(len(objects))
    for i, o in enumerate(objects):
        pen = 0.0 if o.label == f.label else config.class_penalty
        out[i] = bhattacharyya(f.mean, var_f, o.mean, np.maximum(np.diag(o.cov), config.var_floor)) + pen
    return out


class Clusterer:
    """Intermittent clustering (Sec. 2.4.6, Algorithm 2 lines 9-18): re-cluster only when eq. 2.15 asks.

    ``add`` stores (track-window) feature vectors; ``step`` tests the keyframe's associated
    observations (set M) against the current objects: those within ``fit_distance`` of an object are
    in T, the rest in O. It re-clusters when there are no objects yet, when |M n T| < |M n O| since the
    last clustering (eq. 2.15), or when ``outlier_threshold`` outliers have accumulated, and only if
    new feature vectors arrived since the last clustering.
    """

    def __init__(self, config: ClusterConfig | None = None) -> None:
        self.config = config or ClusterConfig()
        self.features: list[FeatureVector] = []
        self.objects: list[ObjectEllipsoid] = []
        self.reclusterings = 0
        self.keyframe_of: Sequence[int] = ()
        """The keyframe of each observation id of ``FeatureVector.sources`` (``ObjectMapper``'s store)."""
        self.locate: Locate | None = None
        """Where a cluster's object lies (``ellipsoid``); None: its pooled Gaussian."""
        self.judge: Judge | None = None
        """Which objects are kept (``kept``); None: all. The others stay objects here, so that clustering runs as
        it would without them, but are not shown."""
        self.unkept: set[int] = set()
        """The ids of the objects ``judge`` did not keep."""
        self._fit = self._out = self._new = 0
        self._next_id = 1
        self.retired: list[int] = []
        """Tracks retired by the re-clusterings since the owner last took them (``ObjectMapper.take_retired``)."""

    def state(self) -> dict:
        """Plain state: stored feature vectors, objects (and those not kept), eq. 2.15 counters and the next
        object id."""
        return {
            "features": self.features,
            "objects": self.objects,
            "unkept": sorted(self.unkept),
            "reclusterings": self.reclusterings,
            "counts": (self._fit, self._out, self._new),
            "next_id": self._next_id,
        }

    @property
    def kept(self) -> list[ObjectEllipsoid]:
        """The objects ``judge`` kept."""
        return [o for o in self.objects if o.id not in self.unkept]

    def restore(self, state: dict) -> None:
        self.features, self.objects, self.reclusterings = state["features"], state["objects"], state["reclusterings"]
        self.unkept = set(state.get("unkept", ()))  # none in snapshots of earlier versions
        (self._fit, self._out, self._new), self._next_id = state["counts"], state["next_id"]

    def add(self, features: Sequence[FeatureVector | None]) -> None:
        """Store new feature vectors for the next clustering."""
        new = [f for f in features if f is not None]
        self.features.extend(new)
        self._new += len(new)

    def step(
        self, observations: Sequence[FeatureVector | None], associated: Sequence[bool], live: Collection[int] = ()
    ) -> bool:
        """Count the associated observations that fit / miss the objects (eq. 2.15); re-cluster when due
        (``live``: the open tracks, as for ``recluster``)."""
        for f, in_m in zip(observations, associated, strict=True):
            if f is None or not in_m:
                continue
            fits = (
                bool(self.objects)
                and float(feature_distances(f, self.objects, self.config).min()) <= self.config.fit_distance
            )
            self._fit += fits
            self._out += not fits
        if self._due():
            self.recluster(live)
            return True
        return False

    def _due(self) -> bool:
        """Algorithm 2: cluster when none exist; else on eq. 2.15 or the outlier count, given new vectors."""
        if self._new == 0:
            return False
        if not self.objects:
            return len(self.features) >= self.config.min_cluster_size
        return self._fit < self._out or self._out >= self.config.outlier_threshold

    def recluster(self, live: Collection[int] = ()) -> list[ObjectEllipsoid]:
        """Cluster all stored feature vectors (bounded by ``max_features``) into objects, keeping ids. ``live``:
        the tracks still open (the others may be retired into their object's anchor track)."""
        self._compact(live)
        labels = cluster_labels(self.features, self.config) if self.features else np.zeros(0, int)
        clusters = [
            [f for f, c in zip(self.features, labels, strict=True) if c == k]
            for k in range(int(labels.max(initial=-1)) + 1)
        ]
        if self.config.merge_distance > 0:
            clusters = merge_overlapping(clusters, self.config, self.keyframe_of)
        clusters = sorted(self._cut(clusters), key=len, reverse=True)
        objects = self._carry_ids(clusters)
        if self.config.coincident > 0 and len(objects) > 1:
            groups = coincident_groups(
                [o.label for o in objects],
                np.array([o.mean for o in objects]),
                np.array([o.cov for o in objects]),
                self.config.coincident,
                [set().union(*keyframe_sets(c, self.keyframe_of)) for c in clusters] if self.keyframe_of else None,
            )
            if len(groups) < len(objects):
                made = {id(c): o for c, o in zip(clusters, objects, strict=True)}  # the clusters left as they were
                joined = [clusters[g[0]] if len(g) == 1 else [f for i in g for f in clusters[i]] for g in groups]
                clusters = sorted(self._cut(joined, self.locate), key=len, reverse=True)  # not back into its parts
                objects = self._carry_ids(clusters, made)
        if self.judge is not None:
            self.unkept = {o.id for o, ok in zip(objects, self.judge(clusters, objects), strict=True) if not ok}
        self.objects = objects
        self.reclusterings += 1
        self._fit = self._out = self._new = 0
        log.debug("re-clustered %d feature vectors into %d objects", len(self.features), len(self.objects))
        return self.objects

    def _cut(self, clusters: list[list[FeatureVector]], place: Locate | None = None) -> list[list[FeatureVector]]:
        """Clusters that hold two views of one keyframe cut apart (``perception.cannot_link``), if configured;
        not into parts that stand in one place, each part's object pooled or where ``place`` puts it."""
        if not (self.config.split_shared and self.keyframe_of):
            return clusters
        return split_all(clusters, self.keyframe_of, self.config.min_cluster_size, self.config.coincident, place)

    def _compact(self, live: Collection[int]) -> None:
        """At most ``max_features`` vectors where pooling allows (``perception.track_retirement``)."""
        self.features, retired = compacted(self.features, self.objects, live, self.config.max_features)
        self.retired.extend(retired)

    def _carry_ids(
        self, clusters: list[list[FeatureVector]], made: dict[int, ObjectEllipsoid] | None = None
    ) -> list[ObjectEllipsoid]:
        """Objects for new clusters; each keeps the id of the old object sharing most of its tracks. ``made``:
        objects already located, by ``id`` of their cluster's list (only their id is set here)."""
        used: set[int] = set()
        out = []
        for members in clusters:
            tracks = {f.track_id for f in members}
            overlap = [
                (len(tracks & o.tracks), o.id) for o in self.objects if o.label == members[0].label and o.id not in used
            ]
            best = max(overlap, default=(0, 0))
            if best[0] > 0:
                oid = best[1]
            else:
                oid, self._next_id = self._next_id, self._next_id + 1
            used.add(oid)
            known = (made or {}).get(id(members))
            out.append(
                replace(known, id=oid)
                if known is not None
                else ellipsoid(members, oid, self.config.axis_scale, self.locate)
            )
        return out
