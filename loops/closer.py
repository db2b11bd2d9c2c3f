"""Loop closure: propose candidates for each keyframe, verify them geometrically, add robust factors.

Every candidate and its verdict is recorded (``loops`` queryable, ``loops.json``). A loop is accepted only
when (1) PnP-RANSAC between the two keyframes has enough inliers and a small residual
(``loops.verification``), and (2) the measured relative pose agrees with the current graph estimate within
a gate (``loops.acceptance``). After each accepted loop the accepted loops are re-checked against the new
estimate, and one that now disagrees is retracted (a false loop is worse than a missed one).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from graph.interface import Graph
from loops.acceptance import AcceptedLoop, LoopAcceptance
from loops.archive import ColdLog, KeyframeArchive
from loops.candidates import candidates
from loops.place_recognition import PlaceIndex, global_descriptor
from loops.records import Candidate, KeyframeEntry, LoopRecord, Verified
from loops.settings import LoopSettings
from loops.verification import verify
from perception.odometry import Features, Rejected, Relative, RelativePoseEstimator


class LoopCloser:
    """Candidates (proposed, appearance, proximity in the current estimate), verification and acceptance."""

    def __init__(
        self,
        graph: Graph,
        estimator: RelativePoseEstimator,
        settings: LoopSettings | None = None,
    ):
        self.settings = settings or LoopSettings()
        self.estimator = estimator
        self.places = PlaceIndex()
        self.keyframes = KeyframeArchive()
        self.acceptance = LoopAcceptance(graph, self.settings)
        s = self.settings
        self.verify_config = estimator.config.model_copy(
            update={"min_matches": s.min_inliers, "min_inliers": s.min_inliers, "max_residual_px": s.max_residual_px}
        )

    @property
    def graph(self) -> Graph:
        return self.acceptance.graph

    @property
    def records(self) -> list[LoopRecord]:
        """Every candidate judged so far, oldest first."""
        return self.acceptance.records

    @property
    def accepted(self) -> dict[int, AcceptedLoop]:
        """The accepted loops by factor index."""
        return self.acceptance.accepted

    @property
    def n_accepted(self) -> int:
        return self.acceptance.n_accepted

    def state(self) -> dict[str, Any]:
        """Plain state: loop records, accepted factors, place descriptors and keyframe features (``joined``
        of ``parts``)."""
        return joined(*self.parts())

    def parts(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """``state()`` in two parts: nothing small, and the append-only logs (live): the records (a retraction
        changes a record's verdict: ``joined`` applies the retractions log to them), the acceptances and
        retractions, the keyframe entries and the places."""
        a = self.acceptance
        logs = {"records": a.records, "accepted_log": a.accepted_log, "retracted": a.retracted, **self.places.logs()}
        return {}, {**logs, "keyframe_stubs": self.keyframes.stubs, "keyframe_features": self.keyframes.features}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from ``state`` (also as release 0.1.0 saved it: records as dicts, loops as tuples)."""
        records = state["records"]
        self.acceptance.records = [r if isinstance(r, LoopRecord) else LoopRecord.from_json(r) for r in records]
        a = self.acceptance
        a.accepted = {f: v if isinstance(v, AcceptedLoop) else AcceptedLoop(*v) for f, v in state["accepted"].items()}
        retracted = [r.factor for r in a.records if r.reason == "retracted_inconsistent" and r.factor is not None]
        a.accepted_log = list(state.get("accepted_log", a.accepted.items()))  # not saved before the map store
        a.retracted = list(state.get("retracted", retracted))
        self.places.restore(state["places"])
        saved = state["keyframes"]
        self.keyframes = saved if isinstance(saved, KeyframeArchive) else KeyframeArchive.of_entries(saved)

    def add_keyframe(
        self, entry: KeyframeEntry, rgb: np.ndarray, proposed: tuple[Candidate, ...] = ()
    ) -> list[LoopRecord]:
        """Store the keyframe, try its candidates, and return the new loop records (``verify`` + ``accept``)."""
        poses = self.graph.poses() if self.settings.proximity else None
        return self.accept(self.verify(entry, rgb, list(proposed), poses))

    def verify(
        self, entry: KeyframeEntry, rgb: np.ndarray, proposed: list[Candidate], poses: np.ndarray | None = None
    ) -> list[Verified]:
        """Find the keyframe's candidates and verify each geometrically; then store the keyframe.

        Needs no graph (it can run beside the tracking): ``poses`` are the keyframe estimates the proximity
        source searches (None: no proximity candidates). Candidates are verified in order until one passes;
        ``accept`` then gates it against the graph.
        """
        descriptor = global_descriptor(rgb)
        found = candidates(entry, descriptor, proposed, self.keyframes, self.places, poses, self.settings)
        verified = []
        for candidate in found:
            match = self.keyframes[candidate.keyframe]
            verified.append(verify(match, entry, candidate, self.estimator, self.verify_config, self.settings))
            if verified[-1].relative is not None:
                break  # one loop per keyframe is enough; the graph's gate decides on this one in ``accept``
        self.places.add(entry.index, entry.timestamp, descriptor)
        features = entry.features.with_depth() if entry.features is not None else None  # only the 3D side kept
        self.keyframes.add(replace(entry, features=features))
        return verified

    def relocalize(
        self, features: Features, rgb: np.ndarray, allowed: Callable[[int], bool], attempts: int = 3
    ) -> tuple[int, Relative] | None:
        """Place a frame that tracking lost: the stored keyframes it looks most like (``allowed`` ones only, at
        most ``attempts`` of them) verified by PnP with the loop thresholds; the first that passes and its
        ``T_keyframe_frame``, else None. Reads the database as it stands (safe beside a mapping thread)."""
        s = self.settings
        found = self.places.query(global_descriptor(rgb), np.inf, 0.0, 4 * attempts, s.min_similarity)
        tried = 0
        for candidate in found:
            entry = self.keyframes.get(candidate.index)
            if entry is None or entry.features is None or not allowed(candidate.index):
                continue
            tried += 1
            try:
                return candidate.index, self.estimator.estimate(entry.features, features, self.verify_config)
            except Rejected:
                pass
            if tried >= attempts:
                break
        return None

    def accept(self, verified: list[Verified]) -> list[LoopRecord]:
        """Gate verified candidates against the graph (``LoopAcceptance.accept``); the new records."""
        return self.acceptance.accept(verified)


def joined(small: dict[str, Any], logs: dict[str, Any], materialize: bool = True) -> dict[str, Any]:
    """``LoopCloser.state()`` of its parts (logs as sequences); ``materialize``: the keyframes as a list of
    entries with their features (plain data), else as a ``KeyframeArchive`` that reads spilled ones on demand."""
    retracted = set(logs["retracted"])
    records = [
        replace(r, accepted=False, reason="retracted_inconsistent") if r.accepted and r.factor in retracted else r
        for r in logs["records"]
    ]
    keyframes = KeyframeArchive(logs["keyframe_stubs"], ColdLog.of(logs["keyframe_features"]))
    return {
        "records": records,
        "accepted": {f: loop for f, loop in logs["accepted_log"] if f not in retracted},
        "accepted_log": list(logs["accepted_log"]),
        "retracted": list(logs["retracted"]),
        "places": PlaceIndex.joined(logs),
        "keyframes": keyframes.entries() if materialize else keyframes,
    }
