"""Typed configuration: defaults < YAML file (``--config``) < ``OBJSLAM_*`` environment < command-line flags.

Nested fields use ``__`` in environment variables, e.g. ``OBJSLAM_ZENOH__MODE=client``.
"""

from __future__ import annotations

import os
import re
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError
from pydantic_settings import (
    BaseSettings,
    InitSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
)

from graph.settings import GraphSettings
from loops.settings import LoopSettings
from perception.detector import DetectorSettings
from perception.keyframing import KeyframeSettings
from perception.odometry import OdometrySettings
from service.protocol import Limits
from service.ros2_settings import Ros2Settings
from slam.settings import ObjectSettings
from sources.tum import CameraDefaults

ENV_PREFIX = "OBJSLAM_"
KEY_CHUNKS = re.compile(r"^[^/*$#?\s]+(/[^/*$#?\s]+)*$")


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
    query_timeout_s: float = Field(5.0, gt=0, allow_inf_nan=False)
    config_file: Path | None = Field(
        None,
        description="a native zenoh configuration file (JSON5): TLS / mTLS, user-password authentication, "
        "access control. It decides the transport; mode, listen and connect given here (or as flags) override it",
    )

    @field_validator("key_prefix")
    @classmethod
    def _valid_key_prefix(cls, value: str) -> str:
        """Checked here, not when the session declares its keys: zenoh's own error there is a traceback."""
        if not KEY_CHUNKS.match(value):
            raise ValueError(
                f"{value!r} is not a zenoh key: chunks separated by '/', none empty, without '*', '$', '#', '?', "
                "spaces or a leading or trailing '/'"
            )
        return value


class IngestSettings(Limits):
    """The bounded ingest queue between zenoh callbacks and the worker thread, and the decoder's bounds."""

    queue_size: int = Field(64, ge=1, description="frames held before the oldest is dropped")
    live: bool = Field(
        False,
        description="latency first, for a robot's live camera (serve --live): the newest frame is tracked and the "
        "older ones waiting are skipped undecoded (frames_dropped, reason stale), a decoded frame older than "
        "max_age_ms is skipped when a newer one waits, and keyframe mapping never holds up tracking (applied "
        "when done; keyframes that arrive while it is behind get no detection). Off: every frame in order "
        "(replays of recordings, benchmarks), the map bit-identical to `run`'s",
    )
    max_age_ms: float = Field(
        100.0, gt=0, allow_inf_nan=False, description="live: a frame older than this is skipped for a newer one"
    )
    polish_after_s: float = Field(
        1.0,
        ge=0,
        allow_inf_nan=False,
        description="live: no frame for this long and every keyframe mapped (the robot paused, the stream ended): "
        "the graph is moved towards the batch optimum of all it holds, as `run` does at the end of a sequence "
        "(in the window while it holds the whole graph, else by the child's solve, not waited for); 0: never",
    )


class PersistenceSettings(BaseModel):
    """Snapshots of the map in ``state_dir`` (``serve --state-dir``), resumed from on start."""

    every_keyframes: int = Field(1, ge=1, description="checkpoint the map store after this many new keyframes")
    keep: int = Field(3, ge=2, description="checkpoints kept in the map store (the older ones are fallbacks)")
    session_gap_s: float = Field(
        2.0, gt=0, description="a resumed map's first frame this long after its last one may be anywhere: relocalized"
    )


class ViewerSettings(BaseModel):
    """The Rerun viewer (``service.viewer``): a recording of every ``run``, a native or a web viewer, live."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = Field(True, description="run records its map into OUT/map.rrd (run --no-rrd: off)")
    rrd: Path | None = Field(None, description="record into this .rrd file (--rrd); run: instead of OUT/map.rrd")
    native: bool = Field(False, description="--rerun: stream to the native viewer at `connect`, started if none is")
    connect: str = Field("rerun+http://127.0.0.1:9876/proxy", description="where --rerun finds the native viewer")
    web_port: int | None = Field(None, ge=1, le=65535, description="--rerun-web: web viewer on 127.0.0.1:PORT")
    max_rate_hz: float = Field(
        10.0,
        gt=0,
        allow_inf_nan=False,
        description="updates sent to the viewer per second at most (frames between "
        "are not shown; the map has them all)",
    )
    images: bool = Field(True, description="colour, depth and detection boxes at keyframes (protocol-v1 input)")
    memory_limit: str = Field("512MiB", description="the web viewer server's buffer for browsers that join late")


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
    ros2: Ros2Settings = Field(default_factory=Ros2Settings)
    viewer: ViewerSettings = Field(default_factory=ViewerSettings)

    @model_validator(mode="before")
    @classmethod
    def _no_unknown_keys(cls, data: Any) -> Any:
        """Every key of every section must be a field: a misspelt key (``queue_sise``) would otherwise leave the
        default in place silently, since not every section's model forbids extra keys itself."""
        if isinstance(data, Mapping):
            unknown = unknown_keys(cls, data)
            if unknown:
                raise PydanticCustomError("unknown_key", "unknown key", {"where": unknown[0]})
        return data

    def map_sections(self) -> dict[str, Any]:
        """The sections that shape the map (not endpoints, queue or state dir), to compare on resume."""
        sections = {"keyframes", "odometry", "loops", "detector", "objects", "graph", "camera"}
        return self.model_dump(mode="json", include=sections)

    @property
    def key_prefix(self) -> str:
        """Keys of this robot: ``<key_prefix>/<robot>``."""
        return f"{self.zenoh.key_prefix}/{self.robot}"


