"""Online object mapping (Algorithm 2): NPDA to the previous keyframe, tracks, feature vectors, clustering."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from graph.geometry import inverse
from perception.amodal import cut_by_border, cut_vertically, detection_feature
from perception.anchoring import anchored_segments
from perception.camera import Intrinsics
from perception.clustering import ClusterConfig, Clusterer, ObjectEllipsoid
from perception.coco import FLOOR_CLASSES
from perception.existence import Looks
from perception.features import (
    FeatureConfig,
    FeatureVector,
    hidden_by_twin,
    repooled,
    transform_feature,
)
from perception.floor import (
    SCREEN_ASPECT,
    Floor,
    FloorConfig,
    ends_seen,
    level_plane,
    on_floor,
    screen_span,
    vertical_span,
    with_span,
    world_floor_view,
)
from perception.footprint import LARGE_CLASSES, horizontal_axes, robust_gaussian, shares_of, union_footprint
from perception.frame import Detection
from perception.npda import NPDAConfig, associate
from perception.tracks import Tracker

MAX_FLOOR_VIEWS = 500
"""Keyframes whose floor planes are kept (the newest): the floor needs many views, not all of them (and the
floor under the robot is the one seen lately: a long run may change levels)."""


def _floor_columns(views: dict[int, tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """Floor views as three arrays (keyframes, planes, poses): a checkpoint copies them, not pickles each."""
    return {
        "keyframes": np.fromiter(views, np.int64, len(views)),
        "planes": np.array([p for p, _ in views.values()], float).reshape(-1, 4),
        "poses": np.array([T for _, T in views.values()], float).reshape(-1, 4, 4),
    }


def _floor_rows(saved: dict) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``_floor_columns`` back as rows (or a state of 2026-12-03, a dict of rows, as it is); the newest
    ``MAX_FLOOR_VIEWS``."""
    if "planes" in saved:
        rows = zip(saved["keyframes"], saved["planes"], saved["poses"], strict=True)
        saved = {int(k): (np.array(p, float), np.array(T, float)) for k, p, T in rows}
    return dict(list(saved.items())[-MAX_FLOOR_VIEWS:])


def _has(poses: Mapping[int, np.ndarray] | np.ndarray, k: int) -> bool:
    """Whether ``poses`` (a mapping, or an array indexed by keyframe) holds keyframe ``k``."""
    return k in poses if isinstance(poses, Mapping) else 0 <= k < len(poses)


def _weighed(f: FeatureVector | None, whole: bool, cut_weight: float) -> FeatureVector | None:
    """A view's feature vector, its point count scaled by ``cut_weight`` when the image border cuts its box."""
    if f is None or whole:
        return f
    return replace(f, n=max(1, round(f.n * cut_weight)))


@dataclass
class _Keyframe:
    detections: list[Detection]
    depth_m: np.ndarray
    pose: np.ndarray
    index: int = -1


