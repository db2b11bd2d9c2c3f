"""The ``loops`` settings section: candidate sources, verification thresholds, the gate and retraction."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class LoopSettings(BaseModel):
    """Loop-closure candidates and their geometric verification."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    source: Literal["off", "appearance", "policy", "both"] = "appearance"
    policy: Path | None = Field(None, description="RL policy FILE.onnx (train-lc --from-map) for source policy/both")
    policy_radius: int = Field(1, ge=0, description="policy candidates: keyframes within this many cells")
    policy_candidates: int = Field(3, ge=1, description="policy candidates verified per proposal at most")
    min_gap_s: float = Field(5.0, ge=0, description="candidates are at least this much older")
    top_k: int = Field(3, ge=1)
    min_similarity: float = Field(0.5, ge=-1, le=1, description="global descriptor cosine similarity")
    min_inliers: int = Field(40, ge=6)
    max_residual_px: float = Field(2.0, gt=0)
    max_loop_m: float = Field(0.25, gt=0, description="a loop closure joins views at most this far apart")
    max_loop_deg: float = Field(17.0, gt=0, description="... and at most this much rotated")
    gate_m: float = Field(0.5, gt=0, description="max disagreement with the current estimate")
    gate_deg: float = Field(20.0, gt=0)
    retract_m: float = Field(0.15, gt=0, description="accepted loops disagreeing more are retracted")
    retract_deg: float = Field(5.0, gt=0)
    proximity: bool = Field(True, description="also verify old keyframes near the current pose estimate")
    proximity_m: float = Field(0.3, gt=0)
    proximity_deg: float = Field(25.0, gt=0)
    proximity_k: int = Field(2, ge=1)
    sigma_floor_m: float = Field(0.01, gt=0, description="loop factor translation sigma at least")
    sigma_floor_deg: float = Field(0.5, gt=0)

    @property
    def classical(self) -> bool:
        """The appearance (and proximity) sources run."""
        return self.source in ("appearance", "both")

    @property
    def uses_policy(self) -> bool:
        """The RL policy proposes candidates."""
        return self.source in ("policy", "both")
