"""Mapped objects against ground-truth boxes: one-to-one matching, ground-plane IoU and centroid error.

Used by ``objslam bench objects`` / ``bench landmarks`` and by ``objslam eval`` (pure computation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from sources.base import ObjectTruth


@dataclass(frozen=True)
class MappedObject:
    """A mapped object as matching needs it: label, centre and (for the IoU) covariance."""

    label: str
    mean: np.ndarray
    cov: np.ndarray | None = None


def aligned_objects(entries: list[dict[str, Any]], T: np.ndarray) -> list[MappedObject]:
    """``objects.json`` entries moved by the rigid transform ``T`` (e.g. the trajectory's ATE alignment)."""
    R, t = T[:3, :3], T[:3, 3]
    return [
        MappedObject(e["label"], R @ np.asarray(e["mean"], float) + t, R @ np.asarray(e["cov"], float) @ R.T)
        for e in entries
    ]


def ellipse_box_iou(mean: np.ndarray, cov: np.ndarray, scale: float, truth: ObjectTruth, res: float = 0.01) -> float:
    """Ground-plane IoU of the ellipse (xy covariance, ``scale`` std) and the true yawed box footprint (raster)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov)[:2, :2])
    ax = np.sqrt(np.clip(vals, 1e-12, None)) * scale
    centre = np.asarray(truth.center[:2], float)
    half = np.asarray(truth.size[:2], float) / 2.0
    reach = max(ax.max(), np.hypot(*half)) + np.linalg.norm(mean[:2] - centre) + res
    g = np.arange(-reach, reach, res)
    X, Y = np.meshgrid((mean[0] + centre[0]) / 2 + g, (mean[1] + centre[1]) / 2 + g)
    dx, dy = X - mean[0], Y - mean[1]
    along, across = dx * vecs[0, 0] + dy * vecs[1, 0], dx * vecs[0, 1] + dy * vecs[1, 1]
    inside_e = (along / ax[0]) ** 2 + (across / ax[1]) ** 2 <= 1
    c, s = np.cos(truth.yaw), np.sin(truth.yaw)
    bx, by = X - centre[0], Y - centre[1]
    inside_b = (np.abs(c * bx + s * by) <= half[0]) & (np.abs(-s * bx + c * by) <= half[1])
    return float((inside_e & inside_b).sum() / max((inside_e | inside_b).sum(), 1))


def match_objects(objects: list, truth: list[ObjectTruth], margin: float = 0.25) -> list[tuple[int, int]]:
    """One-to-one (mapped, true) matches: same label, centroid inside the true box grown by ``margin``;
    ``objects`` need ``label`` and ``mean``."""
    cost = np.full((len(objects), len(truth)), 1e6)
    for a, o in enumerate(objects):
        for b, t in enumerate(truth):
            d = o.mean - np.asarray(t.center)
            c, s = np.cos(t.yaw), np.sin(t.yaw)
            local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
            if o.label == t.label and np.all(np.abs(local) <= np.asarray(t.size) / 2 + margin):
                cost[a, b] = float(np.linalg.norm(d))
    if cost.size == 0:
        return []
    rows, cols = linear_sum_assignment(cost)
    return [(int(a), int(b)) for a, b in zip(rows, cols, strict=True) if cost[a, b] < 1e6]


def object_scores(objects: list, truth: list[ObjectTruth], axis_scale: float) -> dict[str, Any]:
    """Matched / false objects, mean ground-plane IoU (ellipse of ``axis_scale`` std vs true box) and median
    3D centroid error, over the one-to-one matches of ``match_objects``."""
    matches = match_objects(objects, truth)
    ious = [ellipse_box_iou(objects[a].mean, objects[a].cov, axis_scale, truth[b]) for a, b in matches]
    errors = [float(np.linalg.norm(objects[a].mean - np.asarray(truth[b].center))) for a, b in matches]
    return {
        "ground_truth": len(truth),
        "mapped": len(objects),
        "matched": len(matches),
        "false": len(objects) - len(matches),
        "mean_iou": float(np.mean(ious)) if ious else None,
        "median_centroid_error_m": float(np.median(errors)) if errors else None,
        "axis_scale": axis_scale,
    }
