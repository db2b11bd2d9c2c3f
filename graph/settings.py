"""The graph's configuration, defined once: the ``graph`` section of objslam's settings (``service.config``).

Noise models and iSAM2 parameters (every graph) and the bounded window (``WindowedGraph``). A graph's
``state()`` saves the noise fields as ``noise`` and the window fields as ``window.settings``, as plain dicts
(release 0.1.0's format, when they were two dataclasses): ``NOISE_FIELDS`` and ``WINDOW_FIELDS``.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class GraphSettings(BaseModel):
    """iSAM2 pose graph noise models and solver parameters."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    odometry_sigma_m: float = Field(default=0.02, gt=0, description="odometry between-factor translation sigma")
    odometry_sigma_deg: float = Field(default=1.0, gt=0, description="odometry between-factor rotation sigma")
    prior_sigma_m: float = Field(default=1e-4, gt=0)
    prior_sigma_deg: float = Field(default=0.01, gt=0)
    relinearize_threshold: float = Field(
        default=0.1,
        gt=0,
        description="iSAM2 relinearizeThreshold (gtsam's default; "
        "`objslam bench isam2`: p95 update 4x lower than 0.01, same ATE)",
    )
    relinearize_skip: int = Field(default=1, ge=1)
    window_keyframes: int = Field(
        default=400,
        ge=2,
        description="keyframes in the bounded iSAM2 window (older ones are "
        "fixed there; the whole graph is solved in a child process)",
    )
    window_step: int = Field(default=100, ge=1, description="keyframes added before the window rolls forward")
    partial_relinearization_check: bool = Field(
        default=True,
        description="iSAM2 enablePartialRelinearizationCheck: look for variables to relinearize only in the "
        "cliques an update touches, not in the whole tree (`objslam bench isam2`: p95 update time at 10,000 "
        "poses 4x lower)",
    )


NOISE_FIELDS = (
    "odometry_sigma_m",
    "odometry_sigma_deg",
    "prior_sigma_m",
    "prior_sigma_deg",
    "relinearize_threshold",
    "relinearize_skip",
    "partial_relinearization_check",
)
"""The fields a graph's ``state()`` saves as ``noise`` (release 0.1.0's ``NoiseSettings``, in its order)."""

WINDOW_FIELDS = ("window_keyframes", "window_step")
"""The fields a ``WindowedGraph.state()`` saves as ``window.settings`` (release 0.1.0's ``WindowSettings``)."""


def noise_state(settings: GraphSettings) -> dict[str, Any]:
    """The ``noise`` dict of a graph's state."""
    return {name: getattr(settings, name) for name in NOISE_FIELDS}


def window_state(settings: GraphSettings) -> dict[str, Any]:
    """The ``window.settings`` dict of a ``WindowedGraph``'s state."""
    return {name: getattr(settings, name) for name in WINDOW_FIELDS}


def from_noise_state(noise: dict[str, Any]) -> GraphSettings:
    """The settings of a saved ``noise`` dict (the window fields at their defaults). Snapshots from before the
    partial relinearization check was a setting were made without it."""
    return GraphSettings(**{"partial_relinearization_check": False, **noise})


def with_window(settings: GraphSettings, window: GraphSettings | dict[str, Any] | None) -> GraphSettings:
    """``settings`` with the window fields of ``window`` (settings, or a saved ``window.settings`` dict)."""
    if window is None:
        return settings
    fields = window_state(window) if isinstance(window, GraphSettings) else dict(window)
    return GraphSettings(**{**settings.model_dump(), **fields})
