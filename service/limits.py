"""The bounds put on untrusted input (the fields of the ``ingest`` settings section)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Limits(BaseModel):
    """Bounds the decoder enforces on untrusted input (fields of the ``ingest`` settings section)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_payload_bytes: int = Field(32 * 1024 * 1024, ge=1024)
    max_image_pixels: int = Field(
        2048 * 1536,
        ge=1,
        description="colour or depth images larger than this are rejected (too_large), judged by the size the "
        "frame header and the image's own header declare, before anything is decoded",
    )
    max_frame_rate_hz: float = Field(
        1000.0,
        gt=0,
        description="valid frames on the robot's key beyond this rate (1 s burst) are rejected as rate_limited "
        "(zenoh does not name a sample's publisher: who may publish is the access control's to decide)",
    )
    labels: tuple[str, ...] | None = Field(
        None, description="the detection labels kept as they are; default the detector's classes (COCO-80)"
    )
    extra_labels: int = Field(32, ge=0, description="other labels admitted, first come; any later one is 'other'")
    max_detections: int = Field(100, ge=1, description="a frame's best-scored detections kept, the rest dropped")
    max_queries_per_s: float = Field(
        1000.0, gt=0, description="queries beyond this rate (1 s burst) are answered 'busy' (status, map queries)"
    )
    min_save_interval_s: float = Field(
        5.0, ge=0, description="a save request sooner than this after the last one is answered 'busy'"
    )


DEFAULT_LIMITS = Limits()
