"""Depth-scale calibration against a reference trajectory (motion capture, or a dataset's ground truth).

Structured-light depth sensors (Kinect v1 and its kin) report depth with device-specific systematic errors
(Smisek et al. 2011, "3D with Kinect"; Khoshelham 2011); the first-order part is a scale. A scale error makes
every metric motion that depth measures too short or too long, so a trajectory built on it is off in size
against the reference, and no rigid (SE(3)) alignment removes that.

The estimate: for frame pairs ``gap`` frames apart, point-to-plane ICP between their depth images starts at
the reference relative pose and settles where the depth geometry agrees best; the ratio of its translation to
the reference translation measures the scale of depth against the reference (depth scaled by ``s`` scales
every registered translation by ``s``). The median ratio over the pairs is the factor to divide the depth
units per metre by. Pure computation: the caller reads the frames.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from graph.geometry import motion_magnitude
from perception.frame import Intrinsics
from perception.icp import icp_refine


@dataclass(frozen=True)
class DepthScaleEstimate:
    """``ratio``: median ICP / reference translation over ``pairs`` usable pairs (of ``tried``); ``q25``,
    ``q75`` its quartiles. Depth units per metre calibrated = nominal x ``ratio``."""

    ratio: float
    q25: float
    q75: float
    pairs: int
    tried: int

    def calibrated_depth_scale(self, nominal: float) -> float:
        """Raw depth units per metre that make depth agree with the reference (nominal x ratio)."""
        return nominal * self.ratio


def translation_ratio(
    src_depth_m: np.ndarray, dst_depth_m: np.ndarray, K: Intrinsics, T_dst_src: np.ndarray
) -> float | None:
    """ICP translation / reference translation for one pair (None: ICP found too little overlap)."""
    result = icp_refine(src_depth_m, dst_depth_m, K, T_dst_src)
    if result is None:
        return None
    return motion_magnitude(result.T)[0] / motion_magnitude(T_dst_src)[0]


def estimate_depth_scale(
    pairs: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], K: Intrinsics, min_motion_m: float = 0.03
) -> DepthScaleEstimate:
    """The depth scale against the reference from ``(src_depth_m, dst_depth_m, T_dst_src)`` pairs, where
    ``T_dst_src`` is the reference pose of the source camera in the destination camera. Pairs that moved less
    than ``min_motion_m`` are skipped (their ratio is mostly noise). Raises ValueError when no pair is usable."""
    ratios, tried = [], 0
    for src, dst, T in pairs:
        if motion_magnitude(T)[0] < min_motion_m:
            continue
        tried += 1
        ratio = translation_ratio(src, dst, K, T)
        if ratio is not None:
            ratios.append(ratio)
    if not ratios:
        raise ValueError(f"no usable frame pair ({tried} moved at least {min_motion_m} m; ICP failed on all)")
    q25, median, q75 = np.percentile(ratios, [25, 50, 75])
    return DepthScaleEstimate(float(median), float(q25), float(q75), len(ratios), tried)
