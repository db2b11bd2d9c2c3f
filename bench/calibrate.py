"""Sensor calibration against a dataset's reference trajectory, and the reference checked against the sensor:
reads the frames, calls the pure estimators."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from evaluation.depth_calibration import DepthScaleEstimate, estimate_depth_scale
from evaluation.reference_check import PairCheck, check_pair, depth_residual, repaired
from evaluation.trajectory_metrics import trajectory_error
from graph.geometry import pose_from_tum, relative
from sources import Dataset, truth_per_frame


def frame_pairs(dataset: Dataset, start: int, stop: int, gap: int, stride: int) -> list[tuple[int, int]]:
    """Pairs (i, i + gap) for i in [start, stop) every ``stride`` frames, both inside the dataset."""
    if start < 0 or gap < 1 or stride < 1:
        raise ValueError(f"need start >= 0, gap >= 1 and stride >= 1 (got {start}, {gap}, {stride})")
    stop = min(stop, len(dataset)) - gap
    return [(i, i + gap) for i in range(start, stop, stride)]


def _pairs(dataset: Dataset, start: int, stop: int | None, gap: int, stride: int) -> tuple[list[tuple[int, int]], int]:
    """``frame_pairs`` over [start, stop) (stop None: the whole dataset) and the stop used; ValueError when none."""
    stop = len(dataset) if stop is None else min(stop, len(dataset))
    pairs = frame_pairs(dataset, start, stop, gap, stride)
    if not pairs:
        raise ValueError(f"no frame pair {gap} frames apart in frames {start}..{stop - 1}")
    return pairs, stop


def calibrate_depth_scale(
    dataset: Dataset, start: int = 0, stop: int | None = None, gap: int = 15, stride: int = 9
) -> DepthScaleEstimate:
    """The depth scale of ``dataset`` against its ground truth over frames [start, stop)."""
    truth = truth_per_frame(dataset)
    pairs, _ = _pairs(dataset, start, stop, gap, stride)
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


def check_reference(
    dataset: Dataset,
    start: int = 0,
    stop: int | None = None,
    gap: int = 1,
    stride: int = 1,
    margin_m: float = 0.005,
    reference: np.ndarray | None = None,
) -> ReferenceReport:
    """The reference trajectory of ``dataset`` (its ground truth unless ``reference``, (N, 4, 4), is given)
    against its own depth, over pairs (i, i + gap) of frames [start, stop)."""
    reference = truth_per_frame(dataset) if reference is None else reference
    pairs, stop = _pairs(dataset, start, stop, gap, stride)
    K = dataset.camera.depth
    uses = Counter(k for pair in pairs for k in pair)
    checks, depth = [], {}
    for i, j in pairs:
        for k in (i, j):
            if k not in depth:
                depth[k] = dataset.frame(k).depth_m()
        checks.append(check_pair(i, j, depth[i], depth[j], K, relative(reference[j], reference[i])))
        for k in (i, j):  # each depth image is held only until its last pair
            uses[k] -= 1
            if not uses[k]:
                del depth[k]
    if gap != 1 or stride != 1 or stop - start < 3:
        return ReferenceReport(checks, margin_m, [c.src for c in checks if c.refuted(margin_m)], None)
    fixed, refuted = repaired(reference[start:stop], checks, margin_m, first_frame=start)
    return ReferenceReport(checks, margin_m, refuted, trajectory_error(fixed, reference[start:stop]).ate_rmse_m)


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
        q, m = record.get("query_frame"), record.get("match_frame")
        if not (isinstance(q, int) and isinstance(m, int) and 0 <= q < len(dataset) and 0 <= m < len(dataset)):
            raise ValueError(
                f"loop record {q!r} -> {m!r}: frames must be indices of this dataset's "
                f"{len(dataset)} frames (loops.json of a run of another dataset?)"
            )
        src, dst = dataset.frame(q).depth_m(), dataset.frame(m).depth_m()
        check = check_pair(q, m, src, dst, K, relative(reference[m], reference[q]))
        out.append(LoopCheck(check, depth_residual(src, dst, K, pose_from_tum(np.asarray(record["relative_pose"])))))
    return out
