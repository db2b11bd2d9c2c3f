"""``objslam eval``: a run directory against a dataset's ground truth.

Trajectory error (ATE / RPE after SE(3) alignment) of ``trajectory.tum`` and ``odometry.tum``; where the
dataset has ground-truth objects (``objects_gt.json``, the synthetic scenes), the mapped objects of
``objects.json`` moved by the trajectory's alignment, matched one-to-one to them (mapped / matched / false,
ground-plane IoU, centroid error), and each matched object's error vector in the world and in the frames of
the ground-truth cameras that see it (along and across their rays), so a common offset shows at a glance.
Association metrics need per-frame instance masks and the service's per-frame associations, which a run
directory does not hold: ``bench association`` measures them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.object_metrics import aligned_objects, error_summary, error_vectors, object_scores
from evaluation.object_truth import object_truth_for, per_object, per_object_markdown
from evaluation.trajectory_metrics import error_dict, evaluate
from graph.trajectory import match_timestamps
from perception.clustering import ClusterConfig
from service.outputs import ate_table, atomic_write
from sources import DatasetError, Trajectory, open_dataset
from sources.tum import read_trajectory

BEGIN, END = "<!-- objslam eval -->", "<!-- /objslam eval -->"


def evaluate_run(run_dir: Path, gt_spec: str, objects_gt: Path | None = None) -> str:
    """Evaluate ``run_dir`` against ``gt_spec``; writes ``metrics.json``, ``eval.png`` and the evaluation
    section of ``report.md`` (the run's own summary stays); returns that section."""
    data = open_dataset(gt_spec)
    gt = data.ground_truth
    if gt is None:
        raise DatasetError(f"{gt_spec} has no ground truth")
    runs = {
        name: read_trajectory(run_dir / f"{name}.tum")
        for name in ("trajectory", "odometry")
        if (run_dir / f"{name}.tum").is_file()
    }
    errors = {name: err for name, traj in runs.items() if (err := evaluate(traj, gt)) is not None}
    if not errors:
        raise DatasetError(f"{run_dir}: no trajectory.tum poses match the ground-truth timestamps")
    result: dict[str, Any] = {
        "dataset": gt_spec,
        "run": str(run_dir),
        "ate": {name: error_dict(err) for name, err in errors.items()},
    }
    truth, objects_file = object_truth_for(data, objects_gt), run_dir / "objects.json"
    if truth is not None and truth.objects and objects_file.is_file() and "trajectory" in errors:
        entries, scale = json.loads(objects_file.read_text()), ClusterConfig().axis_scale
        to_boxes = truth.box_frame_from_world  # the frame the true boxes are upright in (identity: synthetic)
        mapped = aligned_objects(entries, to_boxes @ errors["trajectory"].alignment)
        camera = data.camera
        vectors = error_vectors(mapped, truth.objects, to_boxes @ gt.poses, camera.color, camera.width, camera.height)
        result["objects"] = {
            **object_scores(mapped, truth.objects, scale),
            "truth": truth.source,
            **error_summary(vectors),
            "per_object": vectors,
            "objects_table": per_object(mapped, truth, scale, entries),
        }
    section = evaluation_markdown(result)
    report = run_dir / "report.md"
    atomic_write(report, with_section(report.read_text() if report.is_file() else None, section))
    atomic_write(run_dir / "metrics.json", json.dumps(result, indent=1))
    from evaluation.plot import plot_errors  # matplotlib is slow to import

    plot_errors(
        run_dir / "eval.png",
        {name: position_errors(runs[name], gt, err.alignment) for name, err in errors.items()},
        gt_spec,
    )
    return section


def position_errors(traj: Trajectory, gt: Trajectory, alignment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, position error in m) of the poses matched to the ground truth, after ``alignment``."""
    i_est, i_ref = match_timestamps(traj.timestamps, gt.timestamps)
    moved = traj.poses[i_est, :3, 3] @ alignment[:3, :3].T + alignment[:3, 3]
    return traj.timestamps[i_est], np.linalg.norm(moved - gt.poses[i_ref, :3, 3], axis=1)


def evaluation_markdown(result: dict[str, Any]) -> str:
    """The evaluation section of ``report.md``."""
    lines = [f"## Evaluation against {result['dataset']} (`objslam eval`)", "", *ate_table(result["ate"])]
    objects = result.get("objects")
    if objects is not None:
        iou = "-" if objects["mean_iou"] is None else f"{objects['mean_iou']:.2f}"
        err = "-" if objects["median_centroid_error_m"] is None else f"{objects['median_centroid_error_m']:.3f}"
        lines += [
            "",
            "| ground-truth objects | mapped | matched | false | mean ground-plane IoU | median centroid error (m) |",
            "|---|---|---|---|---|---|",
            f"| {objects['ground_truth']} | {objects['mapped']} | {objects['matched']} | {objects['false']} | "
            f"{iou} | {err} |",
            "",
            f"Objects in the trajectory's ATE alignment; a mapped object matches a true one of its label when "
            f"its centre lies inside the true box grown by 0.25 m (one-to-one); IoU of the ellipse at "
            f"{objects['axis_scale']:g} std with the true box footprint.",
            *error_table(objects),
        ]
        lines += per_object_markdown(objects["objects_table"]) if "objects_table" in objects else []
    lines += ["", "Per-frame position error: `eval.png`; figures: `metrics.json`."]
    return "\n".join(lines) + "\n"


def _vector(values: list[float] | None) -> str:
    return "-" if values is None else ", ".join(f"{v:+.3f}" for v in values)


def error_table(objects: dict[str, Any]) -> list[str]:
    """Report lines: each matched object's error vector (mapped - true centre), and their common part."""
    rows = sorted(objects.get("per_object", []), key=lambda e: e["truth_id"])
    if not rows:
        return []
    along = objects["median_along_ray_m"]
    return [
        "",
        "| true id | label | error (m) | world dx, dy, dz (m) | camera right, down, forward (m) | along ray (m) | "
        "across ray (m) | views |",
        "|---|---|---|---|---|---|---|---|",
        *(
            f"| {e['truth_id']} | {e['label']} | {e['error_m']:.3f} | {_vector(e['world_m'])} | "
            f"{_vector(e['camera_m'])} | {e['along_ray_m']:+.3f} | {e['across_ray_m']:.3f} | {e['views']} |"
            for e in rows
        ),
        f"| all | | | mean {_vector(objects['mean_world_error_m'])} | mean {_vector(objects['mean_camera_error_m'])} "
        f"| median {along:+.3f} | | |",
        "",
        "Error = mapped minus true centre. Camera frame and rays: averaged over the ground-truth camera poses "
        "whose image holds the true centre (within 5 m, occlusion not tested; else the nearest pose); along the "
        "ray < 0 is towards the camera.",
    ]


def with_section(report: str | None, section: str) -> str:
    """``report`` with the evaluation section replaced (or appended; a report of its own without one)."""
    block = f"{BEGIN}\n{section}{END}\n"
    if report is None:
        return "# objslam evaluation\n\n" + block
    if BEGIN in report and END in report:
        head, rest = report.split(BEGIN, 1)
        return head + block + rest.split(END, 1)[1].lstrip("\n")
    return report.rstrip("\n") + "\n\n" + block
