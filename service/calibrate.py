"""Sensor calibration against a dataset's reference trajectory, and the reference checked against the sensor:
reads the frames, calls the pure estimators."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from graph.geometry import pose_from_tum, relative
from graph.metrics import trajectory_error
from perception.depth_calibration import DepthScaleEstimate, estimate_depth_scale
from perception.reference_check import PairCheck, check_pair, depth_residual, repaired
from service.sources import Dataset, truth_per_frame


def frame_pairs(dataset: Dataset, start: int, stop: int, gap: int, stride: int) -> list[tuple[int, int]]:
    """Pairs (i, i + gap) for i in [start, stop) every ``stride`` frames, both inside the dataset."""
    stop = min(stop, len(dataset)) - gap
    return [(i, i + gap) for i in range(max(0, start), stop, stride)]


def calibrate_depth_scale(dataset: Dataset, start: int = 0, stop: int | None = None, gap: int = 15,
                          stride: int = 9) -> DepthScaleEstimate:
    """The depth scale of ``dataset`` against its ground truth over frames [start, stop)."""
    truth = truth_per_frame(dataset)
    stop = len(dataset) if stop is None else stop
    pairs = frame_pairs(dataset, start, stop, gap, stride)
    if not pairs:
        raise ValueError(f"no frame pair {gap} frames apart in frames {start}..{stop - 1}")
    K = dataset.camera.depth

    def depth_pairs() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for i, j in pairs:
            yield dataset.frame(j).depth_m(), dataset.frame(i).depth_m(), relative(truth[i], truth[j])

    return estimate_depth_scale(depth_pairs(), K)


@dataclass(frozen=True)
class ReferenceReport:
    """``checks`` of frame pairs (``gap`` apart every ``stride`` frames); with gap 1 and stride 1, the
    ``repaired`` reference, its ``refuted_steps`` and the ATE (m) of the repaired reference against the
    original: what the refuted steps alone cost an estimate that follows the depth."""

    checks: list[PairCheck]
    margin_m: float
    refuted_steps: list[int]
    repair_ate_m: float | None


def check_reference(dataset: Dataset, start: int = 0, stop: int | None = None, gap: int = 1, stride: int = 1,
                    margin_m: float = 0.005, reference: np.ndarray | None = None) -> ReferenceReport:
    """The reference trajectory of ``dataset`` (its ground truth unless ``reference``, (N, 4, 4), is given)
    against its own depth, over pairs (i, i + gap) of frames [start, stop)."""
    reference = truth_per_frame(dataset) if reference is None else reference
    stop = len(dataset) if stop is None else stop
    pairs = frame_pairs(dataset, start, stop, gap, stride)
    if not pairs:
        raise ValueError(f"no frame pair {gap} frames apart in frames {start}..{stop - 1}")
    K = dataset.camera.depth
    checks, depth = [], {}
    for i, j in pairs:
        for k in (i, j):
            depth.setdefault(k, dataset.frame(k).depth_m())
        checks.append(check_pair(i, j, depth[i], depth[j], K, relative(reference[j], reference[i])))
        depth.pop(i)
    if gap != 1 or stride != 1:
        return ReferenceReport(checks, margin_m, [c.src for c in checks if c.refuted(margin_m)], None)
    fixed, refuted = repaired(reference[start:stop], _shifted(checks, start), margin_m)
    return ReferenceReport(checks, margin_m, [s + start for s in refuted],
                           trajectory_error(fixed, reference[start:stop]).ate_rmse_m)


def _shifted(checks: list[PairCheck], start: int) -> list[PairCheck]:
    """``checks`` with frame numbers counted from ``start`` (the first frame of a sliced reference)."""
    return [replace(c, src=c.src - start, dst=c.dst - start) for c in checks]


@dataclass(frozen=True)
class LoopCheck:
    """An accepted loop closure (``check``: the reference's relative pose of its two frames against their depth)
    and the depth residual (m) of the loop's own verified relative pose."""

    check: PairCheck
    residual_loop_m: float


def check_loops(dataset: Dataset, loops: list[dict], reference: np.ndarray | None = None) -> list[LoopCheck]:
    """The accepted loops of a run (``loops.json`` records) against the reference and the depth: the query
    frame's depth moved into the match frame by the reference, by the depth's optimum and by the loop."""
    reference = truth_per_frame(dataset) if reference is None else reference
    K, out = dataset.camera.depth, []
    for record in (r for r in loops if r.get("accepted") and "relative_pose" in r):
        q, m = record["query_frame"], record["match_frame"]
        src, dst = dataset.frame(q).depth_m(), dataset.frame(m).depth_m()
        check = check_pair(q, m, src, dst, K, relative(reference[m], reference[q]))
        out.append(LoopCheck(check, depth_residual(src, dst, K, pose_from_tum(np.asarray(record["relative_pose"])))))
    return out