class ObjectMapper:
    """Objects from keyframe detections. ``add_keyframe`` takes colour-registered depth, the colour intrinsics and
    the colour camera's camera-to-world pose; only the previous keyframe's depth is kept.

    Every observation is also kept in its camera frame with its keyframe (the observation store), and every
    feature vector names the observations it pools, so ``repose`` recomputes all feature vectors exactly
    from new keyframe poses and re-clusters (Sec. 2.4.7: after an optimisation moved the poses).
    """

    def __init__(
        self,
        npda: NPDAConfig | None = None,
        clustering: ClusterConfig | None = None,
        features: FeatureConfig | None = None,
        tracker: Tracker | None = None,
        floor: FloorConfig | None = None,
    ):
        self.npda = npda if npda is not None else NPDAConfig()
        self.features = features if features is not None else FeatureConfig()
        self.tracker = tracker or Tracker()
        self.clusterer = Clusterer(clustering)
        self._prev: _Keyframe | None = None
        self.associations = 0
        self._obs_keyframe: list[int] = []
        self.clusterer.keyframe_of = self._obs_keyframe  # two observations of one keyframe: two objects
        self.floor_config = floor if floor is not None else FloorConfig()
        self._floor_views: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        """Per keyframe whose lower half shows a level plane below the camera: that plane (camera frame) and the
        keyframe's camera-to-world pose (``repose`` updates it); the newest ``MAX_FLOOR_VIEWS``."""
        self._floor: Floor | None = None
        self._floor_stale = False
        self._floor_saved: dict[str, np.ndarray] | None = None  # ``_floor_columns`` of the views, until they change
        self.clusterer.locate = self._locate
        self.looks = Looks()
        """The keyframes the detector ran on: an object seen in too few of those that had it in view is not kept."""
        self.clusterer.judge = self._judge
        self._obs_local: list[FeatureVector] = []
        self._obs_cut: list[tuple[bool, bool]] = []
        """Per observation: whether the image's top and bottom edges cut its box (``floor.vertical_span``)."""
        self.last_observations: list[tuple[int, np.ndarray, float]] = []
        """The latest keyframe's (track id, camera-frame centroid, largest std of its points (m)) per detection
        with enough depth whose box the image border does not cut (a cut box measures part of the object)."""

    def add_keyframe(
        self,
        index: int,
        detections: list[Detection],
        depth_m: np.ndarray,
        K: Intrinsics,
        pose: np.ndarray,
        looked: bool = True,
    ) -> bool:
        """Associate, extend tracks, store feature vectors, re-cluster when due; True if it re-clustered.
        ``looked``: whether the detector ran on this keyframe (a keyframe it skipped misses no object)."""
        if looked:
            self.looks.add(index, pose, K, (depth_m.shape[1], depth_m.shape[0]))
        pairs = []
        if self._prev is not None and detections and self._prev.detections:
            pairs = associate(
                self._prev.detections,
                self._prev.depth_m,
                detections,
                depth_m,
                K,
                inverse(pose) @ self._prev.pose,
                self.npda,
            ).pairs
        self.associations += len(pairs)
        ids = self.tracker.update(index, [d.label for d in detections], pairs)
        h, w = depth_m.shape[:2]
        whole = [not any(cut_by_border(d.box, w, h)) for d in detections]
        plane = level_plane(depth_m, K, self.floor_config)
        up = self._camera_up(pose, plane)
        ground = self._ground(pose, plane)
        found = anchored_segments(depth_m, [(d.box, d.label) for d in detections], self.features)
        segments = [f[2] for f in found]
        occluders = [[s for s in segments if s is not None and s is not mine] for mine in segments]
        twins = [
            [
                s
                for s, e in zip(segments, detections, strict=True)
                if s is not None and e is not d and e.label == d.label
            ]
            for d in detections
        ]
        hidden = [
            s is not None and hidden_by_twin(s, t, self.features.gap_m) for s, t in zip(segments, twins, strict=True)
        ]
        local = [
            None
            if behind
            else _weighed(
                detection_feature(depth_m, K, d.box, d.label, t, self.features, up, others, own, ground),
                inside,
                self.features.cut_weight,
            )
            for d, t, inside, others, own, behind in zip(detections, ids, whole, occluders, found, hidden, strict=True)
        ]
        obs = [
            None if f is None else transform_feature(self._store(index, f, cut_vertically(d.box, h)), pose)
            for f, d in zip(local, detections, strict=True)
        ]
        if plane is not None:
            self._floor_views[index] = (plane, np.array(pose, float))
            while len(self._floor_views) > MAX_FLOOR_VIEWS:
                del self._floor_views[next(iter(self._floor_views))]
            self._floor_stale, self._floor_saved = True, None
        self.last_observations = [
            (t, f.mean, float(np.sqrt(np.linalg.eigvalsh(f.cov)[-1])))
            for f, t, inside in zip(local, ids, whole, strict=True)
            if f is not None and inside
        ]
        pooled = [self.tracker.observe(t, f) for t, f in zip(ids, obs, strict=True)]
        self.clusterer.add([*pooled, *self.tracker.close_stale(index)])
        self._prev = _Keyframe(detections, depth_m, pose, index)
        return self.clusterer.step(obs, [self.tracker.associated(t) for t in ids], self.tracker.tracks.keys())

    def _camera_up(self, pose: np.ndarray, plane: np.ndarray | None) -> np.ndarray | None:
        """The world's up in the camera frame of ``pose``: the floor's, else this keyframe's level plane's, else
        None (unknown: views are completed along their rays as they are)."""
        floor = self.floor
        if floor is not None:
            return np.asarray(pose)[:3, :3].T @ floor.up
        return None if plane is None else plane[:3] / np.linalg.norm(plane[:3])

    def _ground(self, pose: np.ndarray, plane: np.ndarray | None) -> float | None:
        """The floor's height along ``_camera_up`` in the camera frame of ``pose``: the floor's, else (before the
        keyframes agree on one) this keyframe's level plane's, else None. On 7-Scenes the floor is agreed from the
        seventh keyframe on; the chair views of the first six were completed without it (``perception.backrest``)."""
        floor = self.floor
        if floor is not None:
            return floor.height - float(floor.up @ np.asarray(pose)[:3, 3])
        return None if plane is None else float(-plane[3] / np.linalg.norm(plane[:3]))

    @property
    def floor(self) -> Floor | None:
        """The floor the keyframes agree on (``perception.floor``), None until ``FloorConfig.min_keyframes`` do."""
        if self._floor_stale:
            views = [world_floor_view(p, T) for p, T in self._floor_views.values()]
            normals, feet = (np.array([v[k] for v in views]).reshape(-1, 3) for k in (0, 1))
            self._floor = Floor.estimate(normals, feet, self.floor_config)
            self._floor_stale = False
        return self._floor

    def _locate(self, members: Sequence[FeatureVector]) -> tuple[np.ndarray, np.ndarray] | None:
        """An object from its views: robust to the few that are another object's (``robust_gaussian``), as wide
        as its views together when it is larger than a view (``perception.footprint``), and reaching down to the
        floor when it stands on it (``perception.floor.on_floor``)."""
        n = np.array([f.n for f in members], float)
        means, covs = np.stack([f.mean for f in members]), np.stack([f.cov for f in members])
        mean, cov = robust_gaussian(means, covs, n)
        floor = self.floor
        if floor is None:
            return mean, cov
        if members[0].label in LARGE_CLASSES:
            mean, cov = union_footprint(mean, cov, (means, covs, n), floor.up, shares_of(members[0].label))
        cut = None
        if all(f.sources for f in members):  # whether the image's top / bottom edge cut each view's box
            cut = np.array([[all(self._obs_cut[x][k] for x in f.sources) for k in (0, 1)] for f in members])
        if members[0].label in FLOOR_CLASSES:
            top_cut = None if cut is None else cut[:, 0]
            return on_floor(mean, cov, (means, covs, n), floor, self.floor_config, top_cut) or (mean, cov)
        if cut is not None:
            span = vertical_span(means, covs, n, floor.up, cut)
            if span is not None and members[0].label in SCREEN_ASPECT:
                wide = horizontal_axes(cov, floor.up)[0]
                height = SCREEN_ASPECT[members[0].label] * float(np.sqrt(12.0 * wide @ cov @ wide))
                span = screen_span(span, ends_seen(cut), height)
            if span is not None:
                mean, cov = with_span(mean, cov, floor.up, *span)
        return mean, cov

    def _judge(self, clusters: Sequence[Sequence[FeatureVector]], objects: Sequence[ObjectEllipsoid]) -> list[bool]:
        """Which of the objects of ``clusters`` are kept: those seen often enough where they stood in view."""
        of = self._obs_keyframe
        seen = [{of[s] for f in members for s in f.sources if s < len(of)} for members in clusters]
        centres = np.array([o.mean for o in objects], float).reshape(-1, 3)
        return self.looks.judged(centres, np.array([o.cov for o in objects], float).reshape(-1, 3, 3), seen)

    def observation(self, source: int) -> tuple[int, FeatureVector]:
        """A stored observation (a ``FeatureVector.sources`` id): its keyframe and camera-frame feature vector."""
        return self._obs_keyframe[source], self._obs_local[source]

    @property
    def observations(self) -> int:
        """How many keyframe observations are stored."""
        return len(self._obs_local)

    def _store(self, keyframe: int, local: FeatureVector, cut: tuple[bool, bool] = (False, False)) -> FeatureVector:
        """Keep a camera-frame observation; the same vector tagged with its store id."""
        self._obs_keyframe.append(keyframe)
        self._obs_cut.append(cut)
        self._obs_local.append(
            FeatureVector(local.mean, local.cov, local.n, local.label, local.track_id, (len(self._obs_local),))
        )
        return self._obs_local[-1]

    def repose(self, poses: Mapping[int, np.ndarray] | np.ndarray) -> list[ObjectEllipsoid]:
        """Recompute every feature vector from new camera-to-world keyframe poses and re-cluster (Sec. 2.4.7).

        ``poses[k]`` is the colour camera's pose of keyframe ``k`` (the index given to ``add_keyframe``).
        Vectors pooled from several observations are re-pooled from their observations, so the result
        equals mapping the sequence again with the new poses (tracks and associations stay as they were).
        """
        if not self._obs_local:
            return self.clusterer.kept
        T = np.stack([poses[k] for k in self._obs_keyframe])
        R, t = T[:, :3, :3], T[:, :3, 3]
        means = np.einsum("nij,nj->ni", R, np.stack([f.mean for f in self._obs_local])) + t
        covs = np.einsum("nij,njk,nlk->nil", R, np.stack([f.cov for f in self._obs_local]), R)

        n = np.array([f.n for f in self._obs_local], float)
        self.clusterer.features = repooled(self.clusterer.features, means, covs, n)
        for track in self.tracker.tracks.values():
            track.window = repooled(track.window, means, covs, n)
        if self._prev is not None and self._prev.index >= 0:
            self._prev.pose = np.asarray(poses[self._prev.index])
        for k, (plane, pose) in list(self._floor_views.items()):
            self._floor_views[k] = (plane, np.array(poses[k], float) if _has(poses, k) else pose)
        self._floor_stale, self._floor_saved = True, None
        self.looks.moved({k: np.asarray(poses[k]) for k in self.looks.poses if _has(poses, k)})
        self.clusterer.recluster(self.tracker.tracks.keys())
        return self.clusterer.kept

    def take_retired(self) -> list[int]:
        """The tracks the re-clusterings retired since the last call (``perception.track_retirement``)."""
        out, self.clusterer.retired = self.clusterer.retired, []
        return out

    def state(self) -> dict:
        """Plain state: tracker, clusterer, the previous keyframe (detections, depth, pose), counters, store
        (``joined`` of ``parts``)."""
        return joined(*self.parts())

    def parts(self) -> tuple[dict, dict]:
        """``state()`` in two parts: what is bounded (tracker, previous keyframe, objects, floor views) and the
        append-only logs (live): the observation store and the clusterer's feature vectors (which a merge of
        track runs replaces)."""
        prev = (
            None
            if self._prev is None
            else (self._prev.detections, self._prev.depth_m, self._prev.pose, self._prev.index)
        )
        clusterer = {k: v for k, v in self.clusterer.state().items() if k != "features"}
        small = {
            "tracker": self.tracker.state(),
            "clusterer": clusterer,
            "prev": prev,
            "associations": self.associations,
            "floor_views": self._floor_saved or self._saved_floor(),
            "looks": self.looks.state(),
        }
        logs = {
            "observations.keyframe": self._obs_keyframe,
            "observations.local": self._obs_local,
            "observations.cut": self._obs_cut,
            "clusterer.features": self.clusterer.features,
        }
        return small, logs

    def _saved_floor(self) -> dict[str, np.ndarray]:
        self._floor_saved = _floor_columns(self._floor_views)
        return self._floor_saved

    def restore(self, state: dict) -> None:
        self.tracker.restore(state["tracker"])
        self.clusterer.restore(state["clusterer"])
        self._prev = None if state["prev"] is None else _Keyframe(*state["prev"])
        self.associations = state["associations"]
        store = state.get("observations", {"keyframe": [], "local": []})
        self._obs_keyframe, self._obs_local = [int(k) for k in store["keyframe"]], list(store["local"])
        cut = store.get("cut", np.zeros((len(self._obs_local), 2), bool))  # none before 2026-12-03: taken as uncut
        self._obs_cut = [(bool(t), bool(b)) for t, b in cut]
        self.clusterer.keyframe_of = self._obs_keyframe
        self._floor_views = _floor_rows(state.get("floor_views", {}))  # none in snapshots of earlier versions
        self._floor_stale, self._floor_saved = True, None
        self.looks.restore(state.get("looks", {}))  # none in snapshots of earlier versions: judged from now on

    def finish(self) -> list[ObjectEllipsoid]:
        """End of sequence: emit every open track window and re-cluster once more."""
        self.clusterer.add(self.tracker.flush())
        self.clusterer.recluster(self.tracker.tracks.keys())
        return self.clusterer.kept

    @property
    def objects(self) -> list[ObjectEllipsoid]:
        """The objects kept (``Clusterer.kept``)."""
        return self.clusterer.kept


def object_json(o: ObjectEllipsoid, landmark: np.ndarray | None = None) -> dict:
    """The ``objects.json`` entry of SPEC section 4, plus ``landmark``: the object's iSAM2 landmark estimate
    (world position) once it is in the graph, else null."""
    return {
        "id": int(o.id),
        "label": o.label,
        "mean": [float(v) for v in o.mean],
        "cov": np.asarray(o.cov, float).tolist(),
        "axes": np.asarray(o.axes, float).tolist(),
        "n_observations": int(o.n_observations),
        "landmark": None if landmark is None else [float(v) for v in landmark],
    }


def joined(small: dict, logs: dict) -> dict:
    """``ObjectMap.state()`` of its parts (logs as sequences)."""
    return {
        **{k: v for k, v in small.items() if k != "clusterer"},
        "clusterer": {**small["clusterer"], "features": list(logs["clusterer.features"])},
        "observations": {
            "keyframe": np.array(list(logs["observations.keyframe"]), np.int64),
            "local": list(logs["observations.local"]),
            "cut": np.array(list(logs["observations.cut"]), bool).reshape(-1, 2),
        },
    }
