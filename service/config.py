"""Typed configuration: defaults < YAML file (``--config``) < ``OBJSLAM_*`` environment < command-line flags.

Nested fields use ``__`` in environment variables, e.g. ``OBJSLAM_ZENOH__MODE=client``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, Field, ValidationError
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict, YamlConfigSettingsSource

from graph.settings import GraphSettings
from sources.tum import CameraDefaults


class ConfigError(Exception):
    """The configuration file, environment or flags are invalid."""


class ZenohSettings(BaseModel):
    """Zenoh session: mode, endpoints and the key prefix (keys are ``<key_prefix>/<robot>/...``)."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], description="serve listens here")
    connect: list[str] = Field(
        default_factory=list, description="endpoints to connect to; clients default to the listen endpoints"
    )
    multicast_scouting: bool = Field(False, description="multicast discovery (off: loopback-only deployments)")
    key_prefix: str = "objslam"
    query_timeout_s: float = 5.0


class IngestSettings(BaseModel):
    """The bounded ingest queue between zenoh callbacks and the worker thread."""

    queue_size: int = Field(64, ge=1, description="frames held before the oldest is dropped")
    max_payload_bytes: int = Field(64 * 1024 * 1024, ge=1024)
    max_image_pixels: int = Field(4096 * 4096, ge=1)


class KeyframeSettings(BaseModel):
    """A frame becomes a keyframe when it moved enough since the last one, or too many frames passed."""

    translation_m: float = Field(0.05, gt=0)
    rotation_deg: float = Field(5.0, gt=0)
    max_interval: int = Field(10, ge=1, description="frames between keyframes at most")
    min_inliers: int = Field(120, ge=0, description="visual odometry: new keyframe when tracking weakens")
    skip_edges: int = Field(
        2,
        ge=1,
        description="visual odometry: factors from a new keyframe to this many earlier "
        "keyframes (1 = the previous one only)",
    )


class OdometrySettings(BaseModel):
    """RGB-D visual odometry, used for frames that carry no odometry."""

    n_features: int = Field(1500, ge=100)
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio test")
    min_matches: int = Field(30, ge=6)
    min_inliers: int = Field(25, ge=6)
    ransac_px: float = Field(3.0, gt=0)
    max_residual_px: float = Field(2.0, gt=0)
    lost_sigma_scale: float = Field(100.0, ge=1, description="odometry sigma multiplier after tracking loss")
    icp: bool = Field(True, description="refine keyframe-to-keyframe poses by depth point-to-plane ICP")
    sigma_m_coeff: float = Field(0.08, gt=0, description="factor translation sigma = coeff / sqrt(inliers)")
    sigma_deg_coeff: float = Field(3.0, gt=0, description="factor rotation sigma = coeff / sqrt(inliers)")


class LoopSettings(BaseModel):
    """Loop-closure candidates and their geometric verification."""

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


class DetectorSettings(BaseModel):
    """The ONNX object detector (SPEC 6.1), used on keyframes whose frames carry no detections."""

    enabled: bool = Field(True, description="run on keyframes whose frames carry no detections")
    kind: Literal["centernet", "nanodet", "yolo"] = "centernet"
    model: Path | None = Field(None, description="ONNX file; empty = the shipped model of `kind` in models/")
    threads: int = Field(2, ge=1)
    score_threshold: float | None = Field(None, ge=0, le=1, description="empty = tuned default of `kind`")
    class_thresholds: dict[str, float] | None = Field(None, description="per-class minimum scores")
    nms_iou: float = Field(0.5, gt=0, le=1)
    max_detections: int = Field(50, ge=1)
    fit_aspect: bool = Field(
        False,
        description="centernet: a 512-wide input as high as the image's aspect needs "
        "(512 x 384 for 4:3) instead of the letterboxed 512 x 512: faster, fewer detections",
    )


