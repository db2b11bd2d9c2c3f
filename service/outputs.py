"""Writing the SPEC section 4 outputs: trajectories, objects, loops, report and the top-down map."""

from __future__ import annotations

import io
import json
import logging
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.trajectory_metrics import error_dict, evaluate
from graph.geometry import pose_to_tum
from graph.trajectory import Trajectory

log = logging.getLogger(__name__)

EXIT_OUTPUTS_FAILED = 3  # exit code of `serve` (on shutdown) and `run` when some output files could not be written


class OutputsError(OSError):
    """Some output files could not be written (each failure logged); the others were. ``summary`` is what
    ``write_outputs`` returns otherwise, ``failed`` maps each missing file to its reason."""

    def __init__(self, out: Path, failed: dict[str, str], summary: dict[str, Any]):
        names = ", ".join(f"{name} ({reason})" for name, reason in failed.items())
        super().__init__(f"could not write {len(failed)} output file(s) into {out}: {names}")
        self.failed, self.summary = failed, summary


def check_output_dir(out: Path, flag: str = "--out") -> None:
    """Before any work: ``out`` must be a writable directory or one that can be created there, so that a long run
    does not end in a failure to write its results."""
    path = Path(out).absolute()
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        where = "is a file" if existing == path else f"cannot be created: {existing} is a file"
        raise NotADirectoryError(f"{flag} {out} {where}, not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"{flag} {out}: {existing} is not writable")


def atomic_write(path: Path, data: str | bytes) -> None:
    """Write via a temporary file and rename, so readers never see a partial file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data.encode() if isinstance(data, str) else data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk or a directory in the way: no temporary file left behind
        Path(tmp).unlink(missing_ok=True)
        raise


def tum_text(traj: Trajectory) -> str:
    """TUM trajectory text (``t tx ty tz qx qy qz qw``), readable by evo."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip(traj.timestamps, traj.poses, strict=True):
        lines.append(" ".join([f"{t:.6f}"] + [f"{v:.9f}" for v in pose_to_tum(T)]))
    return "\n".join(lines) + "\n"


def write_outputs(
    out: Path,
    trajectory: Trajectory,
    odometry: Trajectory,
    summary: dict[str, Any],
    gt: Trajectory | None,
    objects: list | None = None,
    loops: list | None = None,
    cloud: np.ndarray | None = None,
) -> dict[str, Any]:
    """Write every output file into ``out``; returns the summary with the metrics added.

    With map points (``cloud``) also ``cloud.npy`` and, when the trajectory crosses itself, the map's grid
    world ``grid.json`` / ``grid.png`` for ``train-lc --from-map``. Each file is written on its own: one that
    fails (read-only directory, full disk) is logged and the others are still written; then OutputsError names
    the failures. An empty map (no frame processed) gives empty trajectories, objects and loops.
    """
    failed: dict[str, str] = {}

    def attempt(name: str, write: Callable[[], Any]) -> Any:
        try:
            return write()
        except Exception as exc:  # any failure of one file must leave the others to be written
            reason = " ".join(str(exc).split()) or type(exc).__name__
            log.error("could not write %s: %s", out / name, reason)
            log.debug("writing %s failed", name, exc_info=True)
            failed[name] = reason
            return None

    if cloud is not None:
        attempt("cloud.npy", lambda: atomic_write(out / "cloud.npy", _npy(cloud)))
        grid = attempt("grid.json", lambda: _write_grid(out, summary, trajectory, cloud, objects or []))
        summary = {**summary, "grid_world": bool(grid)}
    attempt("trajectory.tum", lambda: atomic_write(out / "trajectory.tum", tum_text(trajectory)))
    attempt("odometry.tum", lambda: atomic_write(out / "odometry.tum", tum_text(odometry)))
    attempt("objects.json", lambda: atomic_write(out / "objects.json", json.dumps(objects or [], indent=1)))
    attempt("loops.json", lambda: atomic_write(out / "loops.json", json.dumps(loops or [], indent=1)))
    metrics = {name: evaluate(t, gt) for name, t in (("trajectory", trajectory), ("odometry", odometry))}
    summary = {**summary, "ate": {k: error_dict(v) for k, v in metrics.items() if v is not None}}
    attempt("report.md", lambda: atomic_write(out / "report.md", report_markdown(summary)))
    from service.mapplot import plot_map  # matplotlib is slow to import; only needed here

    error = metrics["trajectory"]
    attempt("map.png", lambda: plot_map(out / "map.png", trajectory, odometry, gt, error, objects, loops))
    if failed:
        raise OutputsError(out, failed, summary)
    return summary


def _npy(cloud: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(cloud, np.float32))
    return buf.getvalue()


def _write_grid(out: Path, summary: dict[str, Any], trajectory: Trajectory, cloud: np.ndarray, objects: list) -> bool:
    """The map's grid world when it has one; none from a map without poses or points (nothing to build it on)."""
    if len(trajectory) < 2 or len(cloud) == 0:
        return False
    from rl.map_files import try_write_grid

    return try_write_grid(out, summary.get("dataset", "map"), trajectory, cloud, objects)


def report_markdown(summary: dict[str, Any]) -> str:
    """``report.md``: the run summary and, with ground truth, ATE / RPE tables."""
    lines = [f"# objslam report: {summary.get('dataset', '')}", ""]
    if not summary.get("frames_processed"):
        lines += ["No frame was processed: the trajectories, objects and loops are empty.", ""]
    lines += ["| quantity | value |", "|---|---|"]
    for key, value in summary.items():
        if key in ("ate", "dataset", "latency"):
            continue
        lines.append(f"| {key} | {json.dumps(value) if isinstance(value, (dict, list)) else value} |")
    ate = summary.get("ate", {})
    if ate:
        lines += ["", "## Trajectory error (SE(3) Umeyama alignment, matched by timestamp)", "", *ate_table(ate)]
    else:
        lines += ["", "No ground truth: no trajectory error."]
    untied = summary.get("tracking", {}).get("untied_frames")
    if untied:
        lines += [
            "",
            "## Frames not tied to the map",
            "",
            "Tracking was lost before these frames (seq ranges) and no relocalization or loop closure joined their "
            "map segment to the map; trajectory.tum leaves them out (odometry.tum has them).",
            "",
            ", ".join(f"{a}-{b}" if a != b else f"{a}" for a, b in untied),
        ]
    latency = summary.get("latency")
    if latency:
        lines += ["", "## Stage latency (ms)", "", "| stage | n | p50 | p95 | p99 | max |", "|---|---|---|---|---|---|"]
        for stage, s in latency.items():
            if s.get("n"):
                lines.append(f"| {stage} | {s['n']} | {s['p50_ms']} | {s['p95_ms']} | {s['p99_ms']} | {s['max_ms']} |")
    return "\n".join(lines) + "\n"


def ate_table(ate: dict[str, dict[str, Any]]) -> list[str]:
    """Markdown rows of ATE / RPE per trajectory (``error_dict`` entries): report.md and ``objslam eval``."""
    lines = [
        "| trajectory | pairs | ATE RMSE (m) | ATE median (m) | ATE max (m) | RPE trans RMSE (m/frame) "
        "| RPE rot RMSE (deg/frame) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, e in ate.items():
        lines.append(
            f"| {name} | {e['pairs']} | {e['ate_rmse_m']:.4f} | {e['ate_median_m']:.4f} | "
            f"{e['ate_max_m']:.4f} | {e['rpe_trans_rmse_m']:.5f} | {e['rpe_rot_rmse_deg']:.4f} |"
        )
    return lines


def run_summary(name: str, frames: int, elapsed: float, status: dict[str, Any]) -> dict[str, Any]:
    """The summary of a run or a serving service from its ``status`` (report.md, the printed table)."""
    return {
        "dataset": name,
        "frames": frames,
        "frames_processed": status["frames_processed"],
        "frames_rejected": status["frames_rejected"],
        "frames_dropped": status["frames_dropped"],
        "keyframes": status["keyframes"],
        "poses": status["poses"],
        "objects_by_class": status.get("objects_by_class", {}),
        "keyframe_detections_by_class": status.get("keyframe_detections_by_class", {}),
        "loop_closures": status["loop_closures"]["accepted"],
        "loop_candidates": status["loop_closures"]["accepted"] + status["loop_closures"]["rejected"],
        "tracking_lost": status.get("tracking_lost", 0),
        "tracking": status.get("tracking", {}),
        "landmarks": status.get("landmarks", 0),
        "landmark_measurements": status.get("landmark_measurements", 0),
        "object_reposes": status.get("object_reposes", 0),
        "seconds": round(elapsed, 3),
        "throughput_fps": round(status["frames_processed"] / elapsed, 2) if elapsed > 0 else 0.0,
        "latency": status["latency"],
    }
