"""``objslam eval`` on a run directory: trajectory error, object metrics, plot, and the run's report kept."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from evaluation.object_metrics import aligned_objects, object_scores
from service.config import load_settings
from service.evaluate import evaluate_run, with_section
from service.run import run_dataset
from sources import DatasetError, open_dataset
from tests.test_tum_loader import _write_tum

SPEC = "synthetic:room?seed=1&frames=100&width=320&height=240"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    run_dataset(SPEC, out, load_settings(None, {"detector": {"enabled": False}}), progress=False)
    return out


def test_eval_measures_trajectory_and_objects_and_keeps_the_run_report(run_dir):
    run_report = (run_dir / "report.md").read_text()
    section = evaluate_run(run_dir, SPEC)
    report = (run_dir / "report.md").read_text()
    assert report.startswith(run_report.rstrip("\n")) and section in report  # the run's summary stays
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["ate"]["trajectory"]["ate_rmse_m"] < 0.05 and metrics["ate"]["odometry"]["pairs"] == 100
    objects = metrics["objects"]
    assert objects["ground_truth"] == len(open_dataset(SPEC).objects) and objects["mapped"] > 3
    assert objects["matched"] >= objects["mapped"] - 1 and 0.3 < objects["mean_iou"] <= 1.0
    assert objects["median_centroid_error_m"] < 0.2 and (run_dir / "eval.png").stat().st_size > 10_000
    assert evaluate_run(run_dir, SPEC) == section  # a second eval replaces its section
    assert (run_dir / "report.md").read_text() == report


def test_objects_are_scored_in_the_ground_truth_frame_through_the_alignment():
    truth = open_dataset(SPEC).objects
    entries = [
        {"label": t.label, "mean": list(t.center), "cov": np.diag(np.square(t.size) / 12).tolist()} for t in truth
    ]
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = [1.0, 2.0, 0.0]
    moved = [
        {**e, "mean": list(np.linalg.inv(T)[:3, :3] @ np.asarray(e["mean"]) + np.linalg.inv(T)[:3, 3])} for e in entries
    ]  # the map frame differs from the ground truth's by T
    scores = object_scores(aligned_objects(moved, T), truth, 1.5)
    assert scores["matched"] == len(truth) and scores["false"] == 0 and scores["median_centroid_error_m"] < 1e-9
    assert object_scores(aligned_objects(moved, np.eye(4)), truth, 1.5)["matched"] < len(truth)


def test_with_section_appends_replaces_and_starts_a_report():
    once = with_section("# run\n", "A\n")
    assert once.startswith("# run\n") and "A\n" in once and with_section(once, "B\n").count("B\n") == 1
    assert "A\n" not in with_section(once, "B\n") and with_section(None, "C\n").startswith("# objslam evaluation")


def test_eval_without_ground_truth_fails_with_one_clear_line(run_dir, tmp_path):
    _write_tum(tmp_path, odometry=False, detections=False)  # no groundtruth.txt
    with pytest.raises(DatasetError, match="no ground truth"):
        evaluate_run(run_dir, str(tmp_path))
    cli = subprocess.run(
        [sys.executable, "-m", "service", "eval", str(run_dir), "--gt", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert cli.returncode == 1 and cli.stderr.startswith("objslam: error:") and len(cli.stderr.splitlines()) == 1
