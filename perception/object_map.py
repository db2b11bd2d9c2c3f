"""Online object mapping (Algorithm 2): NPDA to the previous keyframe, tracks, feature vectors, clustering."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.geometry import inverse
from perception.clustering import ClusterConfig, Clusterer, ObjectEllipsoid
from perception.features import FeatureConfig, backproject_detection, feature_from_points
from perception.frame import Detection
from perception.npda import NPDAConfig, associate
from perception.tracks import Tracker


@dataclass
class _Keyframe:
    detections: list[Detection]
    depth_m: np.ndarray
    pose: np.ndarray


class ObjectMapper:
    """Objects from keyframe detections. ``add_keyframe`` takes colour-registered depth, the colour K and
    the colour camera's camera-to-world pose; only the previous keyframe's depth is kept."""

    def __init__(self, npda: NPDAConfig = NPDAConfig(), clustering: ClusterConfig = ClusterConfig(),
                 features: FeatureConfig = FeatureConfig(), tracker: Tracker | None = None):
        self.npda, self.features = npda, features
        self.tracker = tracker or Tracker()
        self.clusterer = Clusterer(clustering)
        self._prev: _Keyframe | None = None
        self.associations = 0

    def add_keyframe(self, index: int, detections: list[Detection], depth_m: np.ndarray, K: np.ndarray,
                     pose: np.ndarray) -> bool:
        """Associate, extend tracks, store feature vectors, re-cluster when due; True if it re-clustered."""
        pairs = []
        if self._prev is not None and detections and self._prev.detections:
            pairs = associate(self._prev.detections, self._prev.depth_m, detections, depth_m, K,
                              inverse(pose) @ self._prev.pose, self.npda).pairs
        self.associations += len(pairs)
        ids = self.tracker.update(index, [d.label for d in detections], pairs)
        obs = [feature_from_points(backproject_detection(depth_m, K, pose, d.box, self.features), d.label, t)
               for d, t in zip(detections, ids)]
        self.clusterer.add([self.tracker.observe(t, f) for t, f in zip(ids, obs)] + self.tracker.close_stale(index))
        self._prev = _Keyframe(detections, depth_m, pose)
        return self.clusterer.step(obs, [self.tracker.associated(t) for t in ids])

    def state(self) -> dict:
        """Plain state: tracker, clusterer, the previous keyframe (detections, depth, pose), counters."""
        prev = None if self._prev is None else (self._prev.detections, self._prev.depth_m, self._prev.pose)
        return {"tracker": self.tracker.state(), "clusterer": self.clusterer.state(), "prev": prev,
                "associations": self.associations}

    def restore(self, state: dict) -> None:
        self.tracker.restore(state["tracker"])
        self.clusterer.restore(state["clusterer"])
        self._prev = None if state["prev"] is None else _Keyframe(*state["prev"])
        self.associations = state["associations"]

    def finish(self) -> list[ObjectEllipsoid]:
        """End of sequence: emit every open track window and re-cluster once more."""
        self.clusterer.add(self.tracker.flush())
        return self.clusterer.recluster()

    @property
    def objects(self) -> list[ObjectEllipsoid]:
        return self.clusterer.objects


def object_json(o: ObjectEllipsoid) -> dict:
    """The ``objects.json`` entry of SPEC section 4."""
    return {"id": int(o.id), "label": o.label, "mean": [float(v) for v in o.mean],
            "cov": np.asarray(o.cov, float).tolist(), "axes": np.asarray(o.axes, float).tolist(),
            "n_observations": int(o.n_observations)}
