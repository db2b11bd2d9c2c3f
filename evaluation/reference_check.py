"""Does a reference trajectory agree with the depth it claims to describe? (pure computation)

A dataset's reference (motion capture, or KinectFusion's track, as in 7-Scenes) is what trajectory error is
measured against, so its own errors are a floor no estimate can go below. For a frame pair, the depth of one
frame moved into the other by the reference relative pose should land on the other's depth. The check
compares three motions of each pair by that depth residual (median |depth difference| over the pixels both
frames see):

- the reference motion,
- the motion the depth prefers: point-to-plane ICP started at the reference motion, coarse to fine,
- no motion at all (the null: a reference step that fits worse than standing still is not a motion at all).

A pair is *refuted* when the reference's residual exceeds the depth optimum's by more than a margin: the
depth images themselves show a different motion. Replacing the refuted steps of a frame-to-frame chain by
the depth's motion gives a *repaired* reference; its trajectory error against the original is what the
refuted steps alone cost any estimate that follows the depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.geometry import inverse, motion_magnitude, relative
from perception.frame import Intrinsics
from perception.icp import icp_refine, project, vertex_map

# coarse to fine: (image level, iterations, correspondence gate from -> to, m)
PYRAMID = ((4, 15, (0.08, 0.03)), (2, 15, (0.04, 0.02)))


@dataclass(frozen=True)
class PairCheck:
    """One frame pair: ``T_ref`` and ``T_depth`` map the source camera's points into the destination camera
    (reference motion, depth optimum); residuals are median |depth difference| in metres; ``displacement``
    is how far (m, deg) the depth optimum lies from the reference motion."""

    src: int
    dst: int
    T_ref: np.ndarray
    T_depth: np.ndarray | None
    residual_ref_m: float
    residual_depth_m: float
    residual_still_m: float
    displacement_m: float
    displacement_deg: float

    def refuted(self, margin_m: float) -> bool:
        """The depth fits another motion better than the reference's by more than ``margin_m`` (or the reference
        motion moves the source depth out of the destination image altogether, while that motion does not)."""
        if self.T_depth is None or np.isnan(self.residual_depth_m):
            return False
        return bool(np.isnan(self.residual_ref_m) or self.residual_ref_m - self.residual_depth_m > margin_m)

    @property
    def worse_than_still(self) -> bool:
        """The reference motion fits the depth worse than no motion at all."""
        return self.residual_ref_m > self.residual_still_m


def depth_residual(
    src_depth_m: np.ndarray, dst_depth_m: np.ndarray, K: Intrinsics, T_dst_src: np.ndarray, step: int = 2
) -> float:
    """Median |depth difference| (m) of ``src`` depth moved by ``T_dst_src`` into the ``dst`` image, over every
    ``step``-th source pixel that lands on valid destination depth; NaN when none does."""
    p = vertex_map(src_depth_m, K)[::step, ::step].reshape(-1, 3)
    p = p[np.isfinite(p[:, 2])] @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]
    ok, idx = project(p, K, dst_depth_m.shape)
    z = dst_depth_m.reshape(-1)[idx]
    seen = np.isfinite(z)
    if not seen.any():
        return float("nan")
    return float(np.median(np.abs(z[seen] - p[ok][seen, 2])))


def depth_optimum(
    src_depth_m: np.ndarray, dst_depth_m: np.ndarray, K: Intrinsics, T_init: np.ndarray
) -> np.ndarray | None:
    """``T_dst_src`` where the two depth images agree best near ``T_init`` (coarse-to-fine point-to-plane ICP);
    None when too little of them overlaps."""
    T = T_init
    for level, iterations, gate in PYRAMID:
        result = icp_refine(
            src_depth_m, dst_depth_m, K, T, level=level, step=1, iterations=iterations, max_dist=gate, min_inliers=100
        )
        if result is None:
            return None
        T = result.T
    return T


def check_pair(
    src: int, dst: int, src_depth_m: np.ndarray, dst_depth_m: np.ndarray, K: Intrinsics, T_ref: np.ndarray
) -> PairCheck:
    """The reference motion ``T_ref`` (source points into the destination camera) against the depth. When ICP
    started at the reference finds too little overlap, it is started again at no motion."""
    T_depth = depth_optimum(src_depth_m, dst_depth_m, K, T_ref)
    if T_depth is None:
        T_depth = depth_optimum(src_depth_m, dst_depth_m, K, np.eye(4))
    ref = depth_residual(src_depth_m, dst_depth_m, K, T_ref)
    still = depth_residual(src_depth_m, dst_depth_m, K, np.eye(4))
    if T_depth is None:
        return PairCheck(src, dst, T_ref, None, ref, float("nan"), still, float("nan"), float("nan"))
    dt, dr = motion_magnitude(relative(T_ref, T_depth))
    return PairCheck(
        src,
        dst,
        T_ref,
        T_depth,
        ref,
        depth_residual(src_depth_m, dst_depth_m, K, T_depth),
        still,
        dt,
        float(np.degrees(dr)),
    )


def repaired(
    reference: np.ndarray, checks: list[PairCheck], margin_m: float, first_frame: int = 0
) -> tuple[np.ndarray, list[int]]:
    """The reference poses (N, 4, 4, camera to world; pose k is frame ``first_frame + k``) with every refuted
    step ``i -> i + 1`` among ``checks`` replaced by the depth's motion; frames before such a step are moved with
    it (the newest part of the trajectory keeps its place). Returns the poses and the refuted steps' first
    frames."""
    steps = {
        c.src - first_frame: c.T_depth
        for c in checks
        if c.dst == c.src + 1 and c.refuted(margin_m) and c.T_depth is not None  # refuted: T_depth is set
    }
    out = reference.copy()
    # walk back from the last frame: each frame keeps its reference motion to the next one, except across a
    # refuted step, where the depth's motion is used
    for i in range(len(reference) - 2, -1, -1):
        step = inverse(steps[i]) if i in steps else relative(reference[i], reference[i + 1])
        out[i] = out[i + 1] @ inverse(step)
    return out, sorted(i + first_frame for i in steps if 0 <= i < len(reference) - 1)
