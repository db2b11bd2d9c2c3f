"""Depth-scale calibration against the ground truth: real ICP on rendered depth with a known scale error."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from bench.calibrate import calibrate_depth_scale, frame_pairs
from evaluation.depth_calibration import estimate_depth_scale
from perception.frame import Intrinsics
from sources import DatasetError, ScaledDepth, open_dataset

SCENE = "synthetic:room?seed=0&frames=60"  # 10 cm per frame: pairs 2 frames apart


@pytest.fixture(scope="module")
def scene():
    return open_dataset(SCENE)


def test_scaled_depth_view_scales_metric_depth_and_nothing_else(scene):
    view = ScaledDepth(scene, 1.04)
    a, b = scene.frame(7), view.frame(7)
    valid = np.isfinite(a.depth_m())
    assert valid.mean() > 0.5 and np.array_equal(valid, np.isfinite(b.depth_m()))
    np.testing.assert_allclose(b.depth_m()[valid], 1.04 * a.depth_m()[valid], rtol=1e-5)
    assert np.array_equal(a.rgb, b.rgb) and b.camera.color == scene.camera.color
    with pytest.raises(DatasetError):
        ScaledDepth(scene, 0.0)


@pytest.mark.parametrize("factor", [1.0, 0.96, 1.05])
def test_calibration_recovers_a_known_depth_scale_error(scene, factor):
    estimate = calibrate_depth_scale(ScaledDepth(scene, factor), gap=2, stride=2)
    assert estimate.pairs >= 8
    assert estimate.ratio == pytest.approx(factor, rel=0.006)
    assert estimate.q25 <= estimate.ratio <= estimate.q75
    assert estimate.calibrated_depth_scale(1000.0) == pytest.approx(1000.0 * factor, rel=0.006)


def test_calibrated_view_agrees_with_the_ground_truth(scene):
    wrong = ScaledDepth(scene, 1.05)
    estimate = calibrate_depth_scale(wrong, gap=2, stride=2)
    fixed = calibrate_depth_scale(ScaledDepth(wrong, 1.0 / estimate.ratio), gap=2, stride=2)
    assert fixed.ratio == pytest.approx(1.0, abs=0.006)


def test_pairs_that_did_not_move_are_refused_with_a_reason():
    depth = np.full((48, 64), 2.0, np.float32)
    with pytest.raises(ValueError, match="no usable frame pair"):
        estimate_depth_scale([(depth, depth, np.eye(4))] * 3, Intrinsics(50.0, 50.0, 32.0, 24.0))


def test_frame_pairs_stay_inside_the_range(scene):
    assert frame_pairs(scene, 0, 30, 10, 5) == [(0, 10), (5, 15), (10, 20), (15, 25)]
    assert frame_pairs(scene, 50, 1000, 15, 3) == []


def test_cli_prints_the_calibrated_scale_and_fails_in_one_line():
    ok = subprocess.run(
        [sys.executable, "-m", "service", "calibrate", "depth-scale", SCENE, "--gap", "2", "--stride", "4"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert ok.returncode == 0, ok.stderr
    assert "calibrated" in ok.stdout and "nominal 1000" in ok.stdout
    too_short = "synthetic:room?seed=0&frames=8"
    bad = subprocess.run(
        [sys.executable, "-m", "service", "calibrate", "depth-scale", too_short],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode == 1 and bad.stderr.startswith("objslam: error:") and len(bad.stderr.splitlines()) == 1
