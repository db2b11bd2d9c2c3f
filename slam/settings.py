"""The settings the SLAM core reads: the ``objects`` section, and the shape of the whole configuration it takes.

Each component's section is defined beside the component (``loops.settings.LoopSettings``,
``graph.object_landmarks.LandmarkSettings``, ...); ``service.config.Settings`` gathers them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from pydantic import Field

from graph.object_landmarks import LandmarkSettings
from graph.settings import GraphSettings
from loops.settings import LoopSettings
from perception.keyframing import KeyframeSettings
from perception.odometry import OdometrySettings

if TYPE_CHECKING:  # the detector module imports onnxruntime
    from perception.detector import DetectorSettings


class ObjectSettings(LandmarkSettings):
    """Object association (NPDA), tracks and clustering on keyframes (defaults from `objslam bench association`),
    objects as landmarks of the pose graph, and re-clustering after optimisations (SPEC 6.8)."""

    enabled: bool = True
    landmarks: bool = Field(True, description="stable objects become Point3 landmarks of the iSAM2 graph")
    repose_m: float = Field(
        0.01,
        gt=0,
        description="re-pose and re-cluster objects once an optimisation has moved an observing keyframe this far (m)",
    )
    repose_deg: float = Field(0.5, gt=0, description="... or turned it this much (degrees)")


class SlamConfig(Protocol):
    """The sections of the configuration that shape the map (``service.config.Settings`` has them)."""

    @property
    def keyframes(self) -> KeyframeSettings: ...

    @property
    def odometry(self) -> OdometrySettings: ...

    @property
    def loops(self) -> LoopSettings: ...

    @property
    def detector(self) -> DetectorSettings: ...

    @property
    def objects(self) -> ObjectSettings: ...

    @property
    def graph(self) -> GraphSettings: ...
