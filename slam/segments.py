"""Map segments: what tracking loss leaves, and what relocalization and loop closure join again.

A keyframe that the front end could not pose from the previous one (``Step.lost``) and that relocalization
could not place either starts a new segment: it is held in the graph by a weak gauge prior, not by a guessed
motion. Segments are joined when a measured factor links two of them (a relocalization or a verified loop
closure): the joined segment's gauge prior is then removed, so the map holds measurements only. Frames are
"tied to the map" when their keyframe's segment is joined to the first one (keyframe 0's).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from perception.keyframing import Step


class TrackingState(str, Enum):  # noqa: UP042 - the value is what status reports
    """What the last frame's tracking was (``status``: ``tracking.state``)."""

    TRACKING = "tracking"  # posed by features (or the frames' own odometry), in the map
    PREDICTED = "predicted"  # posed by a fallback from the motion prior (wide features, guided matching, ICP)
    RELOCALIZING = "relocalizing"  # posed within a segment that is not yet joined to the map
    NEW_SEGMENT = "new_segment"  # lost: this frame began a new segment
    LOST = "lost"  # lost, and nothing in view to track from (a blank wall): the frame has no pose

    @classmethod
    def of(cls, step: Step, tied: bool) -> TrackingState:
        """The state of a frame after the front end's ``step`` and the core's placing of it, its keyframe
        ``tied`` to the map or not."""
        if not step.posed:
            return cls.LOST
        if step.lost:
            return cls.NEW_SEGMENT
        if not tied:
            return cls.RELOCALIZING
        return cls.TRACKING if step.method in ("odometry", "tracked", "features", "relocalized") else cls.PREDICTED


@dataclass
class Segments:
    """The segment of every keyframe, the joins between segments (union-find) and their gauge priors."""

    keyframe_segment: list[int] = field(default_factory=list)
    parent: list[int] = field(default_factory=list)  # union-find over segment ids
    gauge: dict[int, int] = field(default_factory=dict)  # segment -> its gauge prior's factor index
    joins: int = 0
    relocalizations: int = 0
    last_match: int | None = None  # the stored keyframe of the last relocalization or join

    @property
    def count(self) -> int:
        """How many segments were started (the first one included)."""
        return len(self.parent)

    def add_keyframe(self, k: int, new_segment: bool = False, gauge_factor: int | None = None) -> int:
        """Record keyframe ``k`` (the next one) in the current segment, or in a new one held by
        ``gauge_factor``; its segment."""
        if k != len(self.keyframe_segment):
            raise ValueError(f"keyframe {k} recorded out of order (expected {len(self.keyframe_segment)})")
        if new_segment or not self.parent:
            self.parent.append(len(self.parent))
            if gauge_factor is not None:
                self.gauge[len(self.parent) - 1] = gauge_factor
        self.keyframe_segment.append(len(self.parent) - 1)
        return len(self.parent) - 1

    def root(self, segment: int) -> int:
        while self.parent[segment] != segment:
            self.parent[segment] = self.parent[self.parent[segment]]
            segment = self.parent[segment]
        return segment

    def component(self, k: int) -> int:
        """The joined group of keyframe ``k``'s segment (its root segment id)."""
        return self.root(self.keyframe_segment[k])

    def joined(self, a: int, b: int) -> bool:
        """Keyframes ``a`` and ``b`` are in segments joined by measurements."""
        return self.component(a) == self.component(b)

    def tied(self, k: int) -> bool:
        """Keyframe ``k`` is tied to the map (joined to keyframe 0's segment)."""
        return bool(self.keyframe_segment) and self.joined(k, 0)

    def join(self, a: int, b: int) -> list[int]:
        """Join keyframes ``a`` and ``b``'s groups; the gauge prior factors to remove (the later group's: the
        group holding keyframe 0 keeps its anchor)."""
        ra, rb = self.component(a), self.component(b)
        if ra == rb:
            return []
        keep, drop = (ra, rb) if ra < rb else (rb, ra)
        self.parent[drop] = keep
        self.joins += 1
        return [self.gauge.pop(drop)] if drop in self.gauge else []

    def unjoined(self) -> int:
        """How many groups are not joined to the map."""
        return len({self.root(s) for s in range(len(self.parent))} - {self.root(0)}) if self.parent else 0

    def state(self) -> dict:
        return {
            "keyframe_segment": list(self.keyframe_segment),
            "parent": list(self.parent),
            "gauge": dict(self.gauge),
            "joins": self.joins,
            "relocalizations": self.relocalizations,
            "last_match": self.last_match,
        }

    @classmethod
    def from_state(cls, state: dict) -> Segments:
        return cls(
            list(state["keyframe_segment"]),
            list(state["parent"]),
            dict(state["gauge"]),
            int(state["joins"]),
            int(state["relocalizations"]),
            state.get("last_match"),
        )
