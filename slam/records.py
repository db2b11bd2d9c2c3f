"""Plain records of the SLAM core: where a frame sits in the graph, what a keyframe's mapping produced, and
what one step changed."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from loops.records import LoopRecord, Verified
from perception.clustering import ObjectEllipsoid
from perception.frame import Detection


@dataclass
class FrameRecord:
    """Where a processed frame sits in the graph: its keyframe and its odometry pose relative to it."""

    timestamp: float
    seq: int
    keyframe: int
    is_keyframe: bool
    odometry: np.ndarray
    from_keyframe: np.ndarray
    posed: bool = True  # False: tracking was lost and the frame had nothing to track from (it has no pose)


@dataclass
class KeyframeObjects:
    """What mapping one keyframe's objects produced, to be applied to the graph (plain data)."""

    keyframe: int
    detections: list[Detection]
    observations: list[tuple[int, np.ndarray, float]] = field(default_factory=list)  # (track, body-frame p, extent)
    reclustered: bool = False
    reposed: bool = False
    objects: list[ObjectEllipsoid] = field(default_factory=list)  # the object map after this keyframe
    retired: tuple[int, ...] = ()  # tracks retired into their objects' anchors (their measurements settled)
    unconfirmed: int = 0  # objects not shown: detected too seldom where they stood in view (perception.existence)
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class KeyframeLoops:
    """What verifying one keyframe's loop candidates produced, to be gated against the graph."""

    verified: list[Verified]
    timings: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class StepResult:
    """What one frame changed: its record, the keyframe it added (or None), the loop records judged and the
    object map changes applied during the step, and the seconds each stage took."""

    record: FrameRecord
    keyframe: int | None
    loops: list[LoopRecord]
    objects_changed: bool
    timings: dict[str, float]
    added: tuple[tuple[int, float], ...] = ()  # keyframes added in the step: (index, its frame's timestamp)
