"""Typed configuration: defaults, YAML file, environment and flags in that order of precedence."""

from __future__ import annotations

import pytest
import yaml
from pydantic import ValidationError

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
    with pytest.raises(ConfigError, match=r"ingest\.queue_size"):
        load_settings(cfg)
    with pytest.raises(ConfigError, match="not found"):
        load_settings(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="robot"):
        load_settings(None, {"robot": "bad/name"})


def test_the_components_take_their_sections_of_the_settings():
    from slam.build import build_core
    from tests.conftest import make_frame

    s = load_settings(None, {"keyframes": {"skip_edges": 4, "min_inliers": 90}, "detector": {"fit_aspect": True}})
    core = build_core(s)
    core.step(make_frame(t=1.0))  # the tracking components are built for the first frame's camera
    policy = core.frontend.policy
    assert policy is s.keyframes and (policy.skip_edges, policy.min_inliers) == (4, 90)  # keyframes' min_inliers
    assert core.loops.estimator.config.min_inliers == 25  # ... not the relative pose estimator's
    assert core.detector_factory().config is s.detector and s.detector.fit_aspect is True
    with pytest.raises(ConfigError):
        load_settings(None, {"keyframes": {"skip_edges": 0}})
    with pytest.raises(ConfigError, match=r"odometry\.icp_max_correction_m"):
        load_settings(None, {"odometry": {"icp_max_correction_m": 0}})


def test_sections_are_frozen_and_reject_unknown_keys():
    s = load_settings(None, {"odometry": {"lost_sigma_scale": 50.0}})
    with pytest.raises(ValidationError):
        s.odometry.icp = False
    with pytest.raises(ConfigError, match=r"keyframes\.lost_sigma_scale"):
        load_settings(None, {"keyframes": {"lost_sigma_scale": 50.0}})  # an odometry setting


def test_the_default_configuration_of_0_1_0_only_gains_keys():
    """Every key of release 0.1.0's `objslam config --dump` is still there, with its value."""
    data = yaml.safe_load(dump_defaults())
    released = {
        "keyframes": {
            "translation_m": 0.05,
            "rotation_deg": 5.0,
            "max_interval": 10,
            "min_inliers": 120,
            "skip_edges": 2,
        },
        "odometry": {
            "n_features": 1500,
            "ratio": 0.8,
            "min_matches": 30,
            "min_inliers": 25,
            "ransac_px": 3.0,
            "max_residual_px": 2.0,
            "lost_sigma_scale": 100.0,
            "icp": True,
            "sigma_m_coeff": 0.08,
            "sigma_deg_coeff": 3.0,
        },
        "detector": {
            "enabled": True,
            "kind": "centernet",
            "model": None,
            "threads": 2,
            "score_threshold": None,
            "class_thresholds": None,
            "nms_iou": 0.5,
            "max_detections": 50,
            "fit_aspect": False,
        },
    }
    for section, values in released.items():
        assert {k: data[section][k] for k in values} == values
        keys = [k for k in data[section] if k in values]
        assert keys == list(values)  # in the same order
    assert data["keyframes"]["max_jump_m"] == 1.0 and data["odometry"]["icp_max_correction_deg"] == 2.0
