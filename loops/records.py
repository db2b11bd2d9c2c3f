"""What loop closure records: a keyframe it can match against, a candidate, and the verdict on it.

A ``LoopRecord`` is one candidate with its verification figures and verdict (``loops`` queryable,
``loops.json``). ``to_json`` writes the documented fields (docs/protocol.md) in a fixed order, only those
the candidate reached: a candidate rejected by PnP has no residual, one never gated no gate figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import StrEnum
from typing import Any

from perception.odometry import Features, Relative


class Source(StrEnum):
    """Where a candidate came from."""

    APPEARANCE = "appearance"
    PROXIMITY = "proximity"
    POLICY = "policy"


@dataclass
class KeyframeEntry:
    """What loop closure keeps of a keyframe."""

    index: int
    timestamp: float
    frame: int
    features: Features | None


@dataclass(frozen=True)
class Candidate:
    """An earlier keyframe that may show the same place; ``score`` is the source's (similarity, probability)."""

    keyframe: int
    source: Source
    score: float = math.nan


@dataclass
class LoopRecord:
    """One loop-closure candidate and its verdict (field meanings in docs/protocol.md)."""

    query_t: float
    match_t: float
    query_frame: int
    match_frame: int
    query_keyframe: int
    match_keyframe: int
    source: str
    accepted: bool = False
    similarity: float | None = None
    policy_probability: float | None = None
    reason: str | None = None
    matches: int | None = None
    inliers: int | None = None
    residual_px: float | None = None
    relative_pose: list[float] | None = None
    distance_m: float | None = None
    angle_deg: float | None = None
    translation_diff_m: float | None = None
    rotation_diff_deg: float | None = None
    factor: int | None = None

    _PREFIX = (
        "query_t",
        "match_t",
        "query_frame",
        "match_frame",
        "query_keyframe",
        "match_keyframe",
        "source",
        "accepted",
        "similarity",
    )
    _MEASURED = ("matches", "inliers", "residual_px", "relative_pose", "distance_m", "angle_deg")

    def to_json(self) -> dict[str, Any]:
        """The record as the ``loops`` reply and ``loops.json`` give it."""
        out = {name: getattr(self, name) for name in self._PREFIX}
        if self.source == Source.POLICY.value:
            out["policy_probability"] = self.policy_probability
        if self.residual_px is None:  # rejected by the relative pose estimation
            out.update(reason=self.reason, matches=self.matches, inliers=self.inliers)
            return out
        out.update({name: getattr(self, name) for name in self._MEASURED})
        if self.translation_diff_m is not None:  # gated against the graph
            out.update(translation_diff_m=self.translation_diff_m, rotation_diff_deg=self.rotation_diff_deg)
        out["reason"] = self.reason
        if self.factor is not None:
            out["factor"] = self.factor
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> LoopRecord:
        """A record from its JSON form (and from the dicts that snapshots of release 0.1.0 hold)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


@dataclass
class Verified:
    """A candidate after geometric verification: its record so far, and the relative pose when it passed."""

    record: LoopRecord
    relative: Relative | None = None
