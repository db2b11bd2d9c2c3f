"""Loop closure: propose candidates for each keyframe, verify them geometrically, add robust factors.

Every candidate and its verdict is recorded (``loops`` queryable, ``loops.json``). A loop is accepted only
when (1) PnP-RANSAC between the two keyframes has enough inliers and a small residual, and (2) the
measured relative pose agrees with the current graph estimate within a gate. After each accepted loop the
accepted loops are re-checked against the new estimate, and one that now disagrees is retracted through
iSAM2's removeFactorIndices (a false loop is worse than a missed one).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from graph.geometry import motion_magnitude, pose_to_tum, relative
from graph.interface import Graph
from loops.place_recognition import PlaceIndex, global_descriptor
from perception.odometry import Features, Rejected, Relative, RelativePoseEstimator

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopConfig:
    """Candidate search, verification thresholds and the consistency gate."""

    source: str = "appearance"
    min_gap_s: float = 5.0
    top_k: int = 3
    min_similarity: float = 0.5
    min_inliers: int = 40
    max_residual_px: float = 2.0
    gate_m: float = 0.5
    gate_deg: float = 20.0
    retract_m: float = 0.15
    retract_deg: float = 5.0
    sigma_floor_m: float = 0.01
    sigma_floor_deg: float = 0.5
    proximity: bool = True
    proximity_m: float = 0.3
    max_loop_m: float = 0.25
    max_loop_deg: float = 17.0
    proximity_deg: float = 25.0
    proximity_k: int = 2


@dataclass
class KeyframeEntry:
    """What loop closure keeps of a keyframe."""

    index: int
    timestamp: float
    frame: int
    features: Features


@dataclass
class Verified:
    """A candidate after geometric verification: its loop record so far, and the relative pose when it
    passed (None when rejected)."""

    record: dict[str, Any]
    relative: Relative | None = None


@dataclass
class LoopCloser:
    """Candidates (appearance, and geometric proximity in the current estimate) + geometric verification."""

    graph: Graph
    estimator: RelativePoseEstimator
    config: LoopConfig = LoopConfig()
    records: list[dict[str, Any]] = field(default_factory=list)
    accepted: dict[int, tuple[int, int, np.ndarray]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.places = PlaceIndex()
        self.keyframes: dict[int, KeyframeEntry] = {}
        c = self.config
        self.verify_config = replace(
            self.estimator.config,
            min_matches=c.min_inliers,
            min_inliers=c.min_inliers,
            max_residual_px=c.max_residual_px,
        )

    @property
    def n_accepted(self) -> int:
        return sum(1 for r in self.records if r["accepted"])

    @property
    def n_rejected(self) -> int:
        return len(self.records) - self.n_accepted

    def state(self) -> dict[str, Any]:
        """Plain state: loop records, accepted factors, place descriptors and keyframe features."""
        return {
            "records": self.records,
            "accepted": self.accepted,
            "places": self.places.state(),
            "keyframes": list(self.keyframes.values()),
        }

    def restore(self, state: dict[str, Any]) -> None:
        self.records, self.accepted = state["records"], state["accepted"]
        self.places.restore(state["places"])
        self.keyframes = {e.index: e for e in state["keyframes"]}

    def add_keyframe(
        self, entry: KeyframeEntry, rgb: np.ndarray, proposed: list[tuple[int, str, float]] = ()
    ) -> list[dict[str, Any]]:
        """Store the keyframe, try its candidates, and return the new loop records (``verify`` + ``accept``)."""
        poses = self.graph.poses() if self.config.proximity else None
        return self.accept(self.verify(entry, rgb, proposed, poses))

    def verify(
        self,
        entry: KeyframeEntry,
        rgb: np.ndarray,
        proposed: list[tuple[int, str, float]] = (),
        poses: np.ndarray | None = None,
    ) -> list[Verified]:
        """Find the keyframe's candidates and verify each geometrically; then store the keyframe.

        Needs no graph (it can run beside the tracking): ``poses`` are the keyframe estimates the proximity
        source searches (None: no proximity candidates). ``proposed`` are candidates from elsewhere (the RL
        policy: (keyframe, source, score)), tried first; the appearance and proximity sources run when
        ``source`` is appearance or both. Candidates are verified in this order until one passes; ``accept``
        then gates it against the graph.
        """
        descriptor = global_descriptor(rgb)
        c = self.config
        candidates = [(i, src, score) for i, src, score in proposed if i in self.keyframes]
        classical = c.source in ("appearance", "both")
        if classical:
            tried = {i for i, _, _ in candidates}
            candidates += [
                (cand.index, "appearance", cand.similarity)
                for cand in self.places.query(descriptor, entry.timestamp, c.min_gap_s, c.top_k, c.min_similarity)
                if cand.index not in tried
            ]
        if classical and c.proximity and poses is not None:
            tried = {i for i, _, _ in candidates}
            candidates += [(i, "proximity", float("nan")) for i in self._nearby(entry, poses) if i not in tried]
        verified = []
        for index, source, similarity in candidates:
            verified.append(self._verify(self.keyframes[index], entry, source, similarity))
            if verified[-1].relative is not None:
                break  # one loop per keyframe is enough; the graph's gate decides on this one in ``accept``
        self.places.add(entry.index, entry.timestamp, descriptor)
        self.keyframes[entry.index] = replace(entry, features=entry.features.with_depth())  # only 3D side kept
        return verified

    def accept(self, verified: list[Verified]) -> list[dict[str, Any]]:
        """Gate verified candidates against the graph; the first that agrees becomes a robust loop factor.

        Candidates after an accepted one are not recorded (one loop per keyframe is enough to pull the
        graph). After an acceptance every accepted loop is re-checked. Returns the new records.
        """
        new: list[dict[str, Any]] = []
        for v in verified:
            new.append(self._gate(v) if v.relative is not None else dict(v.record))
            if new[-1]["accepted"]:
                break
        self.records.extend(new)
        if any(r["accepted"] for r in new):
            self._recheck()
        return new

    def _nearby(self, entry: KeyframeEntry, poses: np.ndarray) -> list[int]:
        """Old keyframes whose estimate (in ``poses``) lies near the new one's (geometric candidates)."""
        c = self.config
        old = [k for k, e in self.keyframes.items() if e.timestamp <= entry.timestamp - c.min_gap_s]
        if not old or entry.index >= len(poses):
            return []
        here = poses[entry.index]
        dist = np.linalg.norm(poses[old, :3, 3] - here[:3, 3], axis=1)
        near = []
        for i in np.argsort(dist):
            if dist[i] > c.proximity_m or len(near) >= c.proximity_k:
                break
            _, angle = motion_magnitude(relative(poses[old[i]], here))
            if math.degrees(angle) <= c.proximity_deg:
                near.append(old[i])
        return near

    def _verify(self, match: KeyframeEntry, query: KeyframeEntry, source: str, similarity: float) -> Verified:
        """PnP-RANSAC between the two keyframes and the viewpoint check; no graph involved."""
        record: dict[str, Any] = {
            "query_t": query.timestamp,
            "match_t": match.timestamp,
            "query_frame": query.frame,
            "match_frame": match.frame,
            "query_keyframe": query.index,
            "match_keyframe": match.index,
            "source": source,
            "accepted": False,
            "similarity": None if math.isnan(similarity) or source == "policy" else round(similarity, 4),
        }
        if source == "policy":
            record["policy_probability"] = round(similarity, 4)
        try:
            rel = self.estimator.estimate(match.features, query.features, self.verify_config)
        except Rejected as exc:
            record.update(reason=exc.reason, matches=exc.matches, inliers=exc.inliers)
            return Verified(record)
        record.update(matches=rel.matches, inliers=rel.inliers, residual_px=round(rel.residual_px, 3))
        dist, angle = motion_magnitude(rel.T_a_b)
        record["relative_pose"] = [round(float(v), 6) for v in pose_to_tum(rel.T_a_b)]
        record.update(distance_m=round(dist, 4), angle_deg=round(math.degrees(angle), 3))
        if dist > self.config.max_loop_m or math.degrees(angle) > self.config.max_loop_deg:
            record["reason"] = "viewpoints_too_far_apart"
            return Verified(record)
        return Verified(record, rel)

    def _gate(self, v: Verified) -> dict[str, Any]:
        """A verified relative pose against the graph's estimate; added as a Huber factor when it agrees."""
        record, rel = dict(v.record), v.relative
        a, b = record["match_keyframe"], record["query_keyframe"]
        estimate = relative(self.graph.pose(a), self.graph.pose(b))
        dt, dr = motion_magnitude(relative(estimate, rel.T_a_b))
        record.update(translation_diff_m=round(dt, 4), rotation_diff_deg=round(math.degrees(dr), 3))
        if dt > self.config.gate_m or math.degrees(dr) > self.config.gate_deg:
            record["reason"] = "inconsistent_with_odometry"
            return record
        sigma_m = max(self.config.sigma_floor_m, rel.sigma_m)
        sigma_deg = max(self.config.sigma_floor_deg, rel.sigma_deg)
        factor = self.graph.add_loop(a, b, rel.T_a_b, sigma_m, sigma_deg)
        self.accepted[factor] = (a, b, rel.T_a_b)
        record.update(accepted=True, reason="verified", factor=factor)
        log.info("loop closure accepted: keyframe %d <-> %d (%d inliers)", a, b, rel.inliers)
        return record

    def _recheck(self) -> None:
        """Retract accepted loops that disagree with the estimate the other loops now give."""
        bad = []
        for factor, (a, b, T_a_b) in self.accepted.items():
            dt, dr = motion_magnitude(relative(relative(self.graph.pose(a), self.graph.pose(b)), T_a_b))
            if dt > self.config.retract_m or math.degrees(dr) > self.config.retract_deg:
                bad.append(factor)
        if not bad:
            return
        self.graph.remove_factors(bad)
        for factor in bad:
            del self.accepted[factor]
            for r in self.records:
                if r.get("factor") == factor:
                    r.update(accepted=False, reason="retracted_inconsistent")
            log.warning("loop closure factor %d retracted: inconsistent with the other loops", factor)
