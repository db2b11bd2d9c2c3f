"""When object observations must be re-placed after the graph moved their keyframes (Sec. 2.4.7)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from graph.geometry import rotation_angles_between
from graph.interface import Graph
from slam.pose_log import PlacedPoses
from slam.settings import ObjectSettings

KEEP_SHARE = 0.1
"""A keyframe that moved less than this share of ``repose_m`` and ``repose_deg`` keeps the pose its observations
were placed with when the others are re-placed (``moved_only``)."""


def repose_due(
    graph: Graph, object_poses: Sequence[np.ndarray] | PlacedPoses, cfg: ObjectSettings
) -> np.ndarray | None:
    """Sec. 2.4.7: after an optimisation the feature vectors are recomputed from the updated poses and the
    objects re-clustered. Due when a keyframe holding object observations (placed with ``object_poses``) has
    moved more than ``repose_m`` or turned more than ``repose_deg`` since (smaller corrections are below the
    objects' own noise, and re-clustering every keyframe costs ~50 ms); then the poses to re-place them with,
    else None.
    """
    n = len(object_poses)
    if n == 0:
        return None
    # at most ~110 keyframes checked (every n/100-th and the last 10): an optimisation that matters moves
    # many keyframes together, and a full estimate per keyframe would grow with the map
    idx = np.unique(np.r_[np.arange(0, n, max(1, n // 100)), np.arange(max(0, n - 10), n)])
    now = np.stack([graph.pose(int(k)) for k in idx])
    used = np.stack([object_poses[k] for k in idx])
    moved, turned = _offsets(now, used)
    if moved.max() <= cfg.repose_m and turned.max() <= cfg.repose_deg:
        return None
    placed = object_poses.rows() if isinstance(object_poses, PlacedPoses) else np.stack(list(object_poses))
    return moved_only(graph.poses()[:n], placed, cfg)


def moved_only(now: np.ndarray, placed: np.ndarray, cfg: ObjectSettings) -> np.ndarray:
    """The poses (n, 4, 4) to re-place object observations with: ``now`` for the keyframes that moved at least
    ``KEEP_SHARE`` of ``repose_m`` or turned that share of ``repose_deg`` since they were ``placed``, the placed
    pose for the others (at most 1 mm and 0.05 degrees off by default, far below the objects' noise). After a
    whole-graph solve nearly every pose changes a little; re-placing them all made the map store write every
    keyframe's pose again (``slam.pose_log.PlacedPoses``), work that grew with the map."""
    if len(now) == 0:
        return now
    moved, turned = _offsets(now, placed)
    keep = (moved < KEEP_SHARE * cfg.repose_m) & (turned < KEEP_SHARE * cfg.repose_deg)
    return np.where(keep[:, None, None], placed, now)


def _offsets(now: np.ndarray, placed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each pose of ``now`` lies from its ``placed`` one: metres and degrees."""
    moved = np.linalg.norm(now[:, :3, 3] - placed[:, :3, 3], axis=1)
    return moved, np.degrees(rotation_angles_between(now[:, :3, :3], placed[:, :3, :3]))