def section_model(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model a field holds (also through ``X | None``), or None for a plain value."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        models = [m for m in map(section_model, typing.get_args(annotation)) if m is not None]
        return models[0] if len(models) == 1 else None
    return None


def _field_named(model: type[BaseModel], key: str) -> Any:
    for name, field in model.model_fields.items():
        if key in (name, field.alias):
            return field
    return None


def unknown_keys(model: type[BaseModel], data: Mapping[str, Any], where: str = "") -> list[str]:
    """Dotted paths of the keys of ``data`` (nested mappings included) that are not fields of ``model``."""
    found = []
    for key, value in data.items():
        field = _field_named(model, str(key))
        if field is None:
            found.append(f"{where}{key}")
            continue
        section = section_model(field.annotation)
        if section is not None and isinstance(value, Mapping):
            found += unknown_keys(section, value, f"{where}{key}.")
    return found


def _known_env_path(model: type[BaseModel], path: list[str]) -> bool:
    """Whether ``OBJSLAM_A__B__C`` (path ``[a, b, c]``) names a field: a section, one of its fields, or a key
    inside a mapping field."""
    field = _field_named(model, path[0])
    if field is None:
        return False
    if len(path) == 1:
        return True
    section = section_model(field.annotation)
    if section is not None:
        return _known_env_path(section, path[1:])
    return _is_mapping(field.annotation)


def _is_mapping(annotation: Any) -> bool:
    """A ``dict[...]`` field (also through ``X | None``): its keys are data, not configuration keys."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_is_mapping(arg) for arg in typing.get_args(annotation))
    return typing.get_origin(annotation) is dict


def check_environment(environ: Mapping[str, str]) -> None:
    """ConfigError naming the first ``OBJSLAM_*`` variable that is no configuration key: pydantic-settings reads
    only the variables it knows, so a misspelt one (``OBJSLAM_ROBOTT``) would be ignored silently."""
    for name in sorted(environ):
        if not name.upper().startswith(ENV_PREFIX):
            continue
        path = name[len(ENV_PREFIX) :].lower().split("__")
        if not _known_env_path(Settings, path):
            raise ConfigError(
                f"unknown environment variable {name}: no configuration key {'.'.join(path)} "
                "(OBJSLAM_<SECTION>__<FIELD>; `objslam config --dump` lists them)"
            )


def read_config_file(config_file: Path) -> dict[str, Any]:
    """The YAML file's sections; ConfigError unless it is a mapping (an empty file is no sections)."""
    if not Path(config_file).is_file():
        raise ConfigError(f"config file not found: {config_file}")
    try:
        data = yaml.safe_load(Path(config_file).read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {config_file} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"config file {config_file}: the top level must be a mapping of sections (robot, zenoh, ...), "
            f"not {type(data).__name__} {data!r:.40}"
        )
    return data


def _settings_class(file_data: dict[str, Any] | None) -> type[Settings]:
    if file_data is None:
        return Settings
    sections: dict[str, Any] = file_data

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
            return (init_settings, env_settings, InitSettingsSource(settings_cls, init_kwargs=sections))

    return FileSettings


def load_settings(config_file: Path | None = None, overrides: dict[str, Any] | None = None) -> Settings:
    """Settings from defaults, an optional YAML file, the environment and ``overrides`` (highest).

    Every mistake is a ConfigError of one line: an unknown key (file, environment or flag), a file that is not
    a mapping, an environment value that does not parse, an invalid value."""
    file_data = read_config_file(config_file) if config_file is not None else None
    check_environment(os.environ)
    try:
        return _settings_class(file_data)(**(overrides or {}))
    except ValidationError as exc:
        raise ConfigError(_one_line(exc)) from None
    except SettingsError as exc:
        raise ConfigError(
            f"invalid environment: {exc} (a whole section's variable, such as OBJSLAM_ZENOH, holds JSON; "
            "or set one field: OBJSLAM_ZENOH__MODE=client)"
        ) from None


def _one_line(exc: ValidationError) -> str:
    """``invalid configuration at <dotted key>: <what is wrong>`` for the first error."""
    first = exc.errors()[0]
    if first["type"] in ("unknown_key", "extra_forbidden"):
        where = first.get("ctx", {}).get("where") or ".".join(str(p) for p in first["loc"])
        return f"invalid configuration at {where}: unknown key"
    where = ".".join(str(p) for p in first["loc"])
    return f"invalid configuration at {where}: {first['msg'].removeprefix('Value error, ')}"


def dump_defaults() -> str:
    """The default configuration as YAML (``objslam config --dump``)."""
    return yaml.safe_dump(Settings.model_construct().model_dump(mode="json"), sort_keys=False)
