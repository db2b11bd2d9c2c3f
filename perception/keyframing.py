"""When a frame becomes a keyframe (``KeyframeSettings``), and what a front end made of a frame (``Step``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from perception.frame import Frame
from perception.hypotheses import Method
from perception.odometry import Features


class KeyframeSettings(BaseModel):
    """A frame becomes a keyframe when it moved enough since the last one, too many frames passed, or (visual
    odometry) too few inliers track it; and external odometry that jumps is rejected (``implausible``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    translation_m: float = Field(default=0.05, gt=0)
    rotation_deg: float = Field(default=5.0, gt=0)
    max_interval: int = Field(default=10, ge=1, description="frames between keyframes at most")
    min_inliers: int = Field(default=120, ge=0, description="visual odometry: new keyframe when tracking weakens")
    skip_edges: int = Field(
        default=2,
        ge=1,
        description="visual odometry: factors from a new keyframe to this many earlier "
        "keyframes (1 = the previous one only)",
    )
    max_jump_m: float = Field(
        default=1.0,
        ge=0,
        description="external odometry: a frame whose pose lies farther than this + max_speed_mps x the time "
        "since the previous frame from the previous frame's is rejected (odometry_jump)",
    )
    max_speed_mps: float = Field(default=10.0, ge=0, description="external odometry: see max_jump_m")
    max_time_jump_s: float = Field(
        default=60.0,
        gt=0,
        description="a frame stamped more than this after the last accepted one is rejected (time_jump), unless "
        "time_jump_frames such frames in a row, each within this of the one before, start a new time reference",
    )
    time_jump_frames: int = Field(default=3, ge=2, description="see max_time_jump_s")

    def implausible(self, previous: np.ndarray, pose: np.ndarray, dt: float) -> bool:
        """External odometry that moved farther than ``max_jump_m`` + ``max_speed_mps`` * dt from the previous
        frame's: a glitch, not motion (it would drag the whole graph, and a kilometre jump makes iSAM2 fail)."""
        jump = float(np.linalg.norm(pose[:3, 3] - previous[:3, 3]))
        return jump > self.max_jump_m + self.max_speed_mps * max(dt, 0.0)


@dataclass
class Step:
    """What the front end made of one frame."""

    pose: np.ndarray
    keyframe: bool
    factor: np.ndarray | None = None
    sigma_m: float | None = None
    sigma_deg: float | None = None
    lost: bool = False
    inliers: int = 0
    features: Features | None = None
    extra: list[tuple[int, np.ndarray, float, float]] = field(default_factory=list)
    method: Method = "features"
    posed: bool = True  # False: lost, and nothing in the frame to track from (no keyframe; no pose)
    deferred: tuple[Frame, Step] | None = None  # live: an earlier frame's keyframe, ready now (added first)