class ObjectSettings(BaseModel):
    """Object association (NPDA), tracks and clustering on keyframes (defaults from `objslam bench association`),
    objects as landmarks of the pose graph, and re-clustering after optimisations (SPEC 6.8)."""

    enabled: bool = True
    landmarks: bool = Field(True, description="stable objects become Point3 landmarks of the iSAM2 graph")
    landmark_sigma_m: float = Field(0.1, gt=0, description="sigma of an object centroid measurement (m)")
    landmark_huber_k: float | None = Field(1.345, gt=0, description="Huber kernel of object measurements; null = none")
    landmark_min_support: int = Field(5, ge=1, description="feature vectors an object needs to become a landmark")
    landmark_extent_scale: float = Field(
        1.0, ge=0, description="a measurement's sigma is at least this times the largest std of the object's points"
    )
    landmark_range_scale: float = Field(
        3.0,
        ge=1,
        description="sigma along the viewing ray = this times the sigma "
        "across it: the visible surface's centroid lies short of the object's",
    )
    repose_m: float = Field(
        0.01,
        gt=0,
        description="re-pose and re-cluster objects once an optimisation has moved an observing keyframe this far (m)",
    )
    repose_deg: float = Field(0.5, gt=0, description="... or turned it this much (degrees)")


class PersistenceSettings(BaseModel):
    """Snapshots of the map in ``state_dir`` (``serve --state-dir``), resumed from on start."""

    every_keyframes: int = Field(10, ge=1, description="write a snapshot after this many new keyframes")
    keep: int = Field(3, ge=2, description="snapshots kept; older ones are deleted after each write")


class Settings(BaseSettings):
    """All of objslam's configuration."""

    model_config = SettingsConfigDict(env_prefix="OBJSLAM_", env_nested_delimiter="__", extra="forbid")

    robot: str = Field("robot1", pattern=r"^[A-Za-z0-9_\-]+$")
    state_dir: Path | None = Field(None, description="serve: snapshots (resumed from on start) and outputs")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    ingest: IngestSettings = Field(default_factory=IngestSettings)
    keyframes: KeyframeSettings = Field(default_factory=KeyframeSettings)
    odometry: OdometrySettings = Field(default_factory=OdometrySettings)
    loops: LoopSettings = Field(default_factory=LoopSettings)
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    objects: ObjectSettings = Field(default_factory=ObjectSettings)
    graph: GraphSettings = Field(default_factory=GraphSettings)
    persistence: PersistenceSettings = Field(default_factory=PersistenceSettings)
    camera: CameraDefaults = Field(default_factory=CameraDefaults)

    @property
    def key_prefix(self) -> str:
        """Keys of this robot: ``<key_prefix>/<robot>``."""
        return f"{self.zenoh.key_prefix}/{self.robot}"


def _settings_class(config_file: Path | None) -> type[Settings]:
    if config_file is None:
        return Settings

    class FileSettings(Settings):
        @classmethod
        def settings_customise_sources(
            cls,
            settings_cls: type[BaseSettings],
            init_settings: PydanticBaseSettingsSource,
            env_settings: PydanticBaseSettingsSource,
            dotenv_settings: PydanticBaseSettingsSource,
            file_secret_settings: PydanticBaseSettingsSource,
        ) -> tuple[PydanticBaseSettingsSource, ...]:
            return (init_settings, env_settings, YamlConfigSettingsSource(settings_cls, yaml_file=config_file))

    return FileSettings


def load_settings(config_file: Path | None = None, overrides: dict[str, Any] | None = None) -> Settings:
    """Settings from defaults, an optional YAML file, the environment and ``overrides`` (highest)."""
    if config_file is not None and not Path(config_file).is_file():
        raise ConfigError(f"config file not found: {config_file}")
    try:
        return _settings_class(config_file)(**(overrides or {}))
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(f"invalid configuration at {where}: {first['msg']}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {config_file} is not valid YAML: {exc}") from None


def dump_defaults() -> str:
    """The default configuration as YAML (``objslam config --dump``)."""
    return yaml.safe_dump(Settings.model_construct().model_dump(mode="json"), sort_keys=False)
