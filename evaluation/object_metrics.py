"""Mapped objects against ground-truth boxes: one-to-one matching, ground-plane IoU, centroid error and its
direction (in the world, and in the frames of the cameras that saw the object).

Used by ``objslam bench objects`` / ``bench landmarks`` and by ``objslam eval`` (pure computation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from perception.camera import Intrinsics, points_to_pixels
from sources.base import ObjectTruth


@dataclass(frozen=True)
class MappedObject:
    """A mapped object as matching needs it: label, centre, (for the IoU) covariance and its map id."""

    label: str
    mean: np.ndarray
    cov: np.ndarray | None = None
    id: int = -1


def aligned_objects(entries: list[dict[str, Any]], T: np.ndarray) -> list[MappedObject]:
    """``objects.json`` entries moved by the rigid transform ``T`` (e.g. the trajectory's ATE alignment)."""
    R, t = T[:3, :3], T[:3, 3]
    return [
        MappedObject(
            e["label"],
            R @ np.asarray(e["mean"], float) + t,
            R @ np.asarray(e["cov"], float) @ R.T,
            int(e.get("id", -1)),
        )
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


def viewing_poses(
    center: np.ndarray, poses: np.ndarray, K: Intrinsics, width: int, height: int, max_range_m: float = 5.0
) -> np.ndarray:
    """Indices of the camera-to-world ``poses`` (N, 4, 4) whose image holds the point ``center``: in front of the
    camera, within ``max_range_m`` and inside the frame (occlusion is not tested); the nearest pose alone when
    none does."""
    cam = np.einsum("nji,nj->ni", poses[:, :3, :3], center - poses[:, :3, 3])  # R^T (c - t)
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = points_to_pixels(cam, K)
    seen = (cam[:, 2] > 0.05) & (np.linalg.norm(cam, axis=1) <= max_range_m)
    seen &= (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    if seen.any():
        return np.flatnonzero(seen)
    return np.array([int(np.argmin(np.linalg.norm(cam, axis=1)))])


def error_vectors(
    objects: list, truth: list[ObjectTruth], poses: np.ndarray, K: Intrinsics, width: int, height: int
) -> list[dict[str, Any]]:
    """Per one-to-one match (``match_objects``): the centroid error ``mapped - true`` in the world (``world_m``)
    and, averaged over the camera poses that see the true centre (``viewing_poses``; the nearest pose when none
    does), in their camera frames (``camera_m``: x right, y down, z forward) and split at each view's ray to the
    true centre: ``along_ray_m`` (negative: towards the camera) and ``across_ray_m`` (the mean of the error's
    part across the ray, its length). ``poses`` are camera-to-world in the frame of ``truth``."""
    out = []
    for a, b in match_objects(objects, truth):
        centre = np.asarray(truth[b].center, float)
        e = np.asarray(objects[a].mean, float) - centre
        views = poses[viewing_poses(centre, poses, K, width, height)]
        rays = centre - views[:, :3, 3]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        along = rays @ e
        across = e[None, :] - along[:, None] * rays
        out.append(
            {
                "truth_id": int(truth[b].id),
                "id": int(getattr(objects[a], "id", -1)),
                "label": truth[b].label,
                "error_m": float(np.linalg.norm(e)),
                "world_m": [float(x) for x in e],
                "camera_m": [float(x) for x in np.einsum("nji,j->ni", views[:, :3, :3], e).mean(axis=0)],
                "along_ray_m": float(along.mean()),
                "across_ray_m": float(np.linalg.norm(across.mean(axis=0))),
                "views": len(views),
            }
        )
    return out


def error_summary(errors: list[dict[str, Any]]) -> dict[str, Any]:
    """The common part of per-object error vectors: their mean world vector and camera-frame vector, and the
    median error along the viewing ray (negative: towards the camera)."""
    if not errors:
        return {"mean_world_error_m": None, "mean_camera_error_m": None, "median_along_ray_m": None}
    return {
        "mean_world_error_m": [float(x) for x in np.mean([e["world_m"] for e in errors], axis=0)],
        "mean_camera_error_m": [float(x) for x in np.mean([e["camera_m"] for e in errors], axis=0)],
        "median_along_ray_m": float(np.median([e["along_ray_m"] for e in errors])),
    }
