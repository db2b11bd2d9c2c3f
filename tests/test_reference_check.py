"""The reference trajectory against its own depth: real ICP on rendered depth, with a reference glitch put in."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from bench.calibrate import check_loops, check_reference, frame_pairs
from bench.slam import default_datasets
from evaluation.reference_check import PairCheck, depth_residual, repaired
from evaluation.trajectory_metrics import trajectory_error
from graph.geometry import pose_to_tum, relative
from perception.frame import Intrinsics
from sources import open_dataset, truth_per_frame
from tests.conftest import REDKITCHEN, requires_redkitchen

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
    out[GLITCH_AT + 1 :] = G @ truth[GLITCH_AT + 1 :]
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
    assert report.repair_ate_m == pytest.approx(cost, rel=0.05)


def test_a_pair_check_with_gap_lists_refuted_pairs_without_a_repair(scene):
    report = check_reference(scene, start=6, stop=14, gap=2, stride=1, reference=_glitched(truth_per_frame(scene)))
    assert report.repair_ate_m is None
    assert report.refuted_steps == [8, 9]  # the two pairs that straddle the glitch


def test_loop_records_are_checked_against_reference_and_depth(scene):
    truth = truth_per_frame(scene)
    true_pose = relative(truth[4], truth[6])  # pose of the query (6) in the match frame (4)
    wrong = true_pose.copy()
    wrong[:3, 3] += [0.05, 0.0, 0.0]
    record = lambda T: {"accepted": True, "match_frame": 4, "query_frame": 6, "relative_pose": list(pose_to_tum(T))}
    checks = check_loops(scene, [record(true_pose), record(wrong), dict(record(wrong), accepted=False)])
    assert len(checks) == 2
    right, off = checks
    assert right.residual_loop_m == pytest.approx(right.check.residual_ref_m, abs=2e-4)
    assert off.residual_loop_m > right.residual_loop_m + 0.005
    assert right.check.displacement_m < 0.005


def test_loop_records_of_another_dataset_are_refused(scene):
    with pytest.raises(ValueError, match="indices of this dataset"):
        check_loops(
            scene, [{"accepted": True, "match_frame": 4, "query_frame": 600, "relative_pose": [0, 0, 0, 0, 0, 0, 1]}]
        )


def test_repair_of_a_slice_replaces_only_the_refuted_step():
    """Pure: a straight-line reference from frame 20 on, glitched at step 23 -> 24; the depth's motion there is
    the true one, so the repaired slice is the true line up to one rigid motion."""
    true = np.stack([np.eye(4)] * 8)
    true[:, 0, 3] = 0.01 * np.arange(8)
    glitched = true.copy()
    glitched[4:, 0, 3] += 0.05
    T_depth = relative(true[4], true[3])  # maps frame 23's points into frame 24
    checks = [
        PairCheck(
            20 + k,
            21 + k,
            relative(glitched[k + 1], glitched[k]),
            T_depth if k == 3 else None,
            0.02 if k == 3 else 0.004,
            0.004,
            0.01,
            0.05,
            0.0,
        )
        for k in range(7)
    ]
    fixed, refuted = repaired(glitched, checks, 0.005, first_frame=20)
    assert refuted == [23]
    np.testing.assert_allclose(fixed[4:], glitched[4:])  # the newest part keeps its place
    np.testing.assert_allclose(relative(fixed[0], fixed[7]), relative(true[0], true[7]), atol=1e-12)


def test_pair_arguments_are_checked(scene):
    for start, gap, stride in ((-1, 1, 1), (0, 0, 1), (0, 1, 0)):
        with pytest.raises(ValueError, match="need start >= 0"):
            frame_pairs(scene, start, 20, gap, stride)


def test_cli_prints_the_check_and_fails_in_one_line(tmp_path):
    ok = subprocess.run(
        [
            sys.executable,
            "-m",
            "service",
            "calibrate",
            "reference",
            SCENE,
            "--stop",
            "6",
            "--write",
            str(tmp_path / "b.md"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert ok.returncode == 0, ok.stderr
    assert "reference against depth" in ok.stdout
    assert "<!-- bench:reference -->" in (tmp_path / "b.md").read_text()
    bad = subprocess.run(
        [sys.executable, "-m", "service", "calibrate", "reference", SCENE, "--start", "70"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode == 1 and bad.stderr.startswith("objslam: error:") and len(bad.stderr.splitlines()) == 1


def test_a_reference_motion_that_leaves_the_image_is_refuted_when_the_depth_finds_one():
    nan = float("nan")
    lost = PairCheck(0, 1, np.eye(4), np.eye(4), nan, 0.004, 0.01, nan, nan)
    assert lost.refuted(0.005)
    assert not PairCheck(0, 1, np.eye(4), None, nan, nan, 0.01, nan, nan).refuted(0.005)
    assert not PairCheck(0, 1, np.eye(4), np.eye(4), 0.008, 0.004, 0.01, 0.0, 0.0).refuted(0.005)


@requires_redkitchen
def test_the_slam_benchmarks_run_the_real_sequence_beside_the_repository_by_default() -> None:
    # bench odometry / loops / landmarks without --dataset: the 7-Scenes kitchen first, then the synthetic seeds
    # (the path was once taken one directory too high, and the real rows silently went missing)
    specs = default_datasets()
    assert specs[0] == str(REDKITCHEN) and len(specs) == 4
