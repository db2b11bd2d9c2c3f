"""``objslam eval``: trajectory error of a run directory against a dataset's ground truth."""

from __future__ import annotations

import json
from pathlib import Path

from service.outputs import atomic_write, evaluate, report_markdown
from service.sources import DatasetError, open_dataset
from service.sources.tum import read_trajectory


def evaluate_run(run_dir: Path, gt_spec: str) -> str:
    """Compute ATE / RPE of ``trajectory.tum`` and ``odometry.tum``; rewrite ``report.md``; return it."""
    gt = open_dataset(gt_spec).ground_truth
    if gt is None:
        raise DatasetError(f"{gt_spec} has no ground truth")
    summary: dict = {"dataset": gt_spec, "run": str(run_dir), "ate": {}}
    for name in ("trajectory", "odometry"):
        path = run_dir / f"{name}.tum"
        if not path.is_file():
            continue
        err = evaluate(read_trajectory(path), gt)
        if err is not None:
            summary["ate"][name] = {k: getattr(err, k) for k in (
                "pairs", "ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_max_m", "rpe_trans_rmse_m",
                "rpe_rot_rmse_deg")}
    if not summary["ate"]:
        raise DatasetError(f"{run_dir}: no trajectory.tum poses match the ground-truth timestamps")
    text = report_markdown(summary)
    atomic_write(run_dir / "report.md", text)
    atomic_write(run_dir / "metrics.json", json.dumps(summary["ate"], indent=1))
    return text
