"""Typed configuration: defaults, YAML file, environment and flags in that order of precedence."""

from __future__ import annotations

import pytest
import yaml

from service.config import ConfigError, dump_defaults, load_settings


def test_defaults_dump_is_valid_yaml_with_every_section():
    data = yaml.safe_load(dump_defaults())
    assert set(data) >= {"robot", "zenoh", "ingest", "keyframes", "graph", "camera"}
    assert data["zenoh"]["multicast_scouting"] is False


def test_file_env_and_flags_take_precedence_in_order(tmp_path, monkeypatch):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("robot: fromfile\nzenoh:\n  mode: client\n  key_prefix: filepfx\ningest:\n  queue_size: 7\n")
    s = load_settings(cfg)
    assert (s.robot, s.zenoh.mode, s.ingest.queue_size, s.key_prefix) == ("fromfile", "client", 7, "filepfx/fromfile")
    monkeypatch.setenv("OBJSLAM_ROBOT", "fromenv")
    monkeypatch.setenv("OBJSLAM_INGEST__QUEUE_SIZE", "9")
    s = load_settings(cfg)
    assert (s.robot, s.ingest.queue_size, s.zenoh.mode) == ("fromenv", 9, "client")
    s = load_settings(cfg, {"robot": "fromflag", "zenoh": {"connect": ["tcp/127.0.0.1:1234"]}})
    assert s.robot == "fromflag" and s.zenoh.connect == ["tcp/127.0.0.1:1234"] and s.zenoh.mode == "client"


def test_invalid_values_give_one_clear_error(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("ingest:\n  queue_size: 0\n")
    with pytest.raises(ConfigError, match="ingest.queue_size"):
        load_settings(cfg)
    with pytest.raises(ConfigError, match="not found"):
        load_settings(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="robot"):
        load_settings(None, {"robot": "bad/name"})


def test_component_configs_take_the_same_named_settings():
    from perception.detector import DetectorConfig
    from perception.frontend import KeyframePolicy
    from slam.build import from_settings

    s = load_settings(None, {"keyframes": {"skip_edges": 4, "min_inliers": 90}, "detector": {"fit_aspect": True}})
    policy = from_settings(KeyframePolicy, s.keyframes, s.odometry)
    assert (policy.skip_edges, policy.min_inliers) == (4, 90)  # keyframes' min_inliers wins over odometry's
    assert from_settings(DetectorConfig, s.detector).fit_aspect is True
    with pytest.raises(ConfigError):
        load_settings(None, {"keyframes": {"skip_edges": 0}})
