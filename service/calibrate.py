"""Sensor calibration against a dataset's reference trajectory: reads the frames, calls the pure estimators."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from graph.geometry import relative
from perception.depth_calibration import DepthScaleEstimate, estimate_depth_scale
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
