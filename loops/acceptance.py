"""Acceptance and retraction of verified loops against the graph.

A verified relative pose is accepted when it agrees with the graph's current estimate within a gate; it
becomes a Huber between-factor. After each acceptance every accepted loop is re-checked against the new
estimate, and one that now disagrees is retracted through iSAM2's removeFactorIndices.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from graph.geometry import disagreements, motion_magnitude, relative
from graph.interface import Graph
from loops.records import LoopRecord, Verified
from loops.settings import LoopSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AcceptedLoop:
    """An accepted loop factor: keyframes a and b and the measured pose of b in a."""

    a: int
    b: int
    T_a_b: np.ndarray


@dataclass
class LoopAcceptance:
    """The accepted loops of a graph, and the records of every candidate judged."""

    graph: Graph
    settings: LoopSettings
    records: list[LoopRecord] = field(default_factory=list)
    accepted: dict[int, AcceptedLoop] = field(default_factory=dict)  # by factor index
    accepted_log: list[tuple[int, AcceptedLoop]] = field(default_factory=list)  # every acceptance, in order
    retracted: list[int] = field(default_factory=list)  # the factors of the retracted ones, in order
    joined: Callable[[int, int], bool] | None = None
    """Whether two keyframes' map segments are already joined (``slam.segments``); a verified loop between
    segments that are not is accepted without the gate: their relative estimate is only a gauge's guess."""

    @property
    def n_accepted(self) -> int:
        return sum(1 for r in self.records if r.accepted)

    def accept(self, verified: list[Verified]) -> list[LoopRecord]:
        """Gate verified candidates against the graph; the first that agrees becomes a robust loop factor.

        Candidates after an accepted one are not recorded (one loop per keyframe is enough to pull the
        graph). After an acceptance every accepted loop is re-checked. Returns the new records.
        """
        new: list[LoopRecord] = []
        for v in verified:
            new.append(self._gate(v) if v.relative is not None else replace(v.record))
            if new[-1].accepted:
                break
        self.records.extend(new)
        if any(r.accepted for r in new):
            self.recheck()
        return new

    def _gate(self, v: Verified) -> LoopRecord:
        """A verified relative pose against the graph's estimate; added as a Huber factor when it agrees."""
        record, rel = replace(v.record), v.relative
        assert rel is not None
        a, b = record.match_keyframe, record.query_keyframe
        estimate = relative(self.graph.pose(a), self.graph.pose(b))
        dt, dr = motion_magnitude(relative(estimate, rel.T_a_b))
        record.translation_diff_m, record.rotation_diff_deg = round(dt, 4), round(math.degrees(dr), 3)
        s = self.settings
        joining = self.joined is not None and not self.joined(a, b)
        if not joining and (dt > s.gate_m or math.degrees(dr) > s.gate_deg):
            record.reason = "inconsistent_with_odometry"
            return record
        sigma_m, sigma_deg = max(s.sigma_floor_m, rel.sigma_m), max(s.sigma_floor_deg, rel.sigma_deg)
        factor = self.graph.add_loop(a, b, rel.T_a_b, sigma_m, sigma_deg)
        self.accepted[factor] = AcceptedLoop(a, b, rel.T_a_b)
        self.accepted_log.append((factor, self.accepted[factor]))
        record.accepted, record.reason, record.factor = True, "joins_segments" if joining else "verified", factor
        log.info("loop closure accepted: keyframe %d <-> %d (%d inliers)", a, b, rel.inliers)
        return record

    def recheck(self) -> list[int]:
        """Retract accepted loops that disagree with the estimate the other loops now give; their factors."""
        s = self.settings
        if not self.accepted:
            return []
        loops = list(self.accepted.values())  # all at once: thousands of loops in a long run's map
        poses = self.graph.poses()
        a, b = np.array([x.a for x in loops]), np.array([x.b for x in loops])
        dt, dr = disagreements(poses[a], poses[b], np.stack([x.T_a_b for x in loops]))
        off = (dt > s.retract_m) | (np.degrees(dr) > s.retract_deg)
        bad = [factor for factor, o in zip(self.accepted, off, strict=True) if o]
        if not bad:
            return []
        self.graph.remove_factors(bad)
        for factor in bad:
            del self.accepted[factor]
            self.retracted.append(factor)
            for r in self.records:
                if r.factor == factor:
                    r.accepted, r.reason = False, "retracted_inconsistent"
            log.warning("loop closure factor %d retracted: inconsistent with the other loops", factor)
        return bad
