"""When object observations must be re-placed after the graph moved their keyframes (Sec. 2.4.7)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from graph.geometry import rotation_angles_between
from graph.interface import Graph
from slam.pose_log import PlacedPoses
from slam.settings import ObjectSettings


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
    moved = np.linalg.norm(now[:, :3, 3] - used[:, :3, 3], axis=1).max()
    turned = np.degrees(rotation_angles_between(now[:, :3, :3], used[:, :3, :3])).max()
    if moved <= cfg.repose_m and turned <= cfg.repose_deg:
        return None
    return graph.poses()[:n]
