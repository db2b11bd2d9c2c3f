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
from loops.settings import LoopSettings
from perception.detector import DetectorSettings
from perception.frontend import KeyframeSettings
from perception.odometry import OdometrySettings
from service.protocol import Limits
from slam.settings import ObjectSettings
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
    config_file: Path | None = Field(
        None,
        description="a native zenoh configuration file (JSON5): TLS / mTLS, user-password authentication, "
        "access control. It decides the transport; mode, listen and connect given here (or as flags) override it",
    )


class IngestSettings(Limits):
    """The bounded ingest queue between zenoh callbacks and the worker thread, and the decoder's bounds."""

    queue_size: int = Field(64, ge=1, description="frames held before the oldest is dropped")


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

    def map_sections(self) -> dict[str, Any]:
        """The sections that shape the map (not endpoints, queue or state dir), to compare on resume."""
        sections = {"keyframes", "odometry", "loops", "detector", "objects", "graph", "camera"}
        return self.model_dump(mode="json", include=sections)

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
