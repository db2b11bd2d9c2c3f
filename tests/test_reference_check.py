"""The reference trajectory against its own depth: real ICP on rendered depth, with a reference glitch put in."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from graph.geometry import relative
from graph.metrics import trajectory_error
from perception.frame import Intrinsics
from perception.reference_check import depth_residual
from service.calibrate import check_loops, check_reference
from service.sources import open_dataset, truth_per_frame

SCENE = "synthetic:room?seed=0&frames=60"
GLITCH_AT = 9  # the reference's step 9 -> 10 is wrong


@pytest.fixture(scope="module")
def scene():
    return open_dataset(SCENE)


def _glitched(truth: np.ndarray) -> np.ndarray:
    """The truth with every frame after ``GLITCH_AT`` moved 4 cm and turned 1.5 degrees in the world frame."""
    a = np.radians(1.5)
    G = np.eye(4)
    G[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
    G[:3, 3] = [0.04, -0.01, 0.01]
    out = truth.copy()
    out[GLITCH_AT + 1:] = G @ truth[GLITCH_AT + 1:]
    return out


def test_depth_residual_is_zero_for_the_true_motion_and_grows_with_a_wrong_one():
    K = Intrinsics(50.0, 50.0, 32.0, 24.0)
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    depth = (2.0 + 0.01 * u + 0.005 * v).astype(np.float32)  # a tilted plane
    assert depth_residual(depth, depth, K, np.eye(4), step=1) == pytest.approx(0.0, abs=1e-6)
    back = np.eye(4)
    back[2, 3] = 0.05
    assert depth_residual(depth, depth, K, back, step=1) > 0.04
    assert np.isnan(depth_residual(np.full_like(depth, np.nan), depth, K, np.eye(4)))


def test_an_exact_reference_is_not_refuted(scene):
    report = check_reference(scene, stop=16)
    assert len(report.checks) == 15 and all(c.T_depth is not None for c in report.checks)
    assert report.refuted_steps == []
    assert np.median([c.displacement_m for c in report.checks]) < 0.003
    assert report.repair_ate_m is not None and report.repair_ate_m < 1e-9


def test_a_glitch_in_the_reference_is_refuted_and_repaired(scene):
    truth = truth_per_frame(scene)
    glitched = _glitched(truth)
    report = check_reference(scene, stop=16, reference=glitched)
    assert report.refuted_steps == [GLITCH_AT]
    bad = next(c for c in report.checks if c.src == GLITCH_AT)
    assert bad.displacement_m > 0.03 and bad.residual_ref_m > bad.residual_depth_m + 0.005
    cost = trajectory_error(glitched[:16], truth[:16]).ate_rmse_m
    assert cost > 0.01
    # the repair removes the glitch: the repaired reference is the truth up to one rigid motion
    assert report.repair_ate_m == pytest.approx(cost, rel=0.15)


def test_a_pair_check_with_gap_lists_refuted_pairs_without_a_repair(scene):
    report = check_reference(scene, start=6, stop=14, gap=2, stride=1, reference=_glitched(truth_per_frame(scene)))
    assert report.repair_ate_m is None
    assert report.refuted_steps == [8, 9]  # the two pairs that straddle the glitch


def test_loop_records_are_checked_against_reference_and_depth(scene):
    truth = truth_per_frame(scene)
    true_pose = relative(truth[4], truth[6])  # pose of the query (6) in the match frame (4)
    wrong = true_pose.copy()
    wrong[:3, 3] += [0.05, 0.0, 0.0]
    record = lambda T: {"accepted": True, "match_frame": 4, "query_frame": 6,  # noqa: E731
                        "relative_pose": list(T[:3, 3]) + list(_quaternion(T))}
    checks = check_loops(scene, [record(true_pose), record(wrong), dict(record(wrong), accepted=False)])
    assert len(checks) == 2
    right, off = checks
    assert right.residual_loop_m == pytest.approx(right.check.residual_ref_m, abs=2e-4)
    assert off.residual_loop_m > right.residual_loop_m + 0.005
    assert right.check.displacement_m < 0.005


def _quaternion(T: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w, as in TUM files


def test_cli_prints_the_check_and_fails_in_one_line(tmp_path):
    ok = subprocess.run([sys.executable, "-m", "service", "calibrate", "reference", SCENE, "--stop", "6",
                         "--write", str(tmp_path / "b.md")], capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert "reference against depth" in ok.stdout
    assert "<!-- bench:reference -->" in (tmp_path / "b.md").read_text()
    bad = subprocess.run([sys.executable, "-m", "service", "calibrate", "reference", SCENE, "--start", "70"],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and bad.stderr.startswith("objslam: error:") and len(bad.stderr.splitlines()) == 1
